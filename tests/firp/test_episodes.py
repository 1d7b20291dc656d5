"""Episode datasets: round trip, resume after interruption, crash safety, content hash.

The data are tiny generated episodes (8x6 pixel frames, 10 steps) so the whole module runs in a
second or two; what matters is the file-level behaviour, not the size.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from firp.core.episodes import writer
from firp.core.contract import CATEGORIES, CONTRACT_VERSION, JOINT_LOWER, JOINT_UPPER, N_CATEGORIES, PlanValidationError, make_plan
from firp.core.episodes import (
    EpisodeDataset,
    EpisodeRecord,
    EpisodeValidationError,
    completed_indices,
    completed_part_indices,
    consolidate,
    part_path,
    write_episode_part,
)

T, H, W, S = 10, 6, 8, 5
DATASET_ATTRS = {"fps": 4, "T": T, "image_size": [H, W], "env": "taskboard", "task": "stack3"}


def make_record(seed: int, success: bool | None = None, t: int = T) -> EpisodeRecord:
    """A valid random episode; its content depends on ``seed`` only."""
    rng = np.random.default_rng(seed)
    plan = make_plan(rng.integers(0, N_CATEGORIES, size=t), rng.uniform(JOINT_LOWER, JOINT_UPPER, size=(t, 9)))
    return EpisodeRecord(
        frames=rng.integers(0, 256, size=(t, H, W, 3), dtype=np.uint8),
        actions=plan.astype(np.float32),
        states=rng.normal(size=(t, S)),
        success=bool(seed % 2 == 0) if success is None else success,
        attrs={
            "task": "stack3",
            "seed": seed,
            "noise": 0.25,
            "perturbed": seed % 3 == 0,
            "block_order": ["red", "green", "blue"],
            "pose_estimates": {"red": [0.1, 0.2, 0.03], "blue": [0.3, -0.1, 0.03]},
            "note": "[not json, just a string]",
        },
    )


def assert_same_record(got: EpisodeRecord, want: EpisodeRecord) -> None:
    np.testing.assert_array_equal(got.frames, want.frames)
    np.testing.assert_array_equal(got.actions, want.actions)
    np.testing.assert_array_equal(got.states, want.states)
    assert got.frames.dtype == np.uint8 and got.actions.dtype == np.float32 and got.states.dtype == np.float64
    assert got.success is want.success
    assert got.attrs == want.attrs


def write_parts(parts: Path, indices: list[int]) -> dict[int, EpisodeRecord]:
    records = {i: make_record(i) for i in indices}
    for i, rec in records.items():
        write_episode_part(parts, i, rec)
    return records


def dead_pid() -> int:
    """The pid of a process that has exited (stands in for a collector killed mid-write)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def listing(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir()) if directory.exists() else []


# ---------------------------------------------------------------------------------------------


def test_write_consolidate_read_round_trip(tmp_path: Path) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    records = write_parts(parts, [0, 1, 2])
    assert listing(parts) == ["demo_000000.h5", "demo_000001.h5", "demo_000002.h5"]

    result = consolidate(parts, out, DATASET_ATTRS)
    assert result.added == (0, 1, 2) and result.num_demos == 3 and result.rewritten
    assert not parts.exists(), "parts are removed after a successful consolidation by default"

    with EpisodeDataset(out) as ds:
        assert len(ds) == 3 and ds.demo_names == ["demo_0", "demo_1", "demo_2"]
        for i, want in records.items():
            assert_same_record(ds.episode(i), want)
            assert_same_record(ds.episode(f"demo_{i}"), want)
            np.testing.assert_array_equal(ds.frames(i), want.frames)
            np.testing.assert_array_equal(ds.actions(f"demo_{i}"), want.actions)
        assert ds.attrs == {
            **DATASET_ATTRS,
            "categories": list(CATEGORIES),
            "contract_version": CONTRACT_VERSION,
            "total": 3 * T,
            "num_demos": 3,
        }
        np.testing.assert_array_equal(ds.success_labels(), [True, False, True])
        assert ds.class_balance() == {"total": 3, "success": 2, "failure": 1, "success_rate": 2 / 3}
        assert 7 not in ds and 1 in ds and "demo_2" in ds
        with pytest.raises(KeyError, match="demo_7"):
            ds.episode(7)

    # robomimic layout, read with plain h5py as robomimic would
    with h5py.File(out, "r") as f:
        demo = f["data/demo_1"]
        img = demo["obs/agentview_image"]
        assert img.dtype == np.uint8 and img.shape == (T, H, W, 3)
        assert img.chunks == (1, H, W, 3) and img.compression == "gzip"
        assert demo["actions"].shape == (T, 16) and demo["states"].shape == (T, S)
        assert int(demo.attrs["num_samples"]) == T and not bool(demo.attrs["success"])
        assert f["data"].attrs["total"] == 3 * T


