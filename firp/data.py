"""Training tensors from a recorded dataset: cached frame features, plans and labels in RAM.

One :class:`SequenceData` per dataset; splits are index arrays into it, so every method in an
evaluation trains and tests on exactly the same episodes. A dataset may keep every frame of only some
episodes and the initial frame of the rest (``firp collect --framed``): :class:`FrameFeatures` holds
both without a copy of the initial frame per step.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import torch

from firp.core.episodes import EpisodeDataset
from firp.features import DEFAULT_CACHE_DIR, cached_features, cached_initial_features
from firp.model.config import EncoderConfig


class FrameFeatures:
    """Backbone features ``(N, T, Db)`` of a dataset's frames, where some episodes kept only their initial frame.

    Indexed like the tensor it stands for: ``features[index]`` gives ``(B, T, Db)`` -- an initial-only episode's
    row repeats its initial frame (what every model that reads the initial frame only needs; the training loop
    keeps such rows out of the terms that read later frames, see :attr:`framed`) -- and ``features[index, 0]``
    gives the initial frames ``(B, Db)``."""

    def __init__(self, first: torch.Tensor, frames: torch.Tensor, row: torch.Tensor):
        self.first = first  # (N, Db) every episode's initial frame
        self.frames = frames  # (N_framed, T, Db) every frame of the framed episodes
        self.row = row  # (N,) long: an episode's row in ``frames``, -1 for an initial-only episode

    @classmethod
    def from_tensor(cls, features: torch.Tensor) -> FrameFeatures:
        """Every episode framed: ``features`` (N, T, Db)."""
        return cls(features[:, 0], features, torch.arange(features.shape[0]))

    @property
    def framed(self) -> torch.Tensor:
        """(N,) bool: which episodes kept every frame."""
        return self.row >= 0

    @property
    def shape(self) -> tuple[int, int, int]:
        return (int(self.first.shape[0]), int(self.frames.shape[1]), int(self.first.shape[1]))

    def __len__(self) -> int:
        return int(self.first.shape[0])

    def __getitem__(self, key):
        if isinstance(key, tuple):
            if len(key) != 2 or not (isinstance(key[1], int) and key[1] == 0):
                raise IndexError("FrameFeatures: index episodes, or episodes and frame 0 ([index, 0])")
            return self.first[key[0]]
        first, row = self.first[key], self.row[key]
        if first.ndim == 1:  # a single episode
            return self.frames[row] if row >= 0 else first.unsqueeze(0).expand(self.shape[1], -1)
        out = first.unsqueeze(1).expand(-1, self.shape[1], -1)
        if bool((row >= 0).any()):
            out = out.clone()
            has = row >= 0
            out[has] = self.frames[row[has]]
        return out

    @classmethod
    def concat(cls, parts: list[FrameFeatures]) -> FrameFeatures:
        """Several datasets' features one after another."""
        rows, offset = [], 0
        for part in parts:
            rows.append(torch.where(part.row >= 0, part.row + offset, part.row))
            offset += int(part.frames.shape[0])
        return cls(torch.cat([p.first for p in parts]), torch.cat([p.frames for p in parts]), torch.cat(rows))

    def subset(self, index: torch.Tensor) -> FrameFeatures:
        row = self.row[index]
        keep = row[row >= 0]
        new_row = torch.full_like(row, -1)
        new_row[row >= 0] = torch.arange(int(keep.shape[0]))
        return FrameFeatures(self.first[index], self.frames[keep], new_row)


@dataclass
class SequenceData:
    features: FrameFeatures  # (N, T, Db) float32 backbone features of frames[0..T-1]
    actions: torch.Tensor  # (N, T, 16) float32 plans
    labels: torch.Tensor  # (N,) float32 1 = success
    dataset_hash: str
    demo_names: list[str]
    attrs: dict = field(default_factory=dict)  # the dataset's attributes (its kinematics, calibration, ...)

    def __post_init__(self) -> None:
        if isinstance(self.features, torch.Tensor):
            self.features = FrameFeatures.from_tensor(self.features)

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @property
    def framed(self) -> torch.Tensor:
        """(N,) bool: which episodes kept every frame (the rest only their initial frame)."""
        return self.features.framed

    def subset(self, index: np.ndarray) -> "SequenceData":
        idx = torch.as_tensor(np.asarray(index), dtype=torch.long)
        return SequenceData(self.features.subset(idx), self.actions[idx], self.labels[idx], self.dataset_hash,
                            [self.demo_names[i] for i in idx.tolist()], self.attrs)


def load_sequences(dataset_path: str | os.PathLike, encoder: EncoderConfig,
                   cache_dir: str | os.PathLike = DEFAULT_CACHE_DIR, progress: bool = True) -> SequenceData:
    """Features (computing the cache if needed), actions and labels of every episode."""
    with EpisodeDataset(dataset_path) as ds:
        names = ds.demo_names
        dataset_hash = ds.content_hash()
        actions = np.stack([ds.actions(n) for n in names]).astype(np.float32)
        labels = ds.success_labels().astype(np.float32)
        framed = ds.framed_mask()
        attrs = ds.attrs
    if framed.all():
        feats = cached_features(dataset_path, encoder, cache_dir, progress=progress, dataset_hash=dataset_hash)
        features = FrameFeatures.from_tensor(torch.from_numpy(np.asarray(feats, dtype=np.float32)))
    else:
        first, frames = cached_initial_features(dataset_path, encoder, cache_dir, progress=progress,
                                                dataset_hash=dataset_hash)
        row = torch.from_numpy(np.where(framed, np.cumsum(framed) - 1, -1).astype(np.int64))
        features = FrameFeatures(torch.from_numpy(np.asarray(first, dtype=np.float32)),
                                 torch.from_numpy(np.asarray(frames, dtype=np.float32)), row)
    return SequenceData(features, torch.from_numpy(actions), torch.from_numpy(labels), dataset_hash, names, attrs)


def stratified_split(labels: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (rest, picked) with ``fraction`` of each class picked at random (at least one each)."""
    rng = np.random.default_rng(seed)
    labels = np.asarray(labels)
    picked = []
    for value in np.unique(labels):
        idx = np.flatnonzero(labels == value)
        rng.shuffle(idx)
        k = max(1, int(round(fraction * len(idx)))) if len(idx) > 1 else 0
        picked.extend(idx[:k].tolist())
    picked_arr = np.sort(np.asarray(picked, dtype=np.int64))
    rest = np.setdiff1d(np.arange(len(labels)), picked_arr)
    return rest, picked_arr
