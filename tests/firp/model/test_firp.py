"""FIRP: training outputs feed the whole objective; scoring; padding."""

import torch

from firp.losses import firp_loss
from firp.model import FIRP

from .helpers import DB, TINY, assert_finite_grads, random_plan


def test_forward_train_outputs_and_the_whole_objective_backpropagates():
    model = FIRP(TINY)
    B, T = 3, 9
    feats, plan = torch.randn(B, T, DB), random_plan(B, T)
    out = model.forward_train(feats, plan, overshooting_distances=[2, 4])
    E, S = TINY.encoder.feature_dim, TINY.rssm.stoch_dim
    assert out["e"].shape == (B, T, E) and out["h"].shape == (B, T, TINY.rssm.deter_dim)
    assert out["open_loop"]["feat"].shape == (B, T - 1, E)
    assert out["overshoot"][4]["prior_mean"].shape == (B, T - 4, S)
    assert out["logits"].shape == out["logits_open_loop"].shape == (B,)
    assert out["weights"].shape == (B, T) and out["features_open_loop"].shape == (B, T, E)
    terms = firp_loss(out, plan, torch.tensor([1.0, 0.0, 1.0]), TINY.loss)
    assert set(terms) >= {"ce", "ce_open_loop", "kl", "re", "kl_overshoot", "re_overshoot", "ttc", "atc", "total"}
    assert all(torch.isfinite(v) for v in terms.values())
    terms["total"].backward()
    assert_finite_grads(model)


def test_score_shapes_and_determinism():
    model = FIRP(TINY).eval()
    feats, plan = torch.randn(2, DB), random_plan(2, 10)
    s = model.score(feats, plan)
    assert s.logits.shape == (2,) and s.weights.shape == (2, 10) and s.features.shape == (2, 10, TINY.encoder.feature_dim)
    torch.testing.assert_close(model.score(feats, plan).logits, s.logits)
    torch.testing.assert_close(s.weights.sum(1), torch.ones(2))


def test_score_ignores_padding_at_the_end():
    """A plan padded to a longer batch (mask False on the padding) scores as the plan alone."""
    model = FIRP(TINY).eval()
    feats, plan = torch.randn(1, DB), random_plan(1, 7)
    alone = model.score(feats, plan)
    padded = torch.cat([plan, random_plan(1, 4)], dim=1)
    mask = torch.tensor([[True] * 7 + [False] * 4])
    s = model.score(feats, padded, mask)
    torch.testing.assert_close(s.logits, alone.logits)
    torch.testing.assert_close(s.weights[:, :7], alone.weights)


def test_padding_does_not_change_the_training_objective():
    model = FIRP(TINY)
    feats, plan, labels = torch.randn(1, 8, DB), random_plan(1, 8), torch.tensor([1.0])
    kw = dict(sample=False, overshooting_distances=[2, 3], overshooting_stride=2)
    ref = firp_loss(model.forward_train(feats, plan, **kw), plan, labels, TINY.loss)
    feats_p = torch.cat([feats, torch.randn(1, 3, DB)], dim=1)
    plan_p = torch.cat([plan, random_plan(1, 3)], dim=1)
    mask = torch.tensor([[True] * 8 + [False] * 3])
    got = firp_loss(model.forward_train(feats_p, plan_p, mask, **kw), plan_p, labels, TINY.loss)
    for k in ("ce", "ce_open_loop", "kl", "re", "kl_overshoot", "re_overshoot", "ttc", "atc", "total"):
        torch.testing.assert_close(got[k], ref[k], msg=k)


def test_image_encoder_shares_the_projection():
    model = FIRP(TINY)
    enc = model.image_encoder()
    assert enc.projection is model.projection
    imgs = torch.randint(0, 256, (2, 40, 40, 3), dtype=torch.uint8)
    torch.testing.assert_close(enc(imgs), model.projection(enc.backbone_features(imgs)))


def test_description_loss_trains_the_descriptions_own_score_and_nothing_of_the_sequence():
    """``LossConfig.description``: the head's logit is the description's own score plus the pooled
    sequence's share, and the extra loss is the BCE of that score alone -- its gradient reaches the
    description's layers and the output layer, never the pooled sequence's query network."""
    from dataclasses import replace

    import pytest

    from firp.model.config import GeometryConfig, LossConfig

    cfg = replace(TINY, geometry=GeometryConfig(enabled=True, hidden=6, description="clearance"),
                  loss=replace(TINY.loss, description=0.5))
    model = FIRP(cfg)
    B, T = 4, 9
    feats, plan, labels = torch.randn(B, T, DB), random_plan(B, T), torch.tensor([1.0, 0.0, 1.0, 0.0])
    out = model.forward_train(feats, plan)
    head = model.head
    context = model.geometry(plan)
    q = head.q(out["e"])
    pooled = torch.einsum("bt,btq->bq", out["weights"], q)
    sequence_share = pooled @ head.out.weight[0, :TINY.head.q_dim]
    torch.testing.assert_close(out["logits_description"] + sequence_share, out["logits"])
    torch.testing.assert_close(out["logits_description"], head.description_logit(context))

    terms = firp_loss(out, plan, labels, cfg.loss)
    expected = torch.nn.functional.binary_cross_entropy_with_logits(out["logits_description"], labels)
    torch.testing.assert_close(terms["ce_description"], expected)
    without = firp_loss(out, plan, labels, replace(cfg.loss, description=0.0))
    torch.testing.assert_close(terms["total"] - without["total"], 0.5 * expected)

    model.zero_grad()
    terms["ce_description"].backward()
    assert all(p.grad is None or not p.grad.any() for p in head.q.parameters())
    assert head.context[0].weight.grad.abs().sum() > 0 and head.out.weight.grad[0, :TINY.head.q_dim].abs().sum() == 0

    with pytest.raises(ValueError, match="reads no plan description"):
        firp_loss(FIRP(TINY).forward_train(feats, plan), plan, labels, replace(TINY.loss, description=1.0))
    with pytest.raises(ValueError, match="description must be >= 0"):
        LossConfig(description=-1.0)