def test_ints_index_numerically_not_lexicographically(tmp_path: Path) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    write_parts(parts, [10, 2, 9])
    consolidate(parts, out, DATASET_ATTRS)
    with EpisodeDataset(out) as ds:
        assert ds.demo_names == ["demo_2", "demo_9", "demo_10"]


def test_resume_after_interruption_then_extend(tmp_path: Path) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    # First run asked for 4 episodes and was killed: the writer of episode 2 died mid-file (its
    # temp file is left behind, the part never published); 0, 1 and 3 finished.
    records = write_parts(parts, [0, 1, 3])
    stale = parts / f".demo_000002.h5.{dead_pid()}.0badc0de.tmp"
    stale.write_bytes(b"half an HDF5 file")
    live = parts / f".demo_000004.h5.{os.getpid()}.cafe0001.tmp"
    live.write_bytes(b"a live writer is still filling this")

    assert completed_part_indices(parts) == {0, 1, 3}
    assert not stale.exists(), "a temp file of a dead writer is stale and removed"
    assert live.exists(), "a temp file of a live writer is kept"
    live.unlink()

    # Resume: the collector fills the gap, consolidates, and a later run asks for 6 episodes.
    records |= write_parts(parts, [2])
    consolidate(parts, out, DATASET_ATTRS)
    assert completed_indices(out, tmp_path / "parts") == {0, 1, 2, 3}
    hash_before = EpisodeDataset(out).content_hash()

    records |= write_parts(parts, [4, 5])
    assert completed_indices(out, parts) == {0, 1, 2, 3, 4, 5}
    result = consolidate(parts, out, DATASET_ATTRS)
    assert result.carried_over == (0, 1, 2, 3) and result.added == (4, 5)
    with EpisodeDataset(out) as ds:
        assert ds.demo_names == [f"demo_{i}" for i in range(6)]
        assert ds.attrs["total"] == 6 * T and ds.attrs["num_demos"] == 6
        for i, want in records.items():
            assert_same_record(ds.episode(i), want)
        assert ds.content_hash() != hash_before


def test_duplicate_part_of_existing_demo_is_skipped(tmp_path: Path) -> None:
    """A consolidation killed after the replace but before removing parts can simply be rerun."""
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    write_parts(parts, [0, 1])
    consolidate(parts, out, DATASET_ATTRS, keep_parts=True)
    before = out.stat().st_mtime_ns
    result = consolidate(parts, out, DATASET_ATTRS)
    assert result.skipped_duplicates == (0, 1) and not result.rewritten
    assert out.stat().st_mtime_ns == before and not parts.exists()


def test_existing_file_with_other_attrs_is_refused(tmp_path: Path) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    write_parts(parts, [0])
    consolidate(parts, out, DATASET_ATTRS)
    write_parts(parts, [1])
    with pytest.raises(EpisodeValidationError, match=r"fps: existing=4 new=8"):
        consolidate(parts, out, {**DATASET_ATTRS, "fps": 8})
    assert completed_part_indices(parts) == {1}, "a refused consolidation keeps the parts"
    with EpisodeDataset(out) as ds:
        assert ds.demo_names == ["demo_0"]


