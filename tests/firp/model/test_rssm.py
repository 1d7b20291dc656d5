"""RSSM: the paper's equations, the index convention, and what inference may see."""

import pytest
import torch

from firp.model import FIRP, RSSM, sample_overshooting_distances

from .helpers import DB, TINY, assert_finite_grads, random_plan

E, A = TINY.encoder.feature_dim, TINY.action_dim


def _rssm() -> RSSM:
    return RSSM(TINY.rssm, E, A)


def test_observe_shapes_and_gradients():
    rssm = _rssm()
    B, T = 3, 7
    out = rssm.observe(torch.randn(B, T, E), random_plan(B, T))
    H, S = TINY.rssm.deter_dim, TINY.rssm.stoch_dim
    assert out["h"].shape == (B, T, H)
    for k in ("post_mean", "post_std", "post_sample", "prior_mean", "prior_std", "prior_sample"):
        assert out[k].shape == (B, T, S)
    assert out["feat_prior"].shape == out["feat_post"].shape == (B, T, E)
    assert (out["post_std"] >= TINY.rssm.min_std).all() and (out["prior_std"] >= TINY.rssm.min_std).all()
    sum(v.sum() for v in out.values()).backward()
    assert_finite_grads(rssm)


def test_first_step_starts_from_zero_h0_and_s0():
    """h_1 = GRU(h_0 = 0, f(s_0 = 0, a_1)) and s_1 ~ g(h_1, e_1), computed by hand."""
    rssm = _rssm()
    e, a = torch.randn(2, 4, E), random_plan(2, 4)
    out = rssm.observe(e, a, sample=False)
    h0 = torch.zeros(2, TINY.rssm.deter_dim)
    s0 = torch.zeros(2, TINY.rssm.stoch_dim)
    h1 = rssm.rnn(rssm.f(torch.cat([s0, a[:, 0]], -1)), h0)
    torch.testing.assert_close(out["h"][:, 0], h1)
    mean1, _ = rssm.posterior(h1, e[:, 0])
    torch.testing.assert_close(out["post_mean"][:, 0], mean1)
    # and step 2 uses s_1 and a_2 (the action of index 1)
    h2 = rssm.rnn(rssm.f(torch.cat([mean1, a[:, 1]], -1)), h1)
    torch.testing.assert_close(out["h"][:, 1], h2)


def test_rollout_from_first_is_observe_at_index_0_then_the_prior():
    rssm = _rssm()
    e, a = torch.randn(2, 6, E), random_plan(2, 6)
    obs = rssm.observe(e, a, sample=False)
    roll = rssm.rollout_from_first(e[:, 0], a, sample=False)
    torch.testing.assert_close(roll["h_1"], obs["h"][:, 0])
    ref = rssm.imagine(obs["h"][:, 0], obs["post_mean"][:, 0], a[:, 1:], sample=False)
    torch.testing.assert_close(roll["prior"]["feat"], ref["feat"])
    assert roll["features"].shape == (2, 6, E)
    torch.testing.assert_close(roll["features"][:, 0], e[:, 0])  # the head reads the real e_1


def test_inference_reads_only_the_first_frame():
    """FIRP.score given all T frames: changing frames 2..T changes nothing, and no gradient
    reaches them; changing frame 1 does change the score."""
    model = FIRP(TINY)
    feats = torch.randn(2, 8, DB, requires_grad=True)
    a = random_plan(2, 8)
    s1 = model.score(feats, a)
    (s1.logits.sum() + s1.features.sum()).backward()
    assert feats.grad[:, 1:].abs().sum() == 0 and feats.grad[:, 0].abs().sum() > 0
    changed = feats.detach().clone()
    changed[:, 1:] = torch.randn_like(changed[:, 1:]) * 10
    s2 = model.score(changed, a)
    torch.testing.assert_close(s1.logits, s2.logits)
    torch.testing.assert_close(s1.features, s2.features)
    changed[:, 0] += 1.0
    assert not torch.allclose(model.score(changed, a).logits, s1.logits)


def test_overshoot_matches_observe_and_the_open_loop():
    rssm = _rssm()
    T = 7
    e, a = torch.randn(2, T, E), random_plan(2, T)
    obs = rssm.observe(e, a, sample=False)
    h, s = obs["h"], obs["post_mean"]
    # tau = 1 reproduces the one-step priors of observe (targets 1..T-1)
    one = rssm.overshoot(h, s, a, 1, sample=False)
    torch.testing.assert_close(one["prior_mean"], obs["prior_mean"][:, 1:])
    # tau = 3, target index 5: three prior steps from the filtered latent at index 2
    three = rssm.overshoot(h, s, a, 3, sample=False)
    assert three["prior_mean"].shape == (2, T - 3, TINY.rssm.stoch_dim)
    ref = rssm.imagine(h[:, 2], s[:, 2], a[:, 3:6], sample=False)
    torch.testing.assert_close(three["prior_mean"][:, 5 - 3], ref["prior_mean"][:, -1])
    torch.testing.assert_close(three["feat"][:, 5 - 3], ref["feat"][:, -1])
    # tau = T-1 has one target, the last step of the open loop from index 0
    last = rssm.overshoot(h, s, a, T - 1, sample=False)
    open_loop = rssm.imagine(h[:, 0], s[:, 0], a[:, 1:], sample=False)
    torch.testing.assert_close(last["prior_mean"][:, 0], open_loop["prior_mean"][:, -1])
    with pytest.raises(ValueError):
        rssm.overshoot(h, s, a, T, sample=False)


def test_sampling_is_reparametrised_and_means_are_deterministic():
    rssm = _rssm()
    e, a = torch.randn(2, 5, E), random_plan(2, 5)
    r1 = rssm.rollout_from_first(e[:, 0], a, sample=False)["features"]
    r2 = rssm.rollout_from_first(e[:, 0], a, sample=False)["features"]
    torch.testing.assert_close(r1, r2)
    assert not torch.allclose(rssm.rollout_from_first(e[:, 0], a, sample=True)["features"], r1)


def test_sample_overshooting_distances():
    taus = sample_overshooting_distances(T=120, n=3, max_tau=30, generator=torch.Generator().manual_seed(1))
    assert len(taus) == 3 and len(set(taus)) == 3 and all(2 <= t <= 30 for t in taus)
    assert sample_overshooting_distances(T=3, n=5) == [2]
    assert sample_overshooting_distances(T=2, n=5) == []


def test_strided_overshoot_is_the_full_one_at_fewer_starts():
    rssm = _rssm()
    e, a = torch.randn(2, 11, E), random_plan(2, 11)
    obs = rssm.observe(e, a, sample=False)
    full = rssm.overshoot(obs["h"], obs["post_mean"], a, 3, sample=False)
    strided = rssm.overshoot(obs["h"], obs["post_mean"], a, 3, sample=False, stride=3)
    assert strided["targets"].tolist() == [3, 6, 9]
    torch.testing.assert_close(strided["prior_mean"], full["prior_mean"][:, [0, 3, 6]])
    torch.testing.assert_close(full["targets"], torch.arange(3, 11))
