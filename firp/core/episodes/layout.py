"""The episode format: names, attribute encoding, the record type and its validation."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import h5py
import numpy as np

from firp.core.contract import CATEGORIES, CONTRACT_VERSION, PlanLimits, validate_plan

AttrValue = Union[str, int, float, bool, list, dict]

#: The robomimic observation key of the camera frames.
IMAGE_KEY = "agentview_image"
#: The observation key of the initial image at the view's (higher) resolution, ``(1, H, W, 3)``: what the
#: plan-conditioned view reads, through the dataset's ``camera_calibration`` (optional).
VIEW_KEY = "view_image"
#: The observation key of the settled final scene at the view's resolution, ``(1, H, W, 3)``: what only an
#: Oracle may read (it shows the outcome), optional.
FINAL_VIEW_KEY = "final_view_image"
#: Attribute listing which attributes of an object hold JSON-encoded containers.
JSON_ATTRS_KEY = "_json_attrs"
#: Per-demo attributes written by this module; a record's own attrs may not use these names.
RESERVED_DEMO_ATTRS = frozenset({"num_samples", "success", JSON_ATTRS_KEY})
#: ``data`` group attributes computed by :func:`consolidate` (not compared between runs).
COMPUTED_DATA_ATTRS = frozenset({"total", "num_demos", JSON_ATTRS_KEY})

PART_RE = re.compile(r"^demo_(\d+)\.h5$")
DEMO_RE = re.compile(r"^demo_(\d+)$")
# Temp files are ".<final name>.<writer pid>.<random>.tmp": the pid lets a later run tell a temp
# file left by a killed writer (stale, removed) from one a live writer is still filling (kept).
TMP_RE = re.compile(r"^\.(?P<final>.+)\.(?P<pid>\d+)\.[0-9a-f]+\.tmp$")
GZIP_LEVEL = 4
HASH_BLOCK_FRAMES = 32


class EpisodeValidationError(ValueError):
    """An episode or dataset broke a rule of this module; the message says which and why."""


@dataclass
class EpisodeRecord:
    """One episode: what the camera saw, the plan that was executed, the sim states and the label.

    ``frames`` uint8 ``(T, H, W, 3)``, or ``(1, H, W, 3)`` for an episode that kept only its initial image
    (cheap to collect: enough to train what classifies from the initial image, not the RSSM's
    prediction terms); ``actions`` float32 ``(T, 16)`` (a contract plan); ``states`` float64 ``(T, S)``
    (MuJoCo qpos/qvel etc., for replay); ``success`` the label the model learns; ``attrs`` metadata
    (task, seed, block order, pose estimates, ...); ``view`` optionally the initial image at a higher
    resolution, uint8 ``(1, H', W', 3)``; ``final_view`` optionally the settled final scene at that resolution
    (what an Oracle reads).
    """

    frames: np.ndarray
    actions: np.ndarray
    states: np.ndarray
    success: bool
    attrs: dict[str, AttrValue] = field(default_factory=dict)
    view: np.ndarray | None = None
    final_view: np.ndarray | None = None

    @property
    def num_samples(self) -> int:
        """Number of time steps ``T``."""
        return int(np.shape(self.actions)[0])


# --------------------------------------------------------------------------------------------
# Names
# --------------------------------------------------------------------------------------------


def demo_name(index: int) -> str:
    """The robomimic group name of episode ``index`` (``demo_<index>``, no zero padding)."""
    return f"demo_{check_index(index)}"


def part_path(parts_dir: str | os.PathLike[str], index: int) -> Path:
    """Where episode ``index``'s part file lives (zero-padded so a directory listing sorts)."""
    return Path(parts_dir) / f"demo_{check_index(index):06d}.h5"


def check_index(index: int) -> int:
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
        raise EpisodeValidationError(f"episode index must be a non-negative int, got {index!r}")
    return int(index)


def demo_index(name: str) -> int:
    match = DEMO_RE.match(name)
    if match is None:
        raise EpisodeValidationError(f"not a demo group name: {name!r} (expected demo_<int>)")
    return int(match.group(1))


# --------------------------------------------------------------------------------------------
# Attributes
# --------------------------------------------------------------------------------------------


