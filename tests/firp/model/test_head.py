"""Attention head: weights are a distribution over time; what the temperature L does."""

import dataclasses
import math

import torch

from firp.model import HeadConfig, SuccessHead

from .helpers import assert_finite_grads


def _head(temperature: float, M: int = 4, Q: int = 8, E: int = 6) -> SuccessHead:
    return SuccessHead(HeadConfig(q_dim=Q, n_prototypes=M, temperature=temperature, hidden=16), E)


def test_shapes_weights_sum_to_one_and_gradients():
    head = _head(20.0)
    logits, w = head(torch.randn(3, 11, 6))
    assert logits.shape == (3,) and w.shape == (3, 11)
    torch.testing.assert_close(w.sum(dim=1), torch.ones(3))
    (logits.sum() + (w * torch.arange(11.0)).sum()).backward()
    assert_finite_grads(head)


def test_paper_temperature_20_gives_nearly_uniform_weights():
    """cos in [-1, 1], so with L = 20 no weight can exceed another by more than e^{2/20} = 1.105:
    every weight lies within ~10% of 1/T whatever the features are."""
    head = _head(20.0)
    T = 50
    _, w = head(torch.randn(4, T, 6) * 100)
    assert (w.max(dim=1).values / w.min(dim=1).values).max() <= math.exp(0.1) + 1e-5
    assert ((w * T - 1).abs() < 0.106).all()


def test_small_temperature_gives_peaked_weights_on_the_matching_step():
    head = _head(0.01, M=1, Q=3)
    with torch.no_grad():
        head.prototypes.copy_(torch.tensor([[1.0, 0.0, 0.0]]))
    q = torch.tensor([[[0.0, 1.0, 0.0]] * 9]).repeat(2, 1, 1)
    q[:, 4] = torch.tensor([2.0, 0.1, 0.0])  # cos ~ 0.999 with the prototype; all others cos 0
    w = head.attention(q)
    assert (w[:, 4] > 0.99).all()
    # the same q at the paper's L = 20 is nearly uniform
    w20 = dataclasses.replace(head.cfg, temperature=20.0)
    head.cfg = w20
    assert head.attention(q)[:, 4].max() < 1.6 / 9


def test_masked_steps_get_zero_weight_and_do_not_change_the_logit():
    head = _head(0.1)
    x = torch.randn(2, 7, 6)
    mask = torch.tensor([[True] * 7, [True] * 4 + [False] * 3])
    logits, w = head(x, mask)
    assert (w[1, 4:] == 0).all()
    torch.testing.assert_close(w.sum(1), torch.ones(2))
    logits_short, _ = head(x[1:, :4])
    torch.testing.assert_close(logits[1:], logits_short)


def test_zero_features_give_finite_gradients():
    head = _head(0.1)
    with torch.no_grad():
        for p in head.q.parameters():
            p.zero_()  # q_t = 0 exactly: cosine of a zero vector
    logits, w = head(torch.randn(2, 5, 6))
    (logits.sum() + w[:, 0].sum()).backward()
    assert_finite_grads(head)
