"""Ensemble bundles: the one artefact training hands to the scoring service.

A bundle is a directory::

    <dir>/manifest.json            what the bundle is, and the sha256 of every weights file
    <dir>/member_<k>.safetensors   state dict of ensemble member k (projection + RSSM + head, ...)
    <dir>/backbone.safetensors     the image backbone, unless it is the pinned pretrained
                                   EfficientNet-Lite0 (identified by the sha256 of its weights)

Why this shape:

* **safetensors, never pickle.** A bundle may come from another machine; ``torch.load`` of a
  pickle runs code. Nothing in this module unpickles anything.
* **Everything checked at load, each failure named.** The service must refuse a bundle that is
  missing a file, corrupt, altered after export, made for another plan contract, or whose weights
  do not fit the configured architecture -- at start-up, with a message naming the file and the
  rule (:class:`BundleError`), not with a shape error deep in the first request.
* **The backbone travels with the bundle when it is not pinned.** Members only hold what sits on
  top of the backbone features. A ``small_cnn`` backbone is trained (or randomly initialised), so
  its weights are part of the model: without them another process would compute other features.
* **Atomic export.** Files are written into a temporary sibling directory which is renamed into
  place, so a reader never sees half a bundle.

The sha256 values protect integrity (a flipped byte, a truncated copy), not authenticity: whoever
can rewrite the manifest can rewrite the hashes too.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from firp.core.bundle_format import BACKBONE_FILE, BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, MANIFEST_NAME, sha256_file
from firp.core.contract import CATEGORIES, CONTRACT_VERSION, FPS, PLAN_WIDTH, T_MAX, T_MIN, PlanLimits
from firp.model.baselines import MODEL_KINDS, build_model
from firp.model.config import EncoderConfig, FIRPConfig
from firp.model.encoder import EFFICIENTNET_LITE0_SHA256, build_backbone

__all__ = [
    "BACKBONE_FILE",
    "BUNDLE_FORMAT",
    "BUNDLE_FORMAT_VERSION",
    "MANIFEST_NAME",
    "Bundle",
    "BundleError",
    "BundleMember",
    "backbone_key",
    "export_bundle",
    "load_bundle",
    "sha256_file",
]

#: Kinds that need frames *after* execution: they cannot score a plan beforehand.
_POST_EXECUTION_KINDS = ("oracle",)


class BundleError(ValueError):
    """A bundle broke a rule. ``path`` is the offending file, ``rule`` the rule's short name:

    ``missing``, ``corrupt``, ``schema``, ``format_version``, ``contract_version``, ``contract``,
    ``sha256``, ``config``, ``state_dict``, ``backbone``.
    """

    def __init__(self, path: str | os.PathLike, rule: str, detail: str):
        self.path = Path(path)
        self.rule = rule
        self.detail = detail
        super().__init__(f"{self.path}: {detail} (rule: {rule})")


@dataclass
class BundleMember:
    """One trained ensemble member as training hands it over."""

    kind: str  # one of firp.model.baselines.MODEL_KINDS (not "oracle")
    config: FIRPConfig
    model: nn.Module
    metrics: dict[str, float] = field(default_factory=dict)  # validation metrics of this member


@dataclass(frozen=True)
class Bundle:
    """A loaded, verified bundle: models in eval mode with gradients off, ready to score."""

    path: Path
    manifest: dict[str, Any]
    kinds: tuple[str, ...]
    configs: tuple[FIRPConfig, ...]
    models: tuple[nn.Module, ...]
    backbone: nn.Module  # the one frozen backbone every member's features come from
    encoder_config: EncoderConfig  # the members' shared encoder settings (backbone, image size)
    threshold: float
    t_range: PlanLimits

    @property
    def name(self) -> str:
        return str(self.manifest["name"])

    @property
    def task(self) -> str:
        return str(self.manifest["task"])


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def backbone_key(cfg: EncoderConfig) -> dict[str, Any]:
    """What determines the backbone's output for an image: members must agree on all of it to
    share one backbone (the projection after it may differ freely)."""
    key: dict[str, Any] = {
        "name": cfg.backbone,
        "image_size": cfg.image_size,
        "normalization": cfg.resolved_normalization,
        "dim": cfg.backbone_dim,
    }
    if cfg.backbone == "small_cnn":
        key["small_cnn_channels"] = list(cfg.small_cnn_channels)
    return key


def _shared_encoder(configs: Sequence[FIRPConfig], where: str | os.PathLike) -> EncoderConfig:
    """The one encoder setting of all members; a :class:`BundleError` if they cannot share one."""
    for k, c in enumerate(configs):
        if not c.encoder.freeze_backbone:
            raise BundleError(where, "backbone", f"member {k} was configured with an unfrozen (per-member trained) "
                              "backbone: a bundle holds one frozen backbone shared by all members")
    keys = [backbone_key(c.encoder) for c in configs]
    for k, key in enumerate(keys[1:], start=1):
        if key != keys[0]:
            raise BundleError(where, "backbone", f"member {k} uses backbone {key}, member 0 uses {keys[0]}: "
                              "an ensemble shares one backbone and image size")
    return configs[0].encoder


def _cpu_state(module: nn.Module) -> dict[str, Tensor]:
    # safetensors refuses shared or non-contiguous storage; clone() gives every tensor its own.
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in module.state_dict().items()}


def _finite_number(name: str, value: object) -> int | float:
    """``value`` as a JSON number (ints stay ints: ``n_val`` is a count); NaN/inf are refused, as
    JSON has no spelling for them and a NaN metric would only hide a failed evaluation."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return int(value) if isinstance(value, int) else float(value)


