"""The shared training loop on a synthetic micro-dataset whose label is learnable from the plan."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import firp.model.firp
import firp.train

from firp.data import SequenceData, stratified_split
from firp.train import TrainConfig, predict, train_model
from tests.firp.model.helpers import DB, TINY, random_plan

T = 12


def micro_data(n: int = 48, seed: int = 0) -> SequenceData:
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    actions = random_plan(n, T)
    labels = (actions[:, :, 7:].mean(dim=(1, 2)) > 0).float()  # success decided by the plan
    features = torch.randn(n, T, DB, generator=g) + labels[:, None, None]
    return SequenceData(features, actions, labels, "synthetic", [f"demo_{i}" for i in range(n)])


def config(**kw) -> TrainConfig:
    base = TrainConfig(epochs=4, batch_size=16, threads=1, overshooting_n=1, overshooting_max_tau=5,
                       overshooting_stride=2, patience=10, e_stop_e=2, model=replace(TINY, baseline=replace(
                           TINY.baseline, max_T=T)))
    return replace(base, **kw)


@pytest.fixture(scope="module")
def splits():
    data = micro_data()
    rest, valid = stratified_split(data.labels.numpy(), 0.25, seed=0)
    return data.subset(rest), data.subset(valid)


@pytest.mark.parametrize("kind", ["firp", "a_mlp", "a_mlp_image", "gru", "oracle"])
def test_every_kind_trains_and_predicts(kind, splits):
    train, valid = splits
    result = train_model(config(kind=kind), train, valid, progress=False)
    assert len(result.history) == 4 and 0.0 <= result.best_val_balanced_accuracy <= 1.0
    probs = predict(result.model, valid)
    assert probs.shape == (len(valid),) and np.all((probs >= 0) & (probs <= 1))


def test_same_seed_same_model_and_resume_equals_uninterrupted(tmp_path, splits, monkeypatch):
    train, valid = splits
    cfg = config(epochs=4, seed=3)
    full = train_model(cfg, train, valid, progress=False)
    again = train_model(cfg, train, valid, progress=False)
    np.testing.assert_allclose(predict(full.model, valid), predict(again.model, valid), atol=1e-6)
    # killed right after the checkpoint of epoch 1, then resumed from it
    ckpt = tmp_path / "run"
    real_save = firp.train._save_checkpoint

    def save_then_die(*args, **kwargs):
        real_save(*args, **kwargs)
        if args[7] == 1:  # epoch
            raise KeyboardInterrupt

    monkeypatch.setattr(firp.train, "_save_checkpoint", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        train_model(cfg, train, valid, checkpoint_dir=ckpt, progress=False)
    monkeypatch.setattr(firp.train, "_save_checkpoint", real_save)
    assert json.loads((ckpt / "state.json").read_text())["epoch"] == 1
    resumed = train_model(cfg, train, valid, checkpoint_dir=ckpt, progress=False)
    assert [h["epoch"] for h in resumed.history] == [0, 1, 2, 3]
    np.testing.assert_allclose(predict(resumed.model, valid), predict(full.model, valid), atol=1e-5)


def test_checkpoint_of_another_config_is_refused(tmp_path, splits):
    train, valid = splits
    train_model(config(epochs=1), train, valid, checkpoint_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="different training config"):
        train_model(config(epochs=1, lr=0.5), train, valid, checkpoint_dir=tmp_path, progress=False)


def test_a_learnable_label_is_learned(splits):
    train, valid = splits
    cfg = config(kind="a_mlp", epochs=30, lr=1e-2, patience=30)
    # mean pooling makes this label (the plan's mean joint target) linear in the input
    cfg = replace(cfg, model=replace(cfg.model, baseline=replace(cfg.model.baseline, plan_pooling="mean")))
    result = train_model(cfg, train, valid, progress=False)
    assert result.best_val_balanced_accuracy >= 0.75


def test_no_early_stop_before_min_epochs(splits):
    train, valid = splits
    early = train_model(config(kind="a_mlp", epochs=8, patience=1, lr=0.0), train, valid, progress=False)
    assert len(early.history) == 2  # lr 0: never better than epoch 0, stops after `patience` epochs
    held = train_model(config(kind="a_mlp", epochs=8, patience=1, lr=0.0, min_epochs=6), train, valid, progress=False)
    assert len(held.history) == 6


def test_checkpoint_without_a_newer_config_field_resumes(tmp_path, splits):
    train, valid = splits
    cfg = config(epochs=1, kind="a_mlp")
    train_model(cfg, train, valid, checkpoint_dir=tmp_path, progress=False)
    state = json.loads((tmp_path / "state.json").read_text())
    del state["config"]["min_epochs"]  # as written before the field existed
    (tmp_path / "state.json").write_text(json.dumps(state))
    resumed = train_model(cfg, train, valid, checkpoint_dir=tmp_path, progress=False)
    assert len(resumed.history) == 1


@pytest.mark.parametrize("kind", ["a_mlp", "a_mlp_image"])
def test_a_recipe_fitted_to_longer_plans_flattens_them(kind, splits):
    """Plans longer than the flattening baselines' max_T (pick & place's 200 steps against 120) are refused
    by the recipe as written and trained once it is fitted to the dataset's horizon; shorter ones keep it."""
    train, valid = splits
    short = config(kind=kind, epochs=1, model=replace(TINY, baseline=replace(TINY.baseline, max_T=T - 4)))
    with pytest.raises(ValueError, match=f"plan has T={T} steps"):
        train_model(short, train, valid, progress=False)
    fitted = short.fit_to_plans(T)
    assert fitted.model.baseline.max_T == T and fitted.fit_to_plans(T - 8) is fitted
    assert len(train_model(fitted, train, valid, progress=False).history) == 1


