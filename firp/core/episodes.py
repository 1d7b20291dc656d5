"""Episode datasets: robomimic/MimicGen-style HDF5 files, written crash-safely. h5py + numpy only.

Why this shape:

* The sim worker collects episodes in several processes at once, and a collection run of hours can
  be killed at any moment. So each worker writes **one file per episode** (a *part*) under a parts
  directory, atomically: to a temp name in the same directory, fsync, then ``os.replace``. A part
  file that has its final name is therefore always complete, and no file handle is ever shared
  between processes.
* :func:`consolidate` then builds the one dataset file the trainer reads, again into a temp file
  that is ``os.replace``-d over the output, so the dataset file is never half-written either. An
  existing dataset (a previous run that asked for fewer episodes) is carried over, so a run can be
  extended or resumed: :func:`completed_indices` tells the collector which episodes exist already.
* The layout follows robomimic (``data/demo_<i>/obs/agentview_image``, ``data/demo_<i>/actions``,
  ``data/demo_<i>/states``, ``data.attrs["total"]``), so the usual robomimic/MimicGen tools and
  habits apply. The per-demo label is ``attrs["success"]``.
* Actions are plans in the sense of :mod:`firp.core.contract` and are validated with its one validator
  before anything is written, so a dataset can never hold an action the service would reject.

Attribute values may be ``str``, ``int``, ``float``, ``bool`` or JSON-able containers (lists,
dicts, tuples, ``None``, numpy arrays). Containers are stored as JSON strings (HDF5 attributes hold
no nested structures) and their names listed in the ``_json_attrs`` attribute, so reading decodes
exactly those and a plain string that happens to look like JSON stays a string.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import h5py
import numpy as np

from firp.core.contract import CATEGORIES, CONTRACT_VERSION, PlanLimits, validate_plan

__all__ = [
    "AttrValue",
    "ConsolidationResult",
    "EpisodeDataset",
    "EpisodeRecord",
    "EpisodeValidationError",
    "IMAGE_KEY",
    "completed_indices",
    "completed_part_indices",
    "consolidate",
    "demo_name",
    "part_path",
    "validate_record",
    "write_episode_part",
]

AttrValue = Union[str, int, float, bool, list, dict]

#: The robomimic observation key of the camera frames.
IMAGE_KEY = "agentview_image"
#: Attribute listing which attributes of an object hold JSON-encoded containers.
JSON_ATTRS_KEY = "_json_attrs"
#: Per-demo attributes written by this module; a record's own attrs may not use these names.
RESERVED_DEMO_ATTRS = frozenset({"num_samples", "success", JSON_ATTRS_KEY})
#: ``data`` group attributes computed by :func:`consolidate` (not compared between runs).
COMPUTED_DATA_ATTRS = frozenset({"total", "num_demos", JSON_ATTRS_KEY})

_PART_RE = re.compile(r"^demo_(\d+)\.h5$")
_DEMO_RE = re.compile(r"^demo_(\d+)$")
# Temp files are ".<final name>.<writer pid>.<random>.tmp": the pid lets a later run tell a temp
# file left by a killed writer (stale, removed) from one a live writer is still filling (kept).
_TMP_RE = re.compile(r"^\.(?P<final>.+)\.(?P<pid>\d+)\.[0-9a-f]+\.tmp$")
_GZIP_LEVEL = 4
_HASH_BLOCK_FRAMES = 32


class EpisodeValidationError(ValueError):
    """An episode or dataset broke a rule of this module; the message says which and why."""


@dataclass
class EpisodeRecord:
    """One episode: what the camera saw, the plan that was executed, the sim states and the label.

    ``frames`` uint8 ``(T, H, W, 3)``; ``actions`` float32 ``(T, 16)`` (a contract plan);
    ``states`` float64 ``(T, S)`` (MuJoCo qpos/qvel etc., for replay); ``success`` the label the
    model learns; ``attrs`` metadata (task, seed, block order, pose estimates, ...).
    """

    frames: np.ndarray
    actions: np.ndarray
    states: np.ndarray
    success: bool
    attrs: dict[str, AttrValue] = field(default_factory=dict)

    @property
    def num_samples(self) -> int:
        """Number of time steps ``T``."""
        return int(np.shape(self.actions)[0])


@dataclass(frozen=True)
class ConsolidationResult:
    """What :func:`consolidate` did, for logs and for the caller's resume bookkeeping."""

    out_path: Path
    num_demos: int
    added: tuple[int, ...]
    carried_over: tuple[int, ...]
    skipped_duplicates: tuple[int, ...]
    rewritten: bool