def test_crash_inside_part_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parts = tmp_path / "parts"
    write_parts(parts, [0])
    real = writer._write_demo_group

    def crash_halfway(group: h5py.Group, record: EpisodeRecord, level: int) -> None:
        group.create_dataset("actions", data=record.actions)  # something is on disk already
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(writer, "_write_demo_group", crash_halfway)
    with pytest.raises(OSError, match="simulated"):
        write_episode_part(parts, 1, make_record(1))
    assert listing(parts) == ["demo_000000.h5"], "no partial part and no temp file"
    assert completed_part_indices(parts) == {0}

    # Overwriting an existing part that crashes keeps the old part intact.
    with pytest.raises(OSError):
        write_episode_part(parts, 0, make_record(99))
    monkeypatch.setattr(writer, "_write_demo_group", real)
    consolidate(parts, tmp_path / "ds.hdf5", DATASET_ATTRS)
    with EpisodeDataset(tmp_path / "ds.hdf5") as ds:
        assert_same_record(ds.episode(0), make_record(0))


def test_crash_inside_consolidate_keeps_old_file_and_parts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    write_parts(parts, [0, 1])
    consolidate(parts, out, DATASET_ATTRS)
    hash_before = EpisodeDataset(out).content_hash()
    write_parts(parts, [2, 3])

    real_copy = writer._copy_demo
    calls = []

    def copy_then_crash(src: h5py.Group, dst: h5py.Group, name: str) -> None:
        calls.append(name)
        if len(calls) == 3:  # after both old demos and one part
            raise KeyboardInterrupt("killed (simulated)")
        real_copy(src, dst, name)

    monkeypatch.setattr(writer, "_copy_demo", copy_then_crash)
    with pytest.raises(KeyboardInterrupt):
        consolidate(parts, out, DATASET_ATTRS)
    assert listing(tmp_path) == ["ds.hdf5", "parts"], "no temp file left next to the output"
    with EpisodeDataset(out) as ds:
        assert ds.demo_names == ["demo_0", "demo_1"] and ds.content_hash() == hash_before
    assert completed_indices(out, parts) == {0, 1, 2, 3}

    monkeypatch.setattr(writer, "_copy_demo", real_copy)
    consolidate(parts, out, DATASET_ATTRS)
    with EpisodeDataset(out) as ds:
        assert len(ds) == 4


def test_stale_output_temp_is_cleaned(tmp_path: Path) -> None:
    parts, out = tmp_path / "parts", tmp_path / "ds.hdf5"
    stale = tmp_path / f".ds.hdf5.{dead_pid()}.00000000.tmp"
    stale.write_bytes(b"left by a killed consolidation")
    write_parts(parts, [0])
    consolidate(parts, out, DATASET_ATTRS)
    assert listing(tmp_path) == ["ds.hdf5"]


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (lambda r: setattr(r, "actions", r.actions[:, :15]), PlanValidationError, "width"),
        (lambda r: r.actions.__setitem__((0, 0), 0.5), PlanValidationError, r"actions\[0\]"),
        (lambda r: setattr(r, "frames", r.frames.astype(np.float32)), EpisodeValidationError, "uint8"),
        (lambda r: setattr(r, "frames", r.frames[..., :1]), EpisodeValidationError, r"\(T, H, W, 3\)"),
        (lambda r: setattr(r, "frames", r.frames[:-1]), EpisodeValidationError, "T must agree"),
        (lambda r: setattr(r, "states", r.states[:-1]), EpisodeValidationError, "T must agree"),
        (lambda r: setattr(r, "states", r.states[:, 0]), EpisodeValidationError, "2-D"),
        (lambda r: setattr(r, "success", 1), EpisodeValidationError, "bool"),
        (lambda r: r.attrs.__setitem__("success", True), EpisodeValidationError, "reserved"),
        (lambda r: r.attrs.__setitem__("obj", object()), EpisodeValidationError, "cannot be stored"),
        (lambda r: setattr(r, "view", np.zeros((2, 8, 8, 3), np.uint8)), EpisodeValidationError, "one uint8 RGB"),
        (lambda r: setattr(r, "view", np.zeros((8, 8, 3), np.float32)), EpisodeValidationError, "one uint8 RGB"),
    ],
    ids=["width", "one_hot", "float_frames", "gray_frames", "frames_T", "states_T", "states_1d", "int_label",
         "reserved_attr", "object_attr", "two_views", "float_view"],
)
def test_invalid_records_are_refused_before_writing(tmp_path: Path, change, error, match) -> None:
    rec = make_record(0)
    change(rec)
    with pytest.raises(error, match=match):
        write_episode_part(tmp_path, 0, rec)
    assert listing(tmp_path) == []


