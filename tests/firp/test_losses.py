"""Losses and TCR against values computed by hand on tiny 2-D inputs."""

import math

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from firp.losses import (
    atc,
    classification_loss,
    feature_reconstruction,
    kl_gaussian,
    overshooting_kl,
    overshooting_reconstruction,
    tcr,
    transition_directions,
    ttc,
    ttc_terms,
)

PI = math.pi


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def _path(*points) -> torch.Tensor:
    """A (1, T, 2) feature sequence through the given 2-D points."""
    return torch.tensor([points], dtype=torch.float64)


# ---- KL, reconstruction, classification ------------------------------------------------------


def test_kl_matches_torch_distributions_summed_over_dims_averaged_over_batch_and_time():
    mq, mp = torch.randn(3, 5, 4), torch.randn(3, 5, 4)
    sq, sp = torch.rand(3, 5, 4) + 0.1, torch.rand(3, 5, 4) + 0.1
    ref = kl_divergence(Normal(mq, sq), Normal(mp, sp)).sum(-1).mean()
    torch.testing.assert_close(kl_gaussian(mq, sq, mp, sp), ref)
    assert kl_gaussian(mq, sq, mq, sq).abs() < 1e-6
    mask = torch.zeros(3, 5, dtype=torch.bool)
    mask[0, :2] = True
    ref_masked = kl_divergence(Normal(mq[0, :2], sq[0, :2]), Normal(mp[0, :2], sp[0, :2])).sum(-1).mean()
    torch.testing.assert_close(kl_gaussian(mq, sq, mp, sp, mask), ref_masked)
    assert kl_gaussian(mq, sq, mq, sq, free_nats=1.5) == pytest.approx(1.5)


def test_feature_reconstruction_is_the_mean_l2_norm():
    e = torch.tensor([[[0.0, 0.0], [3.0, 4.0]]])  # errors: |(0,0)| = 0, |(3,4)| = 5
    e_hat = torch.zeros_like(e)
    assert feature_reconstruction(e, e_hat).item() == pytest.approx(2.5, abs=1e-5)  # (0 + 5) / 2
    assert feature_reconstruction(e, e_hat, squared=True).item() == pytest.approx(12.5)  # (0 + 25) / 2
    assert feature_reconstruction(e, e_hat, mask=torch.tensor([[False, True]])).item() == pytest.approx(5.0)
    # a perfect prediction has a finite gradient (the plain norm's is 0/0)
    e_hat = e.clone().requires_grad_(True)
    feature_reconstruction(e, e_hat).backward()
    assert torch.isfinite(e_hat.grad).all()


def test_classification_loss_is_bce_with_optional_positive_weight():
    logits = torch.tensor([0.0, 2.0])
    labels = torch.tensor([True, False])
    # -log(sigmoid(0)) = log 2; -log(1 - sigmoid(2)) = log(1 + e^2)
    expected = (math.log(2) + math.log(1 + math.e**2)) / 2
    assert classification_loss(logits, labels).item() == pytest.approx(expected, rel=1e-5)
    assert classification_loss(logits, labels, pos_weight=3.0).item() == pytest.approx(
        (3 * math.log(2) + math.log(1 + math.e**2)) / 2, rel=1e-5)


def test_overshooting_terms_average_over_prediction_sets_and_stop_posterior_gradients():
    B, T, S = 2, 6, 3
    pm = torch.randn(B, T, S, requires_grad=True)
    ps = (torch.rand(B, T, S) + 0.2).requires_grad_(True)
    open_m, open_s = torch.randn(B, T - 1, S), torch.rand(B, T - 1, S) + 0.2  # from index 0: targets 1..5
    tau_m, tau_s = torch.randn(B, T - 3, S), torch.rand(B, T - 3, S) + 0.2  # tau = 3: targets 3..5
    got = overshooting_kl(pm, ps, [open_m, tau_m], [open_s, tau_s], [1, 3])
    ref = (kl_gaussian(pm[:, 1:], ps[:, 1:], open_m, open_s) + kl_gaussian(pm[:, 3:], ps[:, 3:], tau_m, tau_s)) / 2
    torch.testing.assert_close(got, ref)
    assert got.grad_fn is None or not got.requires_grad  # the posterior is a fixed target
    assert overshooting_kl(pm, ps, [open_m], [open_s], [1], stop_posterior_grad=False).requires_grad
    e = torch.randn(B, T, 4)
    preds = [torch.randn(B, T - 1, 4), torch.randn(B, T - 3, 4)]
    torch.testing.assert_close(
        overshooting_reconstruction(e, preds, [1, 3]),
        (feature_reconstruction(e[:, 1:], preds[0]) + feature_reconstruction(e[:, 3:], preds[1])) / 2,
    )
    assert overshooting_kl(pm, ps, [], [], []).item() == 0.0


# ---- TTC ---------------------------------------------------------------------------------------


def test_transition_directions():
    e = _path((0, 0), (1, 0), (1, 2))
    torch.testing.assert_close(transition_directions(e), torch.tensor([[[1.0, 0.0], [0.0, 2.0]]], dtype=torch.float64))


