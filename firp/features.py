"""Backbone features of every frame of a dataset, computed once and cached on disk.

The image backbone is frozen, so its output for a given frame never changes: running it once per
dataset (instead of once per epoch) is what makes training on a 2-core CPU affordable. The cache
is keyed by the dataset's content hash and the backbone settings, so a changed dataset or backbone
can never be served stale features. Extraction writes into a memory-mapped ``.npy`` as it goes
and records its progress, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from firp.core.episodes import EpisodeDataset
from firp.model.config import EncoderConfig
from firp.model.encoder import ImageEncoder

DEFAULT_CACHE_DIR = Path("data/cache")


def cache_key(dataset_hash: str, cfg: EncoderConfig) -> str:
    """Name of the cache entry: what determines the backbone's output, and nothing else."""
    settings = {"backbone": cfg.backbone, "image_size": cfg.image_size, "normalization": cfg.resolved_normalization,
                "weights": cfg.weights_path or "shipped", "channels": list(cfg.small_cnn_channels)}
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    return f"{dataset_hash[:16]}-{cfg.backbone}-{cfg.image_size}px-{digest}"


def cached_features(dataset_path: str | os.PathLike, cfg: EncoderConfig, cache_dir: str | os.PathLike = DEFAULT_CACHE_DIR,
                    batch_frames: int = 240, progress: bool = True, dataset_hash: str | None = None) -> np.ndarray:
    """Features ``(N, T, Db)`` float16 of every frame, in the dataset's demo order (memory-mapped).

    Computes what is missing (resuming a partial run) and returns the finished cache.
    """
    if not cfg.freeze_backbone:
        raise ValueError("encoder.freeze_backbone: only a frozen backbone's features can be cached")
    if cfg.backbone != "efficientnet_lite0":
        # a small_cnn is randomly initialised: its features would belong to a backbone no bundle holds,
        # and another process (another random state) would be served them as its own
        raise ValueError(f"encoder.backbone: only the pretrained efficientnet_lite0's features can be cached, "
                         f"got {cfg.backbone!r}")
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with EpisodeDataset(dataset_path) as ds:
        dataset_hash = dataset_hash or ds.content_hash()
        key = cache_key(dataset_hash, cfg)
        final = cache_dir / f"{key}.npy"
        if final.exists():
            return np.load(final, mmap_mode="r", allow_pickle=False)
        # One writer per cache: several tuning workers on one machine start together; the others wait
        # here and then read the finished cache instead of racing on the partial file.
        with open(cache_dir / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not final.exists():
                _compute_features(ds, cfg, cache_dir, key, final, batch_frames, progress)
    return np.load(final, mmap_mode="r", allow_pickle=False)


def cached_initial_features(dataset_path: str | os.PathLike, cfg: EncoderConfig,
                            cache_dir: str | os.PathLike = DEFAULT_CACHE_DIR, batch_frames: int = 240,
                            progress: bool = True, dataset_hash: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For a dataset whose episodes keep only their initial frame beyond the first few (``firp collect --framed``):
    features ``(N, Db)`` of every episode's initial frame and ``(N_framed, T, Db)`` of every frame of the framed
    episodes, float16, memory-mapped, in demo order. Cached, resumable and locked like :func:`cached_features`."""
    if not cfg.freeze_backbone or cfg.backbone != "efficientnet_lite0":
        raise ValueError("encoder: only the pretrained, frozen efficientnet_lite0's features can be cached")
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with EpisodeDataset(dataset_path) as ds:
        dataset_hash = dataset_hash or ds.content_hash()
        key = cache_key(dataset_hash, cfg) + "-initial"
        first_path, framed_path = cache_dir / f"{key}.first.npy", cache_dir / f"{key}.framed.npy"
        if not (first_path.exists() and framed_path.exists()):
            with open(cache_dir / f"{key}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                if not (first_path.exists() and framed_path.exists()):
                    _compute_initial_features(ds, cfg, cache_dir, key, first_path, framed_path, batch_frames,
                                              progress)
    return (np.load(first_path, mmap_mode="r", allow_pickle=False),
            np.load(framed_path, mmap_mode="r", allow_pickle=False))


def _compute_initial_features(ds: EpisodeDataset, cfg: EncoderConfig, cache_dir: Path, key: str, first_path: Path,
                              framed_path: Path, batch_frames: int, progress: bool) -> None:
    names = ds.demo_names
    framed = ds.framed_mask()
    t_len = int(ds.actions(names[0]).shape[0])
    encoder = ImageEncoder(cfg).eval()
    partial_first, partial_framed = cache_dir / f"{key}.first.partial.npy", cache_dir / f"{key}.framed.partial.npy"
    progress_file = cache_dir / f"{key}.progress.json"
    done = 0
    if partial_first.exists() and partial_framed.exists() and progress_file.exists():
        done = int(json.loads(progress_file.read_text())["done"])
        first = np.load(partial_first, mmap_mode="r+", allow_pickle=False)
        frames = np.load(partial_framed, mmap_mode="r+", allow_pickle=False)
    else:
        first = np.lib.format.open_memmap(partial_first, mode="w+", dtype=np.float16,
                                          shape=(len(names), encoder.backbone_dim))
        frames = np.lib.format.open_memmap(partial_framed, mode="w+", dtype=np.float16,
                                           shape=(int(framed.sum()), t_len, encoder.backbone_dim))
    row = np.cumsum(framed) - 1  # each framed episode's row in ``frames``
    bar = tqdm(total=len(names), initial=done, desc=f"features {cfg.backbone}@{cfg.image_size}", unit="ep",
               disable=not progress)
    pending: list[int] = []  # initial-only episodes, encoded in batches

    def flush_initial(first: np.ndarray) -> None:
        if pending:
            images = np.stack([ds.initial_frame(names[i]) for i in pending])
            first[pending] = encoder.backbone_features(torch.from_numpy(images)).float().numpy().astype(np.float16)
            pending.clear()

    with torch.inference_mode():
        for i in range(done, len(names)):
            if framed[i]:
                feats = encoder.backbone_features(torch.from_numpy(ds.frames(names[i])), chunk_size=batch_frames)
                frames[row[i]] = feats.float().numpy().astype(np.float16)
                first[i] = frames[row[i], 0]
            else:
                pending.append(i)
            if len(pending) >= batch_frames or (i + 1) % 256 == 0 or i + 1 == len(names):
                flush_initial(first)  # everything before i + 1 is written: a resumed run starts there
                first.flush()
                frames.flush()
                progress_file.write_text(json.dumps({"done": i + 1, "config": asdict(cfg)}))
            bar.update(1)
    bar.close()
    first.flush()
    frames.flush()
    del first, frames
    os.replace(partial_framed, framed_path)
    os.replace(partial_first, first_path)
    progress_file.unlink(missing_ok=True)


def _compute_features(ds: EpisodeDataset, cfg: EncoderConfig, cache_dir: Path, key: str, final: Path,
                      batch_frames: int, progress: bool) -> None:
    """Fill ``final`` with the backbone's features of every frame, resuming a partial run."""
    names = ds.demo_names
    t_len = ds.frames(names[0]).shape[0]
    encoder = ImageEncoder(cfg).eval()
    partial = cache_dir / f"{key}.partial.npy"
    progress_file = cache_dir / f"{key}.progress.json"
    done = 0
    if partial.exists() and progress_file.exists():
        done = int(json.loads(progress_file.read_text())["done"])
        out = np.load(partial, mmap_mode="r+", allow_pickle=False)
    else:
        out = np.lib.format.open_memmap(partial, mode="w+", dtype=np.float16,
                                        shape=(len(names), t_len, encoder.backbone_dim))
    bar = tqdm(total=len(names), initial=done, desc=f"features {cfg.backbone}@{cfg.image_size}", unit="ep",
               disable=not progress)
    with torch.inference_mode():
        for i in range(done, len(names)):
            frames = ds.frames(names[i])  # (T, H, W, 3) uint8
            feats = encoder.backbone_features(torch.from_numpy(frames), chunk_size=batch_frames)
            out[i] = feats.float().numpy().astype(np.float16)
            if (i + 1) % 16 == 0 or i + 1 == len(names):
                out.flush()
                progress_file.write_text(json.dumps({"done": i + 1, "config": asdict(cfg)}))
            bar.update(1)
    bar.close()
    del out
    os.replace(partial, final)
    progress_file.unlink(missing_ok=True)