def _json_metrics(name: str, metrics: Mapping[str, object]) -> dict[str, int | float]:
    return {str(k): _finite_number(f"{name}[{k!r}]", v) for k, v in metrics.items()}


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_safetensors(path: Path, tensors: dict[str, Tensor], metadata: dict[str, str]) -> str:
    save_file(tensors, str(path), metadata=metadata)
    with open(path, "rb+") as f:
        os.fsync(f.fileno())
    return sha256_file(path)


# --------------------------------------------------------------------------------------------
# export
# --------------------------------------------------------------------------------------------


def export_bundle(
    out_dir: str | os.PathLike,
    members: Sequence[BundleMember],
    *,
    name: str,
    task: str,
    threshold: float,
    calibration: Mapping[str, object],
    metrics: Mapping[str, object],
    training_data_hash: str,
    training_data_path: str | os.PathLike,
    t_range: tuple[int, int] | PlanLimits,
    backbone: nn.Module | None = None,
    extra: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write an ensemble bundle to ``out_dir`` and return its path.

    ``calibration`` holds at least ``ece`` and ``n_val`` (and may hold ``n_bins``); ``metrics`` are
    the ensemble's validation metrics (each member carries its own). The image size and backbone
    are read from the members' configs, which must agree on them. ``backbone`` is the module whose
    features the members were trained on: required (and embedded) unless the members use the
    pinned pretrained EfficientNet-Lite0, whose weights are identified by their sha256 instead.
    ``t_range`` is the range of plan lengths the members were trained and validated on; plans
    outside it are rejected at scoring time.

    Nothing is visible at ``out_dir`` until everything is written: the bundle is built in a
    temporary sibling directory and renamed. ``overwrite=True`` replaces an existing bundle (two
    renames: the old one is moved aside first, then removed).
    """
    out = Path(out_dir)
    if not members:
        raise ValueError("a bundle needs at least one member")
    for k, m in enumerate(members):
        if m.kind not in MODEL_KINDS:
            raise ValueError(f"member {k}: unknown kind {m.kind!r}; one of {MODEL_KINDS}")
        if m.kind in _POST_EXECUTION_KINDS:
            raise ValueError(f"member {k}: kind {m.kind!r} needs the executed frames and cannot score a plan "
                             "beforehand")
        if getattr(m.model, "cfg", m.config) != m.config:
            raise ValueError(f"member {k}: the model was built with another config than the one given")
        # Refuse now what load_bundle would refuse later (e.g. a model of another kind).
        problem = _state_mismatch(build_model(m.kind, m.config), m.model.state_dict())
        if problem:
            raise ValueError(f"member {k}: its weights do not fit a {m.kind!r} model of its config: {problem}")
    limits = t_range if isinstance(t_range, PlanLimits) else PlanLimits(*map(int, t_range))
    if not T_MIN <= limits.t_min <= limits.t_max <= T_MAX:
        raise ValueError(f"t_range must satisfy {T_MIN} <= t_min <= t_max <= {T_MAX}, got {limits}")
    for k, m in enumerate(members):
        b = m.config.baseline
        if m.kind in ("a_mlp", "a_mlp_image") and b.plan_pooling == "flatten" and limits.t_max > b.max_T:
            raise ValueError(f"member {k} ({m.kind}) flattens at most max_T={b.max_T} steps < t_max={limits.t_max}")
    threshold = float(_finite_number("threshold", threshold))
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"threshold is a probability and must lie in [0, 1], got {threshold}")
    if "ece" not in calibration or "n_val" not in calibration:
        raise ValueError("calibration needs 'ece' and 'n_val'")
    calib = _json_metrics("calibration", calibration)
    enc = _shared_encoder([m.config for m in members], out)
    pinned = enc.backbone == "efficientnet_lite0" and enc.weights_path is None
    if backbone is None and not pinned:
        raise ValueError(
            f"backbone {enc.backbone!r} (weights_path={enc.weights_path!r}) is not the pinned pretrained "
            "EfficientNet-Lite0: pass backbone= so that its weights are embedded in the bundle"
        )
    if backbone is not None:
        problem = _state_mismatch(build_backbone(dataclasses.replace(enc, weights_path=None)), backbone.state_dict())
        if problem:
            raise ValueError(f"backbone does not fit the members' {enc.backbone!r} config: {problem}")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists (pass overwrite=True to replace it)")

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        member_entries = []
        for k, m in enumerate(members):
            file = f"member_{k}.safetensors"
            digest = _write_safetensors(tmp / file, _cpu_state(m.model), {"kind": m.kind, "format": "pt"})
            member_entries.append({
                "kind": m.kind,
                "config": m.config.to_dict(),
                "file": file,
                "sha256": digest,
                "validation": _json_metrics(f"member {k} metrics", m.metrics),
            })
        backbone_entry: dict[str, Any] = backbone_key(enc)
        if backbone is not None:
            backbone_entry["file"] = BACKBONE_FILE
            backbone_entry["sha256"] = _write_safetensors(tmp / BACKBONE_FILE, _cpu_state(backbone),
                                                          {"backbone": enc.backbone, "format": "pt"})
        else:
            backbone_entry["file"] = None
            backbone_entry["pretrained_weights_sha256"] = EFFICIENTNET_LITE0_SHA256
        manifest = {
            "format": BUNDLE_FORMAT,
            "format_version": BUNDLE_FORMAT_VERSION,
            "contract_version": CONTRACT_VERSION,
            "name": str(name),
            "task": str(task),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "plan": {"width": PLAN_WIDTH, "categories": list(CATEGORIES), "fps": FPS},
            "t_range": {"t_min": limits.t_min, "t_max": limits.t_max},
            "image_size": enc.image_size,
            "backbone": backbone_entry,
            "members": member_entries,
            "threshold": threshold,
            "calibration": calib,
            "validation": _json_metrics("metrics", metrics),
            "training_data": {"sha256": str(training_data_hash), "path": os.fspath(training_data_path)},
            "extra": dict(extra or {}),
        }
        with open(tmp / MANIFEST_NAME, "w", encoding="utf-8") as f:
            json.dump(manifest, f, indent=2, allow_nan=False)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700; a bundle is meant to be read by a service user
        _fsync_dir(tmp)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.rename(out, old / out.name)
            os.rename(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
        _fsync_dir(out.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


# --------------------------------------------------------------------------------------------
# load
# --------------------------------------------------------------------------------------------


def _require(manifest: Mapping[str, Any], key: str, kind: type | tuple[type, ...], where: Path) -> Any:
    if key not in manifest:
        raise BundleError(where, "schema", f"manifest has no {key!r} field")
    value = manifest[key]
    if not isinstance(value, kind) or isinstance(value, bool):  # JSON true is not a number here
        raise BundleError(where, "schema", f"manifest field {key!r} has the wrong type {type(value).__name__}")
    return value


def _weights_file(root: Path, entry: Mapping[str, Any], what: str, manifest_path: Path) -> Path:
    """Resolve and verify one weights file: a plain name inside the bundle, present, hash equal."""
    file = entry.get("file")
    digest = entry.get("sha256")
    if not isinstance(file, str) or not isinstance(digest, str):
        raise BundleError(manifest_path, "schema", f"{what} needs string fields 'file' and 'sha256'")
    if Path(file).name != file or file in ("", ".", ".."):
        raise BundleError(manifest_path, "schema", f"{what} file {file!r} must be a plain file name inside the bundle")
    path = root / file
    if not path.is_file():
        raise BundleError(path, "missing", f"{what} weights file is missing")
    actual = sha256_file(path)
    if actual != digest:
        raise BundleError(path, "sha256", f"{what} weights file was modified: sha256 {actual} != manifest {digest}")
    return path


def _read_state(path: Path, what: str) -> dict[str, Tensor]:
    try:
        return load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise BundleError(path, "corrupt", f"{what} is not a readable safetensors file ({exc})") from None


def _state_mismatch(module: nn.Module, state: Mapping[str, Tensor]) -> str | None:
    """Every difference between ``state`` and ``module.state_dict()`` by name, or None."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [
        f"{k}: {tuple(state[k].shape)} {state[k].dtype} != {tuple(expected[k].shape)} {expected[k].dtype}"
        for k in sorted(set(expected) & set(state))
        if state[k].shape != expected[k].shape or state[k].dtype != expected[k].dtype
    ]
    parts = []
    if missing:
        parts.append(f"missing keys {missing}")
    if unexpected:
        parts.append(f"unexpected keys {unexpected}")
    if wrong:
        parts.append(f"wrong shapes/dtypes {wrong}")
    return "; ".join(parts) or None