def test_ttc_by_hand_right_angle_turns():
    """e_1..e_6 = (0,0) (1,0) (2,0) (2,1) (1,1) (1,2)
    d_2..d_6 = (1,0) (1,0) (0,1) (-1,0) (0,1)
    theta_3 = angle(d_3, d_2) = 0, theta_4 = angle((0,1), (1,0)) = pi/2,
    theta_5 = angle((-1,0), (0,1)) = pi/2, theta_6 = angle((0,1), (-1,0)) = pi/2
    c_t exists for t = 4..T-1 = 4, 5:
      c_4 = 2 theta_4 - theta_3 - theta_5 = pi - 0 - pi/2 = pi/2
      c_5 = 2 theta_5 - theta_4 - theta_6 = pi - pi/2 - pi/2 = 0
    R_sm = (pi/2)^2 = pi^2/4 = 2.4674, R_sp = pi/2 = 1.5708, R_TTC = 4.0382."""
    e = _path((0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (1, 2))
    r_sm, r_sp = ttc_terms(e)
    assert r_sm.item() == pytest.approx(PI**2 / 4, abs=1e-6)
    assert r_sp.item() == pytest.approx(PI / 2, abs=1e-6)
    assert ttc(e).item() == pytest.approx(PI**2 / 4 + PI / 2, abs=1e-6)


def test_ttc_by_hand_constant_turning_costs_nothing_and_a_kink_does():
    """d = (1,0) (1,1) (0,1) (-1,1) (-1,0): each turns 45 degrees, theta_3..theta_6 = pi/4,
    so every c_t = 2 pi/4 - pi/4 - pi/4 = 0.
    Now change the last step to keep going straight: d_6 = (-1,1) (same as d_5), theta_6 = 0:
    c_4 = 0, c_5 = 2 pi/4 - pi/4 - 0 = pi/4; R_TTC = (pi/4)^2 + pi/4 = 1.4022."""
    smooth = _path((0, 0), (1, 0), (2, 1), (2, 2), (1, 3), (0, 3))
    assert ttc(smooth).item() == pytest.approx(0.0, abs=1e-6)
    kink = _path((0, 0), (1, 0), (2, 1), (2, 2), (1, 3), (0, 4))
    assert ttc(kink).item() == pytest.approx((PI / 4) ** 2 + PI / 4, abs=1e-6)


def test_ttc_sums_over_time_and_averages_over_batch_and_needs_five_frames():
    e1 = _path((0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (1, 2))
    e2 = _path((0, 0), (1, 0), (2, 1), (2, 2), (1, 3), (0, 3))  # R_TTC = 0
    assert ttc(torch.cat([e1, e2])).item() == pytest.approx((PI**2 / 4 + PI / 2) / 2, abs=1e-6)
    assert ttc(_path((0, 0), (1, 0), (1, 1), (0, 1))).item() == 0.0  # T = 4: no c_t exists


def test_ttc_mask_equals_truncation():
    e = torch.randn(2, 9, 3)
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[1, 6:] = False
    ref = (ttc(e[:1]) + ttc(e[1:, :6])) / 2
    torch.testing.assert_close(ttc(e, mask), ref)


def test_ttc_zero_length_transitions_are_finite_with_finite_gradients():
    """Identical consecutive frames give d_t = 0 (a robot holding still renders the same image)."""
    e = _path((0, 0), (0, 0), (1, 0), (1, 0), (1, 1), (1, 1), (2, 1)).float().requires_grad_(True)
    value = ttc(e)
    assert torch.isfinite(value)
    value.backward()
    assert torch.isfinite(e.grad).all()
    # theta with a zero vector is pi/2 by convention: d = 0,(1,0),0,(0,1),0,(1,0) -> all theta = pi/2, c = 0
    assert value.item() == pytest.approx(0.0, abs=1e-4)
    # all frames identical: every d is zero
    still = torch.zeros(1, 6, 4, requires_grad=True)
    ttc(still).backward()
    assert torch.isfinite(still.grad).all()


# ---- ATC ---------------------------------------------------------------------------------------

# d_2..d_6 = (1,0) (1,0) (0,1) (1,1) (-1,0) with categories A A B B A (cause alignment: the
# transition frame k-1 -> k belongs to step k-1). Runs: [d2 d3] A, [d4 d5] B, [d6] A again.
ATC_E = ((0, 0), (1, 0), (2, 0), (2, 1), (3, 2), (2, 2))
ATC_CATS = (0, 0, 1, 1, 0, 1)  # category of plan steps 0..5; step 5's category is not used ("cause")


def test_atc_by_hand_with_a_category_in_two_runs():
    """Three runs (A appears twice and counts as two segments), C = 3:
    mu_1 = (1,0): cos with d2, d3 = 1, 1                         -> S_w^1 = 1
    mu_2 = ((0,1)+(1,1))/2 = (0.5,1), |mu_2| = sqrt(1.25)
          cos(mu_2,(0,1)) = 1/sqrt(1.25) = 0.894427
          cos(mu_2,(1,1)) = 1.5/(sqrt(1.25) sqrt(2)) = 0.948683  -> S_w^2 = 0.921555
    mu_3 = (-1,0): cos with d6 = 1                               -> S_w^3 = 1
    S_w = (1 + 0.921555 + 1) / 3 = 0.973852
    S_b = (cos(mu_1,mu_2) + cos(mu_1,mu_3) + cos(mu_2,mu_3)) / 3
        = (0.5/sqrt(1.25) - 1 - 0.5/sqrt(1.25)) / 3 = -1/3
    R_ATC = S_b - S_w = -0.333333 - 0.973852 = -1.307185"""
    e = _path(*ATC_E)
    cats = torch.tensor([ATC_CATS])
    s_w = (1 + (1 / math.sqrt(1.25) + 1.5 / (math.sqrt(1.25) * math.sqrt(2))) / 2 + 1) / 3
    assert atc(e, cats).item() == pytest.approx(-1 / 3 - s_w, abs=1e-6)
    assert atc(e, cats).item() == pytest.approx(-1.307185, abs=1e-6)


def test_atc_would_differ_if_the_repeated_category_were_merged():
    """Merged, A = {d2, d3, d6}: mu_A = (1/3, 0), cos = 1, 1, -1 -> S_w^A = 1/3; B as before;
    C = 2: S_w = (1/3 + 0.921555)/2, S_b = cos(mu_A, mu_B)/2 = 0.447214/2. Not what atc returns."""
    merged = 0.447214 / 2 - (1 / 3 + 0.921555) / 2
    got = atc(_path(*ATC_E), torch.tensor([ATC_CATS])).item()
    assert abs(got - merged) > 0.5


def test_atc_alignment_paper_reads_the_next_step():
    e = _path(*ATC_E)
    shifted = torch.tensor([(9,) + ATC_CATS[:-1]])  # categories moved one step later
    torch.testing.assert_close(atc(e, shifted, alignment="paper"), atc(e, torch.tensor([ATC_CATS])))


def test_atc_single_run_and_length_one_runs():
    # one run, all d parallel: S_w = 1, S_b = 0 -> -1
    e = _path((0, 0), (1, 0), (2, 0), (3, 0))
    assert atc(e, torch.tensor([[2, 2, 2, 2]])).item() == pytest.approx(-1.0, abs=1e-6)
    # every transition its own run (length 1): S_w = 1; d = (1,0) (0,1) (1,0), C = 3
    # S_b = (cos(d1,d2) + cos(d1,d3) + cos(d2,d3)) / 3 = (0 + 1 + 0) / 3
    e = _path((0, 0), (1, 0), (1, 1), (2, 1))
    assert atc(e, torch.tensor([[0, 1, 2, 0]])).item() == pytest.approx(1 / 3 - 1, abs=1e-6)


def test_atc_batched_and_masked_equals_per_sequence():
    e = torch.randn(3, 10, 4)
    cats = torch.randint(0, 3, (3, 10))
    mask = torch.ones(3, 10, dtype=torch.bool)
    mask[2, 7:] = False
    ref = (atc(e[:1], cats[:1]) + atc(e[1:2], cats[1:2]) + atc(e[2:, :7], cats[2:, :7])) / 3
    torch.testing.assert_close(atc(e, cats, mask), ref)
    padded = cats.clone()
    padded[2, 7:] = -1  # negative categories are padding too
    torch.testing.assert_close(atc(e, padded, mask), ref)


def test_atc_zero_length_transitions_are_finite_with_finite_gradients():
    e = _path((0, 0), (0, 0), (1, 0), (1, 0), (1, 1)).float().requires_grad_(True)
    value = atc(e, torch.tensor([[0, 0, 1, 1, 1]]))
    assert torch.isfinite(value)
    value.backward()
    assert torch.isfinite(e.grad).all()
    still = torch.zeros(2, 5, 3, requires_grad=True)
    v = atc(still, torch.tensor([[0, 0, 1, 1, 2]] * 2))
    v.backward()
    assert torch.isfinite(v) and torch.isfinite(still.grad).all()


def test_tcr_combines_ttc_and_atc():
    e = torch.randn(2, 8, 3, requires_grad=True)
    cats = torch.randint(0, 7, (2, 8))
    value = tcr(e, cats, alpha=0.3, beta=0.7)
    torch.testing.assert_close(value, 0.3 * ttc(e) + 0.7 * atc(e, cats))
    value.backward()
    assert torch.isfinite(e.grad).all()


def test_overshooting_targets_may_be_index_tensors():
    B, T, S = 2, 7, 3
    pm, ps = torch.randn(B, T, S), torch.rand(B, T, S) + 0.2
    m, s = torch.randn(B, 3, S), torch.rand(B, 3, S) + 0.2
    idx = torch.tensor([2, 4, 6])
    torch.testing.assert_close(overshooting_kl(pm, ps, [m], [s], [idx]), kl_gaussian(pm[:, idx], ps[:, idx], m, s))
    e, pred = torch.randn(B, T, 4), torch.randn(B, 3, 4)
    torch.testing.assert_close(overshooting_reconstruction(e, [pred], [idx]), feature_reconstruction(e[:, idx], pred))