def to_jsonable(value: Any) -> Any:
    """numpy scalars/arrays and tuples to plain JSON types (json.dumps cannot take numpy)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    return value


def normalize_attr(key: str, value: Any) -> Any:
    """The value as it will read back: what :func:`consolidate` compares between runs."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, str):
        return value
    try:
        return json.loads(json.dumps(to_jsonable(value), allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise EpisodeValidationError(
            f"attribute {key!r}: {type(value).__name__} cannot be stored (str, int, float, bool or "
            f"JSON-able lists/dicts only): {exc}"
        ) from None


def write_attrs(obj: h5py.HLObject, attrs: Mapping[str, Any]) -> None:
    """Store ``attrs`` on an HDF5 object, JSON-encoding containers and recording which were."""
    json_keys: list[str] = list(decode_json_keys(obj.attrs))
    for key, value in attrs.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise EpisodeValidationError(f"attribute names must be non-empty str without '/', got {key!r}")
        if key == JSON_ATTRS_KEY:
            raise EpisodeValidationError(f"attribute name {JSON_ATTRS_KEY!r} is reserved")
        if key in json_keys:
            json_keys.remove(key)
        if isinstance(value, (bool, np.bool_)):
            obj.attrs[key] = np.bool_(value)
        elif isinstance(value, (int, np.integer)):
            obj.attrs[key] = np.int64(value)
        elif isinstance(value, (float, np.floating)):
            obj.attrs[key] = np.float64(value)
        elif isinstance(value, str):
            obj.attrs[key] = value
        else:
            obj.attrs[key] = json.dumps(normalize_attr(key, value), allow_nan=False)
            json_keys.append(key)
    if json_keys:
        obj.attrs[JSON_ATTRS_KEY] = json.dumps(sorted(set(json_keys)))
    elif JSON_ATTRS_KEY in obj.attrs:
        del obj.attrs[JSON_ATTRS_KEY]


def decode_json_keys(h5attrs: h5py.AttributeManager) -> set[str]:
    raw = h5attrs.get(JSON_ATTRS_KEY)
    if raw is None:
        return set()
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8")
    return set(json.loads(raw))


def read_attrs(obj: h5py.HLObject, exclude: frozenset[str] = frozenset()) -> dict[str, Any]:
    """Decode an HDF5 object's attributes back into plain Python values."""
    json_keys = decode_json_keys(obj.attrs)
    out: dict[str, Any] = {}
    for key, value in obj.attrs.items():
        if key == JSON_ATTRS_KEY or key in exclude:
            continue
        if isinstance(value, bytes):
            value = value.decode("utf-8")
        if key in json_keys and isinstance(value, str):
            out[key] = json.loads(value)
        elif isinstance(value, np.bool_):
            out[key] = bool(value)
        elif isinstance(value, np.integer):
            out[key] = int(value)
        elif isinstance(value, np.floating):
            out[key] = float(value)
        elif isinstance(value, np.ndarray):  # attributes from foreign (robomimic) files
            out[key] = value.tolist()
        else:
            out[key] = value
    return out


def full_dataset_attrs(dataset_attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Caller's dataset attrs plus the contract facts every dataset must carry, normalized."""
    attrs = {key: normalize_attr(key, value) for key, value in dataset_attrs.items()}
    for key in COMPUTED_DATA_ATTRS:
        if key in attrs:
            raise EpisodeValidationError(f"dataset attribute {key!r} is computed by consolidate(); don't pass it")
    fixed = {"categories": list(CATEGORIES), "contract_version": CONTRACT_VERSION}
    for key, value in fixed.items():
        if key in attrs and attrs[key] != value:
            raise EpisodeValidationError(
                f"dataset attribute {key!r}={attrs[key]!r} contradicts firp.core.contract ({value!r})"
            )
        attrs[key] = value
    return attrs


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def validate_record(record: EpisodeRecord, limits: PlanLimits = PlanLimits()) -> EpisodeRecord:
    """Check an episode before it is written and return a normalized copy (dtypes, plain attrs).

    Actions must pass :func:`firp.core.contract.validate_plan` (raises its ``PlanValidationError``
    with field ``actions``); frames must be uint8 ``(T, H, W, 3)``; states ``(T, S)``; all three
    must agree on ``T``. Anything else raises :class:`EpisodeValidationError` saying what.
    """
    actions = validate_plan(record.actions, limits, field="actions").astype(np.float32)
    t = actions.shape[0]

    frames = np.asarray(record.frames)
    if frames.dtype != np.uint8:
        raise EpisodeValidationError(f"frames must be uint8 (0..255 RGB), got dtype {frames.dtype}")
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise EpisodeValidationError(f"frames must be (T, H, W, 3) RGB, got shape {frames.shape}")
    if frames.shape[1] == 0 or frames.shape[2] == 0:
        raise EpisodeValidationError(f"frames must have a non-empty image, got shape {frames.shape}")

    states = np.asarray(record.states)
    if states.ndim != 2:
        raise EpisodeValidationError(f"states must be 2-D (T, S), got shape {states.shape}")
    try:
        states = states.astype(np.float64, casting="same_kind")
    except TypeError:
        raise EpisodeValidationError(f"states must be numeric, got dtype {states.dtype}") from None

    if not t == states.shape[0] or frames.shape[0] not in (1, t):
        raise EpisodeValidationError(
            f"T must agree: frames have {frames.shape[0]} steps (T, or 1: the initial image only), actions {t}, "
            f"states {states.shape[0]}"
        )
    view, final_view = (_one_image(name, image) for name, image in (("view", record.view),
                                                                        ("final_view", record.final_view)))
    if not isinstance(record.success, (bool, np.bool_)):
        raise EpisodeValidationError(f"success must be a bool, got {type(record.success).__name__}")

    attrs: dict[str, Any] = {}
    for key, value in record.attrs.items():
        if key in RESERVED_DEMO_ATTRS:
            raise EpisodeValidationError(f"episode attribute {key!r} is reserved (written by this module)")
        if not isinstance(key, str) or not key or "/" in key:
            raise EpisodeValidationError(f"attribute names must be non-empty str without '/', got {key!r}")
        attrs[key] = normalize_attr(key, value)
    return EpisodeRecord(frames=frames, actions=actions, states=states, success=bool(record.success), attrs=attrs,
                         view=view, final_view=final_view)


def _one_image(name: str, image: np.ndarray | None) -> np.ndarray | None:
    """An optional single image as ``(1, H, W, 3)`` uint8, or the rule it breaks."""
    if image is None:
        return None
    image = np.asarray(image)
    if image.ndim == 3:
        image = image[None]
    if image.dtype != np.uint8 or image.ndim != 4 or image.shape[0] != 1 or image.shape[-1] != 3 or 0 in image.shape:
        raise EpisodeValidationError(f"{name} must be one uint8 RGB image (1, H, W, 3), got {image.dtype} {image.shape}")
    return image


