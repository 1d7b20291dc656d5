"""Writing a bundle: members' weights as safetensors, the manifest with their hashes, atomically."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from safetensors.torch import save_file
from torch import Tensor, nn

from firp.bundle.types import POST_EXECUTION_KINDS, BundleMember, backbone_key, shared_encoder, state_mismatch
from firp.core.bundle_format import BACKBONE_FILE, BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, MANIFEST_NAME, sha256_file
from firp.core.contract import CATEGORIES, CONTRACT_VERSION, FPS, PLAN_WIDTH, T_MAX, T_MIN, PlanLimits
from firp.core.decisions import EVIDENCE_KEY
from firp.model.baselines import MODEL_KINDS, build_model
from firp.model.encoder import EFFICIENTNET_LITE0_SHA256, build_backbone

__all__ = ["export_bundle"]


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


def write_manifest(path: Path, manifest: Mapping[str, Any]) -> None:
    """``manifest.json`` as every bundle has it (indented JSON, no NaN), written beside ``path``, fsynced and
    renamed over it: a reader sees the old manifest or the new one, never half of one."""
    fd, tmp = tempfile.mkstemp(prefix=".manifest-", suffix=".json", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(manifest, f, indent=2, allow_nan=False)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; a bundle is meant to be read by a service user
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


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
    evidence: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write an ensemble bundle to ``out_dir`` and return its path.

    ``calibration`` holds at least ``ece`` and ``n_val`` (and may hold ``n_bins``); ``metrics`` are
    the ensemble's validation metrics (each member carries its own). The image size and backbone
    are read from the members' configs, which must agree on them. ``backbone`` is the module whose
    features the members were trained on: required (and embedded) unless the members use the
    pinned pretrained EfficientNet-Lite0, whose weights are identified by their sha256 instead.
    ``t_range`` is the range of plan lengths the members were trained and validated on; plans
    outside it are rejected at scoring time. ``evidence`` (:func:`firp.core.decisions.decision_evidence`)
    is the ensemble's validation balanced accuracy with its interval and the failures' scores, which the
    service reports and the planner client's decisions rest on.

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
        if m.kind in POST_EXECUTION_KINDS:
            raise ValueError(f"member {k}: kind {m.kind!r} needs the executed frames and cannot score a plan "
                             "beforehand")
        if getattr(m.model, "cfg", m.config) != m.config:
            raise ValueError(f"member {k}: the model was built with another config than the one given")
        # Refuse now what load_bundle would refuse later (e.g. a model of another kind).
        problem = state_mismatch(build_model(m.kind, m.config), m.model.state_dict())
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
    enc = shared_encoder([m.config for m in members], out)
    pinned = enc.backbone == "efficientnet_lite0" and enc.weights_path is None
    if backbone is None and not pinned:
        raise ValueError(
            f"backbone {enc.backbone!r} (weights_path={enc.weights_path!r}) is not the pinned pretrained "
            "EfficientNet-Lite0: pass backbone= so that its weights are embedded in the bundle"
        )
    if backbone is not None:
        problem = state_mismatch(build_backbone(dataclasses.replace(enc, weights_path=None)), backbone.state_dict())
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
        if evidence is not None:  # firp.core.decisions.decision_evidence: what decisions on the scores may rest on
            manifest[EVIDENCE_KEY] = dict(evidence)
        write_manifest(tmp / MANIFEST_NAME, manifest)
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
