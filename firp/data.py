"""Training tensors from a recorded dataset: cached frame features, plans and labels in RAM.

One :class:`SequenceData` per dataset; splits are index arrays into it, so every method in an
evaluation trains and tests on exactly the same episodes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from firp.core.episodes import EpisodeDataset
from firp.features import DEFAULT_CACHE_DIR, cached_features
from firp.model.config import EncoderConfig


@dataclass
class SequenceData:
    features: torch.Tensor  # (N, T, Db) float32 backbone features of frames[0..T-1]
    actions: torch.Tensor  # (N, T, 16) float32 plans
    labels: torch.Tensor  # (N,) float32 1 = success
    dataset_hash: str
    demo_names: list[str]

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def subset(self, index: np.ndarray) -> "SequenceData":
        idx = torch.as_tensor(np.asarray(index), dtype=torch.long)
        return SequenceData(self.features[idx], self.actions[idx], self.labels[idx], self.dataset_hash,
                            [self.demo_names[i] for i in idx.tolist()])


def load_sequences(dataset_path: str | os.PathLike, encoder: EncoderConfig,
                   cache_dir: str | os.PathLike = DEFAULT_CACHE_DIR, progress: bool = True) -> SequenceData:
    """Features (computing the cache if needed), actions and labels of every episode."""
    with EpisodeDataset(dataset_path) as ds:
        names = ds.demo_names
        dataset_hash = ds.content_hash()
        actions = np.stack([ds.actions(n) for n in names]).astype(np.float32)
        labels = ds.success_labels().astype(np.float32)
    feats = cached_features(dataset_path, encoder, cache_dir, progress=progress, dataset_hash=dataset_hash)
    return SequenceData(torch.from_numpy(np.asarray(feats, dtype=np.float32)), torch.from_numpy(actions),
                        torch.from_numpy(labels), dataset_hash, names)


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