def _load_strict(module: nn.Module, state: Mapping[str, Tensor], path: Path, what: str) -> None:
    """``load_state_dict(strict=True)``, but a mismatch is a :class:`BundleError` listing it by name."""
    problem = _state_mismatch(module, state)
    if problem:
        raise BundleError(path, "state_dict", f"{what} does not fit the architecture of its config: {problem}")
    module.load_state_dict(state, strict=True)


def _frozen(module: nn.Module) -> nn.Module:
    module.eval()
    module.requires_grad_(False)
    return module


def load_bundle(bundle_dir: str | os.PathLike) -> Bundle:
    """Read and verify a bundle; raise :class:`BundleError` naming the file and the rule broken.

    Checks, in order: the manifest exists and is JSON with the expected fields; the format version
    and ``CONTRACT_VERSION`` equal this code's (and so do the plan width and category list); the
    plan length range lies inside the contract's; every weights file is a plain name inside the
    bundle, exists, and has the sha256 the manifest records; it parses as safetensors; its state
    dict fits, key by key and shape by shape, the model built from its config. Models come back in
    eval mode with gradients off.
    """
    root = Path(bundle_dir)
    mpath = root / MANIFEST_NAME
    if not root.is_dir():
        raise BundleError(root, "missing", "bundle directory does not exist")
    if not mpath.is_file():
        raise BundleError(mpath, "missing", "bundle has no manifest")
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(mpath, "corrupt", f"manifest is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise BundleError(mpath, "schema", "manifest must be a JSON object")

    if manifest.get("format") != BUNDLE_FORMAT:
        raise BundleError(mpath, "schema", f"not a {BUNDLE_FORMAT} manifest (format={manifest.get('format')!r})")
    version = manifest.get("format_version")
    if version != BUNDLE_FORMAT_VERSION:
        raise BundleError(mpath, "format_version",
                          f"bundle format version {version!r} is incompatible with this code's {BUNDLE_FORMAT_VERSION}")
    contract = manifest.get("contract_version")
    if contract != CONTRACT_VERSION:
        raise BundleError(mpath, "contract_version",
                          f"bundle was made for plan contract {contract!r}, this code implements {CONTRACT_VERSION!r}")
    plan = _require(manifest, "plan", dict, mpath)
    if plan.get("width") != PLAN_WIDTH or plan.get("categories") != list(CATEGORIES):
        raise BundleError(mpath, "contract", f"bundle's plan layout (width {plan.get('width')}, categories "
                          f"{plan.get('categories')}) differs from the contract's ({PLAN_WIDTH}, {list(CATEGORIES)})")
    for key, kind in (("name", str), ("task", str), ("threshold", (int, float)), ("members", list),
                      ("t_range", dict), ("backbone", dict), ("image_size", int)):
        _require(manifest, key, kind, mpath)
    t_range = manifest["t_range"]
    try:
        limits = PlanLimits(int(t_range["t_min"]), int(t_range["t_max"]))
    except (KeyError, TypeError, ValueError):
        raise BundleError(mpath, "schema", f"t_range must be {{'t_min': int, 't_max': int}}, got {t_range!r}") from None
    if not T_MIN <= limits.t_min <= limits.t_max <= T_MAX:
        raise BundleError(mpath, "contract", f"t_range {limits} lies outside the contract's [{T_MIN}, {T_MAX}]")
    threshold = float(manifest["threshold"])
    if not 0.0 <= threshold <= 1.0:
        raise BundleError(mpath, "schema", f"threshold must lie in [0, 1], got {threshold}")
    entries = manifest["members"]
    if not entries:
        raise BundleError(mpath, "schema", "bundle has no members")

    kinds: list[str] = []
    configs: list[FIRPConfig] = []
    models: list[nn.Module] = []
    for k, entry in enumerate(entries):
        what = f"member {k}"
        if not isinstance(entry, dict):
            raise BundleError(mpath, "schema", f"{what} must be a JSON object")
        kind = entry.get("kind")
        if kind not in MODEL_KINDS or kind in _POST_EXECUTION_KINDS:
            raise BundleError(mpath, "config", f"{what} has kind {kind!r}; a bundle member is one of "
                              f"{[m for m in MODEL_KINDS if m not in _POST_EXECUTION_KINDS]}")
        try:
            cfg = FIRPConfig.from_dict(entry.get("config"))
        except (TypeError, ValueError, AttributeError) as exc:
            raise BundleError(mpath, "config", f"{what} config is invalid ({exc})") from None
        path = _weights_file(root, entry, what, mpath)
        state = _read_state(path, what)
        model = build_model(kind, cfg)
        _load_strict(model, state, path, what)
        kinds.append(kind)
        configs.append(cfg)
        models.append(_frozen(model))

    enc = _shared_encoder(configs, mpath)
    if manifest["image_size"] != enc.image_size:
        raise BundleError(mpath, "backbone", f"image_size {manifest['image_size']} != members' {enc.image_size}")
    backbone_entry = manifest["backbone"]
    declared = {k: backbone_entry.get(k) for k in backbone_key(enc)}
    if declared != backbone_key(enc):
        raise BundleError(mpath, "backbone", f"manifest backbone {declared} != members' {backbone_key(enc)}")
    if backbone_entry.get("file") is None:
        if not (enc.backbone == "efficientnet_lite0"
                and backbone_entry.get("pretrained_weights_sha256") == EFFICIENTNET_LITE0_SHA256):
            raise BundleError(mpath, "backbone", "the backbone is neither embedded nor the pinned pretrained "
                              f"EfficientNet-Lite0 (sha256 {EFFICIENTNET_LITE0_SHA256})")
        # The members' configs may carry a machine-specific weights_path only if it is embedded.
        backbone = build_backbone(dataclasses.replace(enc, weights_path=None))
    else:
        path = _weights_file(root, backbone_entry, "backbone", mpath)
        state = _read_state(path, "backbone")
        # Built without the training machine's weights_path: the embedded weights replace them.
        backbone = build_backbone(dataclasses.replace(enc, weights_path=None))
        _load_strict(backbone, state, path, "backbone")

    return Bundle(
        path=root,
        manifest=manifest,
        kinds=tuple(kinds),
        configs=tuple(configs),
        models=tuple(models),
        backbone=_frozen(backbone),
        encoder_config=enc,
        threshold=threshold,
        t_range=limits,
    )
