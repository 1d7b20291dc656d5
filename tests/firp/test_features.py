"""The backbone feature cache: right features, computed once, never stale, resumed after a crash."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from firp.core.episodes import EpisodeDataset, EpisodeRecord, consolidate, write_episode_part
from firp.features import cache_key, cached_features
from firp.model.config import EncoderConfig
from firp.model.encoder import ImageEncoder

CFG = EncoderConfig(image_size=32)  # the pinned EfficientNet-Lite0, small frames


def _direct(dataset) -> np.ndarray:
    encoder = ImageEncoder(CFG).eval()
    with EpisodeDataset(dataset) as ds, torch.inference_mode():
        return np.stack([encoder.backbone_features(torch.from_numpy(ds.frames(n))).numpy() for n in ds.demo_names])


class CountingBackbone:
    """Counts backbone calls (one per episode) and can fail at a given one, as a killed run does."""

    def __init__(self, monkeypatch, fail_at: int | None = None):
        self.calls = 0
        original = ImageEncoder.backbone_features
        counter = self

        def counted(encoder, frames, *args, **kwargs):
            counter.calls += 1
            if fail_at is not None and counter.calls == fail_at:
                raise KeyboardInterrupt("killed mid-run")
            return original(encoder, frames, *args, **kwargs)

        monkeypatch.setattr(ImageEncoder, "backbone_features", counted)


def test_features_are_the_backbones_and_are_computed_once(tiny_dataset, tmp_path, monkeypatch):
    feats = cached_features(tiny_dataset, CFG, tmp_path, progress=False)
    assert feats.dtype == np.float16 and feats.shape == (20, 10, CFG.backbone_dim)
    np.testing.assert_allclose(feats.astype(np.float32), _direct(tiny_dataset), rtol=2e-3, atol=2e-3)
    counter = CountingBackbone(monkeypatch)
    again = cached_features(tiny_dataset, CFG, tmp_path, progress=False)
    assert counter.calls == 0
    np.testing.assert_array_equal(again, feats)


def test_another_dataset_or_backbone_setting_never_gets_stale_features(tiny_dataset, tmp_path):
    first = np.array(cached_features(tiny_dataset, CFG, tmp_path, progress=False))
    # the same episodes with one frame changed: another content hash, another cache entry
    changed = tmp_path / "changed"
    with EpisodeDataset(tiny_dataset) as ds:
        for i, name in enumerate(ds.demo_names):
            record = ds.episode(name)
            if i == 3:
                frames = record.frames.copy()
                frames[0] = 255 - frames[0]
                record = EpisodeRecord(frames, record.actions, record.states, record.success, record.attrs)
            write_episode_part(changed / "parts", i, record)
        attrs = {k: v for k, v in ds.attrs.items() if k in ("fps", "T", "task")}
    consolidate(changed / "parts", changed / "tiny.h5", attrs)
    other = np.array(cached_features(changed / "tiny.h5", CFG, tmp_path, progress=False))
    assert np.abs(other[3, 0].astype(np.float32) - first[3, 0]).max() > 1e-2  # the changed frame is recomputed
    np.testing.assert_array_equal(other[:3], first[:3])
    bigger = cached_features(tiny_dataset, EncoderConfig(image_size=64), tmp_path, progress=False)
    assert not np.array_equal(np.asarray(bigger), first)
    assert len(list(tmp_path.glob("*.npy"))) == 3  # three entries side by side, none overwritten
    with EpisodeDataset(tiny_dataset) as ds:
        assert cache_key(ds.content_hash(), CFG) != cache_key(ds.content_hash(), EncoderConfig(image_size=64))


def test_an_interrupted_extraction_resumes_where_it_stopped(tiny_dataset, tmp_path, monkeypatch):
    uninterrupted = np.array(cached_features(tiny_dataset, CFG, tmp_path / "whole", progress=False))
    counter = CountingBackbone(monkeypatch, fail_at=19)  # progress is saved every 16 episodes
    with pytest.raises(KeyboardInterrupt):
        cached_features(tiny_dataset, CFG, tmp_path / "cache", progress=False)
    assert not list((tmp_path / "cache").glob("*[0-9a-f].npy"))  # no finished entry: readers cannot see half
    assert list((tmp_path / "cache").glob("*.partial.npy"))
    monkeypatch.undo()
    counter = CountingBackbone(monkeypatch)
    resumed = cached_features(tiny_dataset, CFG, tmp_path / "cache", progress=False)
    assert counter.calls == 20 - 16  # only the episodes after the last saved progress
    np.testing.assert_array_equal(np.asarray(resumed), uninterrupted)
    assert not list((tmp_path / "cache").glob("*.partial.npy")) and not list((tmp_path / "cache").glob("*.json"))


def test_a_randomly_initialised_backbone_is_never_cached(tiny_dataset, tmp_path):
    with pytest.raises(ValueError, match="encoder.backbone: only the pretrained efficientnet_lite0"):
        cached_features(tiny_dataset, EncoderConfig(backbone="small_cnn", image_size=32), tmp_path, progress=False)
    shutil.rmtree(tmp_path)


def test_a_dataset_of_initial_frames_caches_them_and_the_framed_episodes_every_frame(tiny_dataset, tmp_path,
                                                                                      monkeypatch):
    """``firp collect --framed``: features of every initial frame and of every frame of the framed episodes, equal
    to the backbone's; a killed run resumes; load_sequences serves both through FrameFeatures."""
    from firp.core.episodes import EpisodeDataset as Dataset
    from firp.data import load_sequences
    from firp.features import cached_initial_features

    parts = tmp_path / "parts"
    with Dataset(tiny_dataset) as ds:
        for i, name in enumerate(ds.demo_names):
            record = ds.episode(name)
            if i % 3:  # episodes 0, 3, 6, ... keep every frame
                record.frames = record.frames[:1].copy()
            write_episode_part(parts, i, record)
    mixed = tmp_path / "mixed.h5"
    consolidate(parts, mixed, {"fps": 4, "T": 10, "task": "stacking"})
    direct = _direct(tiny_dataset)
    counter = CountingBackbone(monkeypatch, fail_at=3)
    with pytest.raises(KeyboardInterrupt):
        cached_initial_features(mixed, CFG, tmp_path / "cache", batch_frames=4, progress=False)
    first, framed = cached_initial_features(mixed, CFG, tmp_path / "cache", batch_frames=4, progress=False)
    assert counter.calls < 20  # resumed, not redone from the start
    assert first.shape == (20, CFG.backbone_dim) and framed.shape == (7, 10, CFG.backbone_dim)
    np.testing.assert_allclose(first.astype(np.float32), direct[:, 0], rtol=2e-3, atol=2e-3)
    np.testing.assert_allclose(framed.astype(np.float32), direct[::3], rtol=2e-3, atol=2e-3)
    data = load_sequences(mixed, CFG, tmp_path / "cache", progress=False)
    assert data.framed.tolist() == [i % 3 == 0 for i in range(20)]
    np.testing.assert_allclose(data.features[torch.tensor([3])][0].numpy(), direct[3], rtol=2e-3, atol=2e-3)
    np.testing.assert_allclose(data.features[torch.tensor([4])][0].numpy(), np.repeat(direct[4, :1], 10, 0),
                               rtol=2e-3, atol=2e-3)