def initial_only(data: SequenceData, keep_frames: int) -> SequenceData:
    """``data`` as a ``firp collect --framed`` dataset: the first ``keep_frames`` episodes framed, the rest with their
    initial frame alone."""
    from firp.data import FrameFeatures

    full = data.features[torch.arange(len(data))]
    row = torch.where(torch.arange(len(data)) < keep_frames, torch.arange(len(data)), torch.tensor(-1))
    return SequenceData(FrameFeatures(full[:, 0], full[:keep_frames], row), data.actions, data.labels, "mixed",
                        data.demo_names)


def test_frame_features_index_like_the_tensor_they_stand_for():
    data = micro_data(12)
    full = data.features[torch.arange(12)]
    mixed = initial_only(data, 5).features
    assert mixed.shape == (12, T, DB) and mixed.framed.tolist() == [True] * 5 + [False] * 7
    idx = torch.tensor([7, 1, 4, 9])
    got = mixed[idx]
    torch.testing.assert_close(got[1], full[1]) and torch.testing.assert_close(got[2], full[4])
    torch.testing.assert_close(got[0], full[7, :1].expand(T, DB))  # an initial-only row repeats frame 0
    torch.testing.assert_close(mixed[idx, 0], full[idx, 0])
    sub = mixed.subset(torch.tensor([9, 4, 2]))
    assert sub.framed.tolist() == [False, True, True] and sub.frames.shape[0] == 2
    torch.testing.assert_close(sub[torch.arange(3)][2], full[2])
    from firp.data import FrameFeatures

    both = FrameFeatures.concat([sub, mixed.subset(torch.tensor([3]))])
    assert both.framed.tolist() == [False, True, True, True]
    torch.testing.assert_close(both[torch.tensor([3])][0], full[3])


def test_episodes_with_only_their_initial_frame_train_firp_s_open_loop(monkeypatch):
    """FIRP trains on a mixed set: framed episodes give every term, the others the open loop's classification
    through forward_initial; the Oracle, which reads every frame, is refused such episodes."""
    data = initial_only(micro_data(48), 12)
    rest, valid = stratified_split(data.labels.numpy(), 0.25, seed=0)
    train, valid = data.subset(rest), data.subset(valid)
    seen: list[int] = []
    real = firp.model.firp.FIRP.forward_initial

    def spy(self, first, actions, *args, **kwargs):
        assert first.ndim == 2  # the initial frame alone
        seen.append(int(first.shape[0]))
        return real(self, first, actions, *args, **kwargs)

    monkeypatch.setattr(firp.model.firp.FIRP, "forward_initial", spy)
    result = train_model(config(epochs=2), train, valid, progress=False)
    assert sum(seen) == 2 * int((~train.framed).sum())  # every initial-only episode, every epoch
    assert {"ce_open_loop", "kl", "total"} <= set(result.history[-1])
    with pytest.raises(ValueError, match="framed episodes only"):
        train_model(config(kind="oracle", epochs=1), train, valid, progress=False)


def test_a_recipe_reading_the_events_takes_the_kinematics_from_the_dataset():
    from firp.model.config import PlanEventsConfig

    data = micro_data(8)
    cfg = config(model=replace(TINY, events=PlanEventsConfig(enabled=True)))
    with pytest.raises(ValueError, match="carries none"):
        cfg.fit_to_data(data)
    data.attrs["kinematics"] = {"format": "firp-serial-chain-v1"}
    assert cfg.fit_to_data(data).model.events.kinematics == {"format": "firp-serial-chain-v1"}


def test_devices_are_named_and_a_missing_gpu_is_an_error_not_a_fall_back():
    from firp.train import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="none of auto, cpu, cuda"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")


def test_the_gpu_check_script_trains_and_scores_on_the_cpu_here(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "gpu_check.py"
    spec = importlib.util.spec_from_file_location("gpu_check", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--device", "cpu", "--episodes", "64", "--epochs", "1", "--out", str(tmp_path / "g.json")]) == 0
    figures = json.loads((tmp_path / "g.json").read_text())
    assert figures["device"] == "cpu" and figures["max_probability_difference_device_vs_cpu"] == 0.0