# --------------------------------------------------------------------------------------------
# Names
# --------------------------------------------------------------------------------------------


def demo_name(index: int) -> str:
    """The robomimic group name of episode ``index`` (``demo_<index>``, no zero padding)."""
    return f"demo_{_check_index(index)}"


def part_path(parts_dir: str | os.PathLike[str], index: int) -> Path:
    """Where episode ``index``'s part file lives (zero-padded so a directory listing sorts)."""
    return Path(parts_dir) / f"demo_{_check_index(index):06d}.h5"


def _check_index(index: int) -> int:
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
        raise EpisodeValidationError(f"episode index must be a non-negative int, got {index!r}")
    return int(index)


def _demo_index(name: str) -> int:
    match = _DEMO_RE.match(name)
    if match is None:
        raise EpisodeValidationError(f"not a demo group name: {name!r} (expected demo_<int>)")
    return int(match.group(1))


# --------------------------------------------------------------------------------------------
# Attributes
# --------------------------------------------------------------------------------------------


def _to_jsonable(value: Any) -> Any:
    """numpy scalars/arrays and tuples to plain JSON types (json.dumps cannot take numpy)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_jsonable(v) for v in value]
    return value


def _normalize_attr(key: str, value: Any) -> Any:
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
        return json.loads(json.dumps(_to_jsonable(value), allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise EpisodeValidationError(
            f"attribute {key!r}: {type(value).__name__} cannot be stored (str, int, float, bool or "
            f"JSON-able lists/dicts only): {exc}"
        ) from None


def _write_attrs(obj: h5py.HLObject, attrs: Mapping[str, Any]) -> None:
    """Store ``attrs`` on an HDF5 object, JSON-encoding containers and recording which were."""
    json_keys: list[str] = list(_decode_json_keys(obj.attrs))
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
            obj.attrs[key] = json.dumps(_normalize_attr(key, value), allow_nan=False)
            json_keys.append(key)
    if json_keys:
        obj.attrs[JSON_ATTRS_KEY] = json.dumps(sorted(set(json_keys)))
    elif JSON_ATTRS_KEY in obj.attrs:
        del obj.attrs[JSON_ATTRS_KEY]


def _decode_json_keys(h5attrs: h5py.AttributeManager) -> set[str]:
    raw = h5attrs.get(JSON_ATTRS_KEY)
    if raw is None:
        return set()
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8")
    return set(json.loads(raw))


def _read_attrs(obj: h5py.HLObject, exclude: frozenset[str] = frozenset()) -> dict[str, Any]:
    """Decode an HDF5 object's attributes back into plain Python values."""
    json_keys = _decode_json_keys(obj.attrs)
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


