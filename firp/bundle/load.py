"""Loading a bundle: every file checked against the manifest, every rule broken named (:class:`BundleError`)."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from safetensors import SafetensorError
from safetensors.torch import load_file
from torch import Tensor, nn

from firp.bundle.types import POST_EXECUTION_KINDS, Bundle, BundleError, backbone_key, shared_encoder, state_mismatch
from firp.core.bundle_format import BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, MANIFEST_NAME, sha256_file
from firp.core.contract import CATEGORIES, CONTRACT_VERSION, PLAN_WIDTH, T_MAX, T_MIN, PlanLimits
from firp.model.baselines import MODEL_KINDS, build_model
from firp.model.config import FIRPConfig
from firp.model.encoder import EFFICIENTNET_LITE0_SHA256, build_backbone

__all__ = ["load_bundle"]


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


def _load_strict(module: nn.Module, state: Mapping[str, Tensor], path: Path, what: str) -> None:
    """``load_state_dict(strict=True)``, but a mismatch is a :class:`BundleError` listing it by name."""
    problem = state_mismatch(module, state)
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
        if kind not in MODEL_KINDS or kind in POST_EXECUTION_KINDS:
            raise BundleError(mpath, "config", f"{what} has kind {kind!r}; a bundle member is one of "
                              f"{[m for m in MODEL_KINDS if m not in POST_EXECUTION_KINDS]}")
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

    enc = shared_encoder(configs, mpath)
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