def test_mixed_image_sizes_are_refused(tmp_path: Path) -> None:
    parts = tmp_path / "parts"
    write_parts(parts, [0])
    odd = make_record(1)
    odd.frames = np.zeros((T, H + 1, W, 3), np.uint8)
    write_episode_part(parts, 1, odd)
    with pytest.raises(EpisodeValidationError, match="one image size"):
        consolidate(parts, tmp_path / "ds.hdf5", DATASET_ATTRS)
    assert not (tmp_path / "ds.hdf5").exists()


def test_content_hash_stable_and_label_sensitive(tmp_path: Path) -> None:
    parts_a, parts_b = tmp_path / "a", tmp_path / "b"
    a, b = tmp_path / "a.hdf5", tmp_path / "b.hdf5"
    write_parts(parts_a, [0, 1, 2])
    consolidate(parts_a, a, DATASET_ATTRS)
    for i in range(3):
        write_episode_part(parts_b, i, make_record(i))
    consolidate(parts_b, b, DATASET_ATTRS)
    with EpisodeDataset(a) as da, EpisodeDataset(b) as db:
        h = da.content_hash()
        assert len(h) == 64 and h == da.content_hash() == db.content_hash()

    # Flip one label only: same images and actions, different hash.
    with h5py.File(b, "r+") as f:
        f["data/demo_1"].attrs["success"] = True
    with EpisodeDataset(b) as db:
        assert db.content_hash() != h

    # Change one pixel: different hash too.
    with h5py.File(a, "r+") as f:
        f["data/demo_2/obs/agentview_image"][5, 0, 0, 0] ^= 1
    with EpisodeDataset(a) as da:
        assert da.content_hash() != h


def test_dataset_attrs_cannot_contradict_contract(tmp_path: Path) -> None:
    write_parts(tmp_path / "parts", [0])
    with pytest.raises(EpisodeValidationError, match="contract_version"):
        consolidate(tmp_path / "parts", tmp_path / "ds.hdf5", {**DATASET_ATTRS, "contract_version": "0.1"})
    with pytest.raises(EpisodeValidationError, match="computed"):
        consolidate(tmp_path / "parts", tmp_path / "ds.hdf5", {**DATASET_ATTRS, "total": 3})


def test_nothing_to_consolidate(tmp_path: Path) -> None:
    with pytest.raises(EpisodeValidationError, match="nothing to consolidate"):
        consolidate(tmp_path / "parts", tmp_path / "ds.hdf5", DATASET_ATTRS)
    assert part_path(tmp_path, 7).name == "demo_000007.h5"


def test_episodes_with_only_their_initial_frame_and_a_view_read_back(tmp_path: Path) -> None:
    """``firp collect --framed --view-size``: some episodes keep one frame, every one its view; reading tells which."""
    parts = tmp_path / "parts"
    for index in range(3):
        rec = make_record(index)
        if index > 0:
            rec.frames = rec.frames[:1].copy()
        rec.view = np.full((16, 16, 3), index, np.uint8)
        write_episode_part(parts, index, rec)
    consolidate(parts, tmp_path / "ds.hdf5", DATASET_ATTRS)
    with EpisodeDataset(tmp_path / "ds.hdf5") as ds:
        assert ds.framed_mask().tolist() == [True, False, False] and ds.has_view
        assert ds.frames(1).shape == (1, H, W, 3) and ds.view(2).shape == (16, 16, 3) and ds.view(2)[0, 0, 0] == 2
        np.testing.assert_array_equal(ds.initial_frame(0), ds.frames(0)[0])
        assert ds.episode(1).view.shape == (1, 16, 16, 3)
        hash_with_views = ds.content_hash()
    odd = make_record(3)
    odd.view = np.zeros((8, 8, 3), np.uint8)  # another view size
    write_episode_part(parts, 3, odd)
    with pytest.raises(EpisodeValidationError, match="view"):
        consolidate(parts, tmp_path / "ds.hdf5", DATASET_ATTRS)
    assert hash_with_views