def _full_dataset_attrs(dataset_attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Caller's dataset attrs plus the contract facts every dataset must carry, normalized."""
    attrs = {key: _normalize_attr(key, value) for key, value in dataset_attrs.items()}
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

    if not frames.shape[0] == t == states.shape[0]:
        raise EpisodeValidationError(
            f"T must agree: frames have {frames.shape[0]} steps, actions {t}, states {states.shape[0]}"
        )
    if not isinstance(record.success, (bool, np.bool_)):
        raise EpisodeValidationError(f"success must be a bool, got {type(record.success).__name__}")

    attrs: dict[str, Any] = {}
    for key, value in record.attrs.items():
        if key in RESERVED_DEMO_ATTRS:
            raise EpisodeValidationError(f"episode attribute {key!r} is reserved (written by this module)")
        if not isinstance(key, str) or not key or "/" in key:
            raise EpisodeValidationError(f"attribute names must be non-empty str without '/', got {key!r}")
        attrs[key] = _normalize_attr(key, value)
    return EpisodeRecord(frames=frames, actions=actions, states=states, success=bool(record.success), attrs=attrs)


# --------------------------------------------------------------------------------------------
# Files: atomic writes and stale temp files
# --------------------------------------------------------------------------------------------


def _temp_path_for(final: Path) -> Path:
    return final.with_name(f".{final.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def _fsync_path(path: Path) -> None:
    """Flush a file's (or directory's) data to disk so an ``os.replace`` publishes whole bytes."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # some filesystems refuse fsync on directories; the file fsync matters most
        if not path.is_dir():
            raise
    finally:
        os.close(fd)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    return True


def _remove_stale_temps(directory: Path, final_name_re: re.Pattern[str] | None = None) -> list[Path]:
    """Delete temp files whose writer process is gone; keep those a live writer still owns."""
    removed: list[Path] = []
    if not directory.is_dir():
        return removed
    for entry in directory.iterdir():
        match = _TMP_RE.match(entry.name)
        if match is None or (final_name_re is not None and not final_name_re.match(match.group("final"))):
            continue
        if _pid_alive(int(match.group("pid"))):
            continue
        entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed


def _write_demo_group(group: h5py.Group, record: EpisodeRecord, compression_level: int) -> None:
    """Write one validated episode into ``group`` with the robomimic demo layout."""
    t, h, w, c = record.frames.shape
    obs = group.create_group("obs")
    # Per-frame chunks: a training loader reads frame windows, and gzip on whole frames keeps the
    # file small (rendered scenes compress well) without making a random frame expensive.
    obs.create_dataset(
        IMAGE_KEY, data=record.frames, chunks=(1, h, w, c), compression="gzip", compression_opts=compression_level
    )
    group.create_dataset("actions", data=record.actions)
    group.create_dataset("states", data=record.states)
    group.attrs["num_samples"] = np.int64(t)
    group.attrs["success"] = np.bool_(record.success)
    _write_attrs(group, record.attrs)


# --------------------------------------------------------------------------------------------
# Parts (one file per episode, written by the collecting workers)
# --------------------------------------------------------------------------------------------


def write_episode_part(
    parts_dir: str | os.PathLike[str],
    index: int,
    record: EpisodeRecord,
    *,
    limits: PlanLimits = PlanLimits(),
    compression_level: int = _GZIP_LEVEL,
) -> Path:
    """Validate ``record`` and write it atomically to ``parts_dir/demo_{index:06d}.h5``.

    Safe to call from many processes at once (each episode its own file, no shared handle). The
    file appears under its final name only once it is complete and fsynced; a crash at any point
    leaves at most a temp file, which :func:`completed_part_indices` removes later. Rewriting an
    index replaces the old part atomically. Returns the part's path.
    """
    rec = validate_record(record, limits)
    final = part_path(parts_dir, index)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path_for(final)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["index"] = np.int64(index)
            f.attrs["contract_version"] = CONTRACT_VERSION
            _write_demo_group(f.create_group("demo"), rec, compression_level)
        _fsync_path(tmp)
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_path(final.parent)
    return final


def completed_part_indices(parts_dir: str | os.PathLike[str], *, remove_stale: bool = True) -> set[int]:
    """Indices of the episodes whose part file is complete (for resuming a collection run).

    Temp files are never counted. With ``remove_stale`` (default), temp files left by writers that
    no longer run are deleted; those of live writers are left alone.
    """
    parts = Path(parts_dir)
    if not parts.is_dir():
        return set()
    if remove_stale:
        _remove_stale_temps(parts, _PART_RE)
    out: set[int] = set()
    for entry in parts.iterdir():
        match = _PART_RE.match(entry.name)
        if match is not None and entry.is_file():
            out.add(int(match.group(1)))
    return out


def completed_indices(out_path: str | os.PathLike[str], parts_dir: str | os.PathLike[str]) -> set[int]:
    """Indices already collected: in the consolidated file at ``out_path`` or as finished parts."""
    done = completed_part_indices(parts_dir)
    out = Path(out_path)
    if out.exists():
        with h5py.File(out, "r") as f:
            done |= {_demo_index(name) for name in f.get("data", {})}
    return done


# --------------------------------------------------------------------------------------------
# Consolidation (parts + previous dataset -> one robomimic file)
# --------------------------------------------------------------------------------------------


def _check_compatible(old: h5py.File, attrs: Mapping[str, Any], out_path: Path) -> None:
    if "data" not in old:
        raise EpisodeValidationError(f"{out_path} exists but has no 'data' group: not an episode dataset")
    old_attrs = _read_attrs(old["data"], exclude=COMPUTED_DATA_ATTRS)
    if old_attrs != dict(attrs):
        keys = sorted(set(old_attrs) | set(attrs))
        diffs = [
            f"{k}: existing={old_attrs.get(k, '<missing>')!r} new={attrs.get(k, '<missing>')!r}"
            for k in keys
            if old_attrs.get(k, object()) != attrs.get(k, object())
        ]
        raise EpisodeValidationError(
            f"{out_path} holds episodes collected with different dataset attributes; refusing to mix "
            f"them (use another output path or delete the old file): " + "; ".join(diffs)
        )


def _copy_demo(src: h5py.Group, dst_parent: h5py.Group, name: str) -> None:
    """Copy a demo group between files as stored (H5Ocopy: no decompression/recompression)."""
    src.file.copy(src, dst_parent, name=name)


def _demo_shape(group: h5py.Group) -> tuple[tuple[int, ...], int]:
    return tuple(group["obs"][IMAGE_KEY].shape[1:]), int(group["states"].shape[1])


def consolidate(
    parts_dir: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    dataset_attrs: Mapping[str, Any],
    *,
    keep_parts: bool = False,
) -> ConsolidationResult:
    """Merge finished parts (and an existing dataset at ``out_path``) into one robomimic file.

    ``dataset_attrs`` (fps, T, image size, env, task, ...) go on the ``data`` group together with
    ``categories`` and ``contract_version`` from :mod:`firp.core.contract`, ``total`` (samples, as in
    robomimic) and ``num_demos``. If ``out_path`` exists its demos are carried over; its dataset
    attributes must equal the new ones, else :class:`EpisodeValidationError` (mixing episodes of
    different settings would silently poison training). A part whose index the file already holds
    is skipped (that happens when an earlier consolidation was killed after the replace but before
    the parts were removed). All demos must share image size and state width.

    The new file is built next to ``out_path`` and ``os.replace``-d over it, so ``out_path`` is
    always either the old or the new complete dataset. Unless ``keep_parts``, the parts directory is
    removed afterwards. (No ``mask/`` split is written: training splits by seed with
    :func:`firp.data.stratified_split`, so a dataset's splits never go stale when it grows.)
    """
    parts = Path(parts_dir)
    out = Path(out_path)
    attrs = _full_dataset_attrs(dataset_attrs)
    part_indices = completed_part_indices(parts)

    existing: list[int] = []
    if out.exists():
        with h5py.File(out, "r") as old:
            _check_compatible(old, attrs, out)
            existing = sorted(_demo_index(name) for name in old["data"])
    existing_set = set(existing)
    new = sorted(part_indices - existing_set)
    duplicates = tuple(sorted(part_indices & existing_set))
    if not new and not existing:
        raise EpisodeValidationError(f"nothing to consolidate: no finished parts in {parts} and no {out}")

    rewritten = False
    if new:
        out.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(out.parent, re.compile(re.escape(out.name) + "$"))
        tmp = _temp_path_for(out)
        try:
            with h5py.File(tmp, "w") as dst:
                data = dst.create_group("data")
                if existing:
                    with h5py.File(out, "r") as old:
                        for idx in existing:
                            _copy_demo(old["data"][demo_name(idx)], data, demo_name(idx))
                for idx in new:
                    path = part_path(parts, idx)
                    with h5py.File(path, "r") as part:
                        version = part.attrs.get("contract_version")
                        if isinstance(version, bytes):
                            version = version.decode("utf-8")
                        if version != CONTRACT_VERSION:
                            raise EpisodeValidationError(
                                f"{path} was written under contract {version!r}, this code is {CONTRACT_VERSION!r}"
                            )
                        _copy_demo(part["demo"], data, demo_name(idx))
                _finish_data_group(data, attrs)
            _fsync_path(tmp)
            os.replace(tmp, out)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        _fsync_path(out.parent)
        rewritten = True

    if not keep_parts and parts.exists():
        shutil.rmtree(parts)
    return ConsolidationResult(
        out_path=out,
        num_demos=len(existing) + len(new),
        added=tuple(new),
        carried_over=tuple(existing),
        skipped_duplicates=duplicates,
        rewritten=rewritten,
    )


def _finish_data_group(data: h5py.Group, attrs: Mapping[str, Any]) -> None:
    """Check all demos are uniform and write the ``data`` attributes (robomimic ``total`` = samples)."""
    names = sorted(data, key=_demo_index)
    reference: tuple[str, tuple[tuple[int, ...], int]] | None = None
    total = 0
    for name in names:
        shape = _demo_shape(data[name])
        if reference is None:
            reference = (name, shape)
        elif shape != reference[1]:
            raise EpisodeValidationError(
                f"{name} has frames {shape[0]} / state width {shape[1]}, but {reference[0]} has "
                f"{reference[1][0]} / {reference[1][1]}: one dataset must have one image size and state layout"
            )
        total += int(data[name].attrs["num_samples"])
    _write_attrs(data, attrs)
    data.attrs["total"] = np.int64(total)
    data.attrs["num_demos"] = np.int64(len(names))


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


class EpisodeDataset:
    """Read-only view of a consolidated dataset; arrays are read per episode, on demand.

    Use as a context manager (``with EpisodeDataset(path) as ds: ...``) so the HDF5 handle is
    closed. An ``int`` passed where a demo is expected is the episode index (``demo_<i>``), which
    is stable across resumes; use ``ds.demo_names[k]`` for positional access.
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        self._file = h5py.File(self.path, "r")
        try:
            if "data" not in self._file:
                raise EpisodeValidationError(f"{self.path} has no 'data' group: not an episode dataset")
            self._data: h5py.Group = self._file["data"]
            self._names: list[str] = sorted(self._data, key=_demo_index)
        except BaseException:
            self._file.close()
            raise

    # lifecycle -------------------------------------------------------------------------------
    def close(self) -> None:
        """Close the HDF5 file (idempotent)."""
        if self._file.id.valid:
            self._file.close()

    def __enter__(self) -> EpisodeDataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # index -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._names)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __contains__(self, name_or_index: object) -> bool:
        try:
            return self._resolve(name_or_index) in self._data  # type: ignore[arg-type]
        except (KeyError, EpisodeValidationError):
            return False

    @property
    def demo_names(self) -> list[str]:
        """Demo group names sorted by episode index (not lexicographically: demo_10 after demo_9)."""
        return list(self._names)

    @property
    def attrs(self) -> dict[str, Any]:
        """Dataset attributes (fps, T, categories, contract_version, total, ...), decoded."""
        return _read_attrs(self._data)

    def _resolve(self, name_or_index: str | int) -> str:
        name = demo_name(name_or_index) if not isinstance(name_or_index, str) else name_or_index
        if name not in self._data:
            raise KeyError(f"{self.path} has no demo {name!r}")
        return name

    # per-demo --------------------------------------------------------------------------------
    def demo_attrs(self, name_or_index: str | int) -> dict[str, Any]:
        """The record attrs of one demo (without ``num_samples``/``success``)."""
        return _read_attrs(self._data[self._resolve(name_or_index)], exclude=RESERVED_DEMO_ATTRS)

    def frames(self, name_or_index: str | int) -> np.ndarray:
        """Camera frames, uint8 ``(T, H, W, 3)``."""
        return self._data[self._resolve(name_or_index)]["obs"][IMAGE_KEY][()]

    def actions(self, name_or_index: str | int) -> np.ndarray:
        """The executed plan, float32 ``(T, 16)``."""
        return self._data[self._resolve(name_or_index)]["actions"][()]

    def states(self, name_or_index: str | int) -> np.ndarray:
        """Simulator states, float64 ``(T, S)``."""
        return self._data[self._resolve(name_or_index)]["states"][()]

    def success(self, name_or_index: str | int) -> bool:
        """The label of one demo."""
        return bool(self._data[self._resolve(name_or_index)].attrs["success"])

    def episode(self, name_or_index: str | int) -> EpisodeRecord:
        """One full episode (reads only this demo's arrays)."""
        name = self._resolve(name_or_index)
        return EpisodeRecord(
            frames=self.frames(name),
            actions=self.actions(name),
            states=self.states(name),
            success=self.success(name),
            attrs=self.demo_attrs(name),
        )

    # whole dataset ---------------------------------------------------------------------------
    def success_labels(self) -> np.ndarray:
        """Labels in :attr:`demo_names` order, bool ``(N,)`` (attributes only: no array reads)."""
        return np.array([bool(self._data[n].attrs["success"]) for n in self._names], dtype=bool)

    def class_balance(self) -> dict[str, float | int]:
        """Counts of successes and failures and the success rate (a skewed set needs weighting)."""
        labels = self.success_labels()
        n = int(labels.size)
        n_success = int(labels.sum())
        return {
            "total": n,
            "success": n_success,
            "failure": n - n_success,
            "success_rate": (n_success / n) if n else float("nan"),
        }

    def content_hash(self) -> str:
        """sha256 over names, actions, labels and image bytes, in demo order (a cache key).

        Streams frames in blocks so memory stays bounded on big datasets. Attributes other than the
        label and the storage layout (chunking, compression) do not change the hash.
        """
        h = hashlib.sha256(b"firp-episodes-content-v1\0")
        for name in self._names:
            demo = self._data[name]
            h.update(name.encode("utf-8") + b"\0")
            actions = np.ascontiguousarray(demo["actions"][()], dtype="<f4")
            h.update(repr(actions.shape).encode("ascii"))
            h.update(actions.tobytes())
            h.update(b"\1" if bool(demo.attrs["success"]) else b"\0")
            images = demo["obs"][IMAGE_KEY]
            h.update(repr(images.shape).encode("ascii"))
            for start in range(0, images.shape[0], _HASH_BLOCK_FRAMES):
                block = np.ascontiguousarray(images[start : start + _HASH_BLOCK_FRAMES], dtype=np.uint8)
                h.update(block.tobytes())
        return h.hexdigest()
