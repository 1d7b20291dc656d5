"""Action chunking: k plan steps per RSSM transition (``FIRPConfig.action_chunk``)."""

from dataclasses import replace

import pytest
import torch

from firp.losses import firp_loss
from firp.model import FIRP
from firp.model.firp import chunk_actions, chunk_frame_index, spread_chunk_weights

from .helpers import DB, TINY, assert_finite_grads, random_plan


@pytest.mark.parametrize("T, k, expected", [
    (8, 4, [0, 7]),  # first chunk observes the initial image, the next one its own last frame
    (12, 4, [0, 7, 11]),
    (10, 4, [0, 7, 9]),  # a short last chunk observes the plan's last frame
    (5, 1, [0, 1, 2, 3, 4]),
])
def test_frame_index(T, k, expected):
    assert chunk_frame_index(T, k) == expected


def test_chunk_actions_concatenates_rows_and_pads_with_the_last_row():
    a = torch.arange(2 * 10 * 3, dtype=torch.float32).reshape(2, 10, 3)
    c = chunk_actions(a, 4)
    assert c.shape == (2, 3, 12)
    assert torch.equal(c[:, 0], a[:, 0:4].reshape(2, 12))
    assert torch.equal(c[:, 2, :6], a[:, 8:10].reshape(2, 6))
    assert torch.equal(c[:, 2, 6:9], a[:, 9]) and torch.equal(c[:, 2, 9:], a[:, 9])
    assert chunk_actions(a, 1) is a


def test_chunk_weights_land_on_the_chunk_frames_and_keep_their_sum():
    w = torch.softmax(torch.randn(3, 3), dim=-1)
    full = spread_chunk_weights(w, 10, 4)
    assert full.shape == (3, 10)
    assert torch.allclose(full.sum(dim=1), torch.ones(3))
    assert torch.equal(full[:, [0, 7, 9]], w)
    assert torch.count_nonzero(full[:, [1, 2, 3, 4, 5, 6, 8]]) == 0


def test_chunked_model_trains_and_scores_on_plan_steps():
    cfg = replace(TINY, action_chunk=4)
    model = FIRP(cfg)
    B, T = 3, 10
    feats, actions = torch.randn(B, T, DB), random_plan(B, T)
    out = model.forward_train(feats, actions, overshooting_distances=[2])
    assert out["e"].shape == (B, 3, cfg.encoder.feature_dim)
    assert out["categories"].shape == (B, 3)
    terms = firp_loss(out, actions, torch.tensor([1.0, 0.0, 1.0]), cfg.loss)
    terms["total"].backward()
    assert_finite_grads(model)
    model.eval()
    score = model.score(feats[:, 0], actions)
    assert score.logits.shape == (B,)
    assert score.weights.shape == (B, T)  # attention reported per plan step, for the service
    assert torch.allclose(score.weights.sum(dim=1), torch.ones(B))
    assert score.features.shape == (B, 3, cfg.encoder.feature_dim)


def test_prediction_targets_do_not_train_the_projection():
    """With ``stop_target_gradient`` the reconstruction term leaves the projection untouched."""
    model = FIRP(TINY)
    out = model.forward_train(torch.randn(2, 8, DB), random_plan(2, 8))
    terms = firp_loss(out, random_plan(2, 8), torch.tensor([1.0, 0.0]), TINY.loss)
    terms["re"].backward()
    assert all(p.grad is None or torch.count_nonzero(p.grad) == 0 for p in model.projection.parameters())
    through = FIRP(replace(TINY, loss=replace(TINY.loss, stop_target_gradient=False)))
    out = through.forward_train(torch.randn(2, 8, DB), random_plan(2, 8))
    firp_loss(out, random_plan(2, 8), torch.tensor([1.0, 0.0]), TINY.loss)["re"].backward()
    assert any(p.grad is not None and torch.count_nonzero(p.grad) > 0 for p in through.projection.parameters())


@pytest.mark.parametrize("k", [1, 4])
def test_open_loop_on_means_is_what_inference_scores(k):
    """With ``open_loop_sample`` off, training classifies exactly the sequence ``score`` reads; with it on
    (the paper), the training open loop is a noisy sample of it."""
    cfg = replace(TINY, action_chunk=k)
    model = FIRP(replace(cfg, loss=replace(cfg.loss, open_loop_sample=False))).eval()
    B, T = 3, 10
    feats, actions = torch.randn(B, T, DB), random_plan(B, T)
    torch.manual_seed(0)
    out = model.forward_train(feats, actions, sample=True)
    score = model.score(feats[:, 0], actions)
    assert torch.allclose(out["logits_open_loop"], score.logits, atol=1e-5)
    assert torch.allclose(out["features_open_loop"], score.features, atol=1e-5)
    sampled = FIRP(cfg).eval()
    sampled.load_state_dict(model.state_dict())
    noisy = sampled.forward_train(feats, actions, sample=True)
    assert not torch.allclose(noisy["features_open_loop"][:, 1:], score.features[:, 1:], atol=1e-3)
