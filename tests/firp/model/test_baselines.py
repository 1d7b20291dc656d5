"""Baselines: one call signature for all, shapes, gradients, and who may see which frames."""

import dataclasses

import pytest
import torch

from firp.losses import classification_loss
from firp.model import MODEL_KINDS, BaselineConfig, build_model, plan_vector

from .helpers import DB, TINY, assert_finite_grads, random_plan


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_one_training_step_for_every_model(kind):
    model = build_model(kind, TINY)
    B, T = 3, 10
    feats, plan = torch.randn(B, T, DB), random_plan(B, T)
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[2, 7:] = False
    out = model.forward_train(feats, plan, mask)
    assert out["logits"].shape == (B,)
    classification_loss(out["logits"], torch.tensor([1, 0, 1])).backward()
    if kind == "firp":  # the RSSM's posterior/decoder only get gradients from the future-prediction loss
        return
    assert_finite_grads(model)


@pytest.mark.parametrize("kind", [k for k in MODEL_KINDS if k != "oracle"])
def test_models_that_score_before_execution_read_only_the_first_frame(kind):
    model = build_model(kind, TINY).eval()
    assert not model.requires_future_frames
    feats, plan = torch.randn(2, 10, DB), random_plan(2, 10)
    s = model.score(feats, plan)
    assert s.logits.shape == (2,)
    changed = feats.clone()
    changed[:, 1:] = torch.randn_like(changed[:, 1:])
    torch.testing.assert_close(model.score(changed, plan).logits, s.logits)
    torch.testing.assert_close(model.score(feats[:, 0], plan).logits, s.logits)  # (B, Db) works too


def test_oracle_uses_the_executed_frames():
    model = build_model("oracle", TINY).eval()
    assert model.requires_future_frames
    feats = torch.randn(2, 10, DB)
    s = model.score(feats)
    changed = feats.clone()
    changed[:, -1] += 1.0
    assert not torch.allclose(model.score(changed).logits, s.logits)
    with pytest.raises(ValueError):
        model.score(feats[:, 0])


def test_gru_baseline_predicts_a_feature_sequence_for_the_head():
    model = build_model("gru", TINY)
    feats, plan = torch.randn(2, 6, DB), random_plan(2, 6)
    out = model.forward_train(feats, plan)
    assert out["features_pred"].shape == out["e"].shape == (2, 6, TINY.encoder.feature_dim)
    torch.testing.assert_close(out["features_pred"][:, 0], out["e"][:, 0])
    torch.testing.assert_close(out["weights"].sum(1), torch.ones(2))


def test_plan_vector_flatten_pads_masks_and_rejects_long_plans():
    plan = random_plan(2, 5)
    mask = torch.tensor([[True] * 5, [True] * 3 + [False] * 2])
    v = plan_vector(plan, mask, "flatten", max_T=8)
    assert v.shape == (2, 8 * 16)
    torch.testing.assert_close(v[1], plan_vector(plan[1:, :3], None, "flatten", max_T=8)[0])
    with pytest.raises(ValueError, match="max_T"):
        plan_vector(random_plan(1, 9), None, "flatten", max_T=8)
    m = plan_vector(plan, mask, "mean", max_T=8)
    torch.testing.assert_close(m[1], plan[1, :3].mean(0))


def test_a_mlp_mean_pooling_accepts_any_length():
    cfg = dataclasses.replace(TINY, baseline=BaselineConfig(hidden=9, plan_pooling="mean", max_T=4))
    model = build_model("a_mlp", cfg)
    assert model.score(None, random_plan(2, 30)).logits.shape == (2,)
