"""Writing datasets: one part file per episode (collecting workers), then one consolidated file."""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from firp.core.contract import CONTRACT_VERSION, PlanLimits
from firp.core.episodes.files import atomic_file, remove_stale_temps
from firp.core.episodes.layout import (
    COMPUTED_DATA_ATTRS,
    GZIP_LEVEL,
    IMAGE_KEY,
    PART_RE,
    VIEW_KEY,
    FINAL_VIEW_KEY,
    EpisodeRecord,
    EpisodeValidationError,
    demo_index,
    demo_name,
    full_dataset_attrs,
    part_path,
    read_attrs,
    validate_record,
    write_attrs,
)

@dataclass(frozen=True)
class ConsolidationResult:
    """What :func:`consolidate` did, for logs and for the caller's resume bookkeeping."""

    out_path: Path
    num_demos: int
    added: tuple[int, ...]
    carried_over: tuple[int, ...]
    skipped_duplicates: tuple[int, ...]
    rewritten: bool


def _write_demo_group(group: h5py.Group, record: EpisodeRecord, compression_level: int) -> None:
    """Write one validated episode into ``group`` with the robomimic demo layout."""
    t, h, w, c = record.frames.shape
    obs = group.create_group("obs")
    # Per-frame chunks: a training loader reads frame windows, and gzip on whole frames keeps the
    # file small (rendered scenes compress well) without making a random frame expensive.
    obs.create_dataset(
        IMAGE_KEY, data=record.frames, chunks=(1, h, w, c), compression="gzip", compression_opts=compression_level
    )
    for key, image in ((VIEW_KEY, record.view), (FINAL_VIEW_KEY, record.final_view)):
        if image is not None:
            obs.create_dataset(key, data=image, chunks=image.shape, compression="gzip",
                               compression_opts=compression_level)
    group.create_dataset("actions", data=record.actions)
    group.create_dataset("states", data=record.states)
    group.attrs["num_samples"] = np.int64(record.actions.shape[0])
    group.attrs["success"] = np.bool_(record.success)
    write_attrs(group, record.attrs)


# --------------------------------------------------------------------------------------------
# Parts (one file per episode, written by the collecting workers)
# --------------------------------------------------------------------------------------------


def write_episode_part(
    parts_dir: str | os.PathLike[str],
    index: int,
    record: EpisodeRecord,
    *,
    limits: PlanLimits = PlanLimits(),
    compression_level: int = GZIP_LEVEL,
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
    with atomic_file(final) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["index"] = np.int64(index)
        f.attrs["contract_version"] = CONTRACT_VERSION
        _write_demo_group(f.create_group("demo"), rec, compression_level)
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
        remove_stale_temps(parts, PART_RE)
    out: set[int] = set()
    for entry in parts.iterdir():
        match = PART_RE.match(entry.name)
        if match is not None and entry.is_file():
            out.add(int(match.group(1)))
    return out


def completed_indices(out_path: str | os.PathLike[str], parts_dir: str | os.PathLike[str]) -> set[int]:
    """Indices already collected: in the consolidated file at ``out_path`` or as finished parts."""
    done = completed_part_indices(parts_dir)
    out = Path(out_path)
    if out.exists():
        with h5py.File(out, "r") as f:
            done |= {demo_index(name) for name in f.get("data", {})}
    return done


# --------------------------------------------------------------------------------------------
# Consolidation (parts + previous dataset -> one robomimic file)
# --------------------------------------------------------------------------------------------


def _check_compatible(old: h5py.File, attrs: Mapping[str, Any], out_path: Path) -> None:
    if "data" not in old:
        raise EpisodeValidationError(f"{out_path} exists but has no 'data' group: not an episode dataset")
    old_attrs = read_attrs(old["data"], exclude=COMPUTED_DATA_ATTRS)
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


def _demo_shape(group: h5py.Group) -> tuple[tuple[int, ...], int, tuple]:
    """What must be one across a dataset: the frames' image size, the state width and the views' sizes."""
    views = tuple(tuple(group["obs"][k].shape) if k in group["obs"] else None for k in (VIEW_KEY, FINAL_VIEW_KEY))
    return tuple(group["obs"][IMAGE_KEY].shape[1:]), int(group["states"].shape[1]), views


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
    attrs = full_dataset_attrs(dataset_attrs)
    part_indices = completed_part_indices(parts)

    existing: list[int] = []
    if out.exists():
        with h5py.File(out, "r") as old:
            _check_compatible(old, attrs, out)
            existing = sorted(demo_index(name) for name in old["data"])
    existing_set = set(existing)
    new = sorted(part_indices - existing_set)
    duplicates = tuple(sorted(part_indices & existing_set))
    if not new and not existing:
        raise EpisodeValidationError(f"nothing to consolidate: no finished parts in {parts} and no {out}")

    rewritten = False
    if new:
        out.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(out.parent, re.compile(re.escape(out.name) + "$"))
        with atomic_file(out) as tmp, h5py.File(tmp, "w") as dst:
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
    names = sorted(data, key=demo_index)
    reference: tuple[str, tuple[tuple[int, ...], int]] | None = None
    total = 0
    for name in names:
        shape = _demo_shape(data[name])
        if reference is None:
            reference = (name, shape)
        elif shape != reference[1]:
            raise EpisodeValidationError(
                f"{name} has frames {shape[0]} / state width {shape[1]} / view {shape[2]}, but {reference[0]} has "
                f"{reference[1][0]} / {reference[1][1]} / {reference[1][2]}: one dataset must have one image size, "
                "state layout and view"
            )
        total += int(data[name].attrs["num_samples"])
    write_attrs(data, attrs)
    data.attrs["total"] = np.int64(total)
    data.attrs["num_demos"] = np.int64(len(names))


