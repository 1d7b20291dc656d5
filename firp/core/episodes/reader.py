"""Reading a consolidated dataset: :class:`EpisodeDataset`, arrays read per episode on demand."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from firp.core.episodes.layout import (
    HASH_BLOCK_FRAMES,
    IMAGE_KEY,
    RESERVED_DEMO_ATTRS,
    VIEW_KEY,
    FINAL_VIEW_KEY,
    EpisodeRecord,
    EpisodeValidationError,
    demo_index,
    demo_name,
    read_attrs,
)

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
            self._names: list[str] = sorted(self._data, key=demo_index)
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
        return read_attrs(self._data)

    def _resolve(self, name_or_index: str | int) -> str:
        name = demo_name(name_or_index) if not isinstance(name_or_index, str) else name_or_index
        if name not in self._data:
            raise KeyError(f"{self.path} has no demo {name!r}")
        return name

    # per-demo --------------------------------------------------------------------------------
    def demo_attrs(self, name_or_index: str | int) -> dict[str, Any]:
        """The record attrs of one demo (without ``num_samples``/``success``)."""
        return read_attrs(self._data[self._resolve(name_or_index)], exclude=RESERVED_DEMO_ATTRS)

    def frames(self, name_or_index: str | int) -> np.ndarray:
        """Camera frames, uint8 ``(T, H, W, 3)``."""
        return self._data[self._resolve(name_or_index)]["obs"][IMAGE_KEY][()]

    def initial_frame(self, name_or_index: str | int) -> np.ndarray:
        """The initial camera frame I_1, uint8 ``(H, W, 3)`` (every episode has it)."""
        return self._data[self._resolve(name_or_index)]["obs"][IMAGE_KEY][0]

    def is_framed(self, name_or_index: str | int) -> bool:
        """Whether the episode kept a frame per step (else only its initial frame)."""
        demo = self._data[self._resolve(name_or_index)]
        return int(demo["obs"][IMAGE_KEY].shape[0]) == int(demo.attrs["num_samples"])

    def framed_mask(self) -> np.ndarray:
        """:meth:`is_framed` of every episode in :attr:`demo_names` order, bool ``(N,)`` (no image reads)."""
        return np.array([int(self._data[n]["obs"][IMAGE_KEY].shape[0]) == int(self._data[n].attrs["num_samples"])
                         for n in self._names], dtype=bool)

    @property
    def has_view(self) -> bool:
        """Whether the episodes carry the initial image at the view's resolution (:data:`VIEW_KEY`)."""
        return bool(self._names) and VIEW_KEY in self._data[self._names[0]]["obs"]

    def view(self, name_or_index: str | int) -> np.ndarray:
        """The initial image at the view's resolution, uint8 ``(H', W', 3)``."""
        obs = self._data[self._resolve(name_or_index)]["obs"]
        if VIEW_KEY not in obs:
            raise KeyError(f"{self.path} has no view image ({VIEW_KEY}): collect it with --view-size")
        return obs[VIEW_KEY][0]

    @property
    def has_final_view(self) -> bool:
        """Whether the episodes carry the settled final scene at the view's resolution (:data:`FINAL_VIEW_KEY`)."""
        return bool(self._names) and FINAL_VIEW_KEY in self._data[self._names[0]]["obs"]

    def final_view(self, name_or_index: str | int) -> np.ndarray:
        """The settled final scene at the view's resolution, uint8 ``(H', W', 3)`` (an Oracle's input)."""
        obs = self._data[self._resolve(name_or_index)]["obs"]
        if FINAL_VIEW_KEY not in obs:
            raise KeyError(f"{self.path} has no final view ({FINAL_VIEW_KEY}): collect it with --final-view")
        return obs[FINAL_VIEW_KEY][0]

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
            view=self.view(name)[None] if VIEW_KEY in self._data[name]["obs"] else None,
            final_view=self.final_view(name)[None] if FINAL_VIEW_KEY in self._data[name]["obs"] else None,
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
        label and the storage layout (chunking, compression) do not change the hash. A view image, where
        episodes carry one, counts too (a dataset without views hashes as it always did).
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
            for start in range(0, images.shape[0], HASH_BLOCK_FRAMES):
                block = np.ascontiguousarray(images[start : start + HASH_BLOCK_FRAMES], dtype=np.uint8)
                h.update(block.tobytes())
            for key, tag in ((VIEW_KEY, b"view"), (FINAL_VIEW_KEY, b"final_view")):
                if key in demo["obs"]:
                    view = demo["obs"][key]
                    h.update(tag + repr(view.shape).encode("ascii"))
                    h.update(np.ascontiguousarray(view[()], dtype=np.uint8).tobytes())
        return h.hexdigest()
