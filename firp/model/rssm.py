"""Recurrent state-space model (PlaNet's RSSM) exactly as in the FIRP paper, eqs. (1)-(4).

    h_t     = GRUCell(h_{t-1}, f(s_{t-1}, a_t))          deterministic model
    s_t     ~ g(h_t, e_t)        = N(mean, std)           transition module I  (posterior)
    s^_t    ~ g^(h_t)            = N(mean, std)           transition module II (prior)
    e^_t    = D(s_t or s^_t, h_t)                         feature decoder
    h_0 = s_0 = 0

``f, g, g^, D`` are two-layer ReLU MLPs; ``std = softplus(raw) + min_std``; samples use the
reparametrisation ``mean + std * eps``.

Index convention (tensors are 0-based; the paper is 1-based)
-------------------------------------------------------------
``e[:, k]`` is the feature of ``frames[k]`` (paper ``e_{k+1}``; ``frames[0]`` is the initial image
``I_1``) and ``a[:, k]`` is ``actions[k]`` (paper ``a_{k+1}``). Following the paper literally, the
latent at index ``k`` first absorbs action ``k`` and then observes frame ``k``:

    h[:, k] = GRU(h[:, k-1], f(s[:, k-1], a[:, k]))   with h[:, -1] = s[:, -1] = 0
    s[:, k] ~ g(h[:, k], e[:, k])

In the dataset ``frames[k]`` is the image *before* step ``k`` and action ``k`` leads from frame
``k`` to frame ``k+1``. So the latent at index ``k`` holds every cause of frame ``k`` (actions
``0..k-1``) plus one action of look-ahead (action ``k``, not yet executed when frame ``k`` was
taken); the first frame that shows the effect of action ``k`` is frame ``k+1``, predicted by the
latent at ``k+1``. The look-ahead is harmless (extra input the model may ignore) and keeping it
makes this module the paper's equations verbatim. Consequence worth knowing: the effect of the
*last* action is never in a frame of the dataset (there are T frames and T actions).

Inference (:meth:`RSSM.rollout_from_first`) is the paper's recipe: the posterior at index 0 from
``e[:, 0]`` (after absorbing ``a[:, 0]``), then the prior rolled forward under ``a[:, 1:]``
giving ``e^`` for indices ``1..T-1`` (paper ``e^_2..e^_T``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from firp.model.config import RSSMConfig
from firp.model.ops import mlp2

__all__ = ["RSSM", "sample_overshooting_distances"]


class RSSM(nn.Module):
    """The paper's RSSM. Shapes: B batch, T steps, E feature, A action, H deter, S stoch."""

    def __init__(self, cfg: RSSMConfig, feature_dim: int, action_dim: int):
        super().__init__()
        self.cfg = cfg
        H, S, hid = cfg.deter_dim, cfg.stoch_dim, cfg.hidden
        self.feature_dim = feature_dim
        self.action_dim = action_dim
        self.f = mlp2(S + action_dim, hid, hid)  # f(s_{t-1}, a_t)
        self.rnn = nn.GRUCell(hid, H)  # RNN of eq. (1)
        self.g = mlp2(H + feature_dim, hid, 2 * S)  # posterior g(h_t, e_t)
        self.g_hat = mlp2(H, hid, 2 * S)  # prior g^(h_t)
        self.decoder = mlp2(S + H, hid, feature_dim)  # D(s, h)

    # building blocks --------------------------------------------------------------------------
    def initial_state(self, batch: int, device: torch.device, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
        """``h_0 = 0`` (B, H) and ``s_0 = 0`` (B, S), as in PlaNet and the paper."""
        return (
            torch.zeros(batch, self.cfg.deter_dim, device=device, dtype=dtype),
            torch.zeros(batch, self.cfg.stoch_dim, device=device, dtype=dtype),
        )

    def _gaussian(self, raw: Tensor) -> tuple[Tensor, Tensor]:
        mean, raw_std = raw.chunk(2, dim=-1)
        return mean, F.softplus(raw_std) + self.cfg.min_std

    @staticmethod
    def _draw(mean: Tensor, std: Tensor, sample: bool) -> Tensor:
        """Reparametrised sample ``mean + std * eps`` (or the mean, for deterministic scoring)."""
        return mean + std * torch.randn_like(std) if sample else mean

    def deter_step(self, h_prev: Tensor, s_prev: Tensor, a: Tensor) -> Tensor:
        """Eq. (1): ``h_t = GRU(h_{t-1}, f(s_{t-1}, a_t))``; (B, H), (B, S), (B, A) -> (B, H)."""
        return self.rnn(self.f(torch.cat([s_prev, a], dim=-1)), h_prev)

    def posterior(self, h: Tensor, e: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. (2): ``g(h_t, e_t)`` -> mean, std (..., S)."""
        return self._gaussian(self.g(torch.cat([h, e], dim=-1)))

    def prior(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. (3): ``g^(h_t)`` -> mean, std (..., S)."""
        return self._gaussian(self.g_hat(h))

    def decode(self, s: Tensor, h: Tensor) -> Tensor:
        """Eq. (4): ``D(s, h)`` -> e^ (..., E)."""
        return self.decoder(torch.cat([s, h], dim=-1))

    # sequences --------------------------------------------------------------------------------
    def observe(self, e: Tensor, a: Tensor, sample: bool = True) -> dict[str, Tensor]:
        """Filter a whole observed sequence (training).

        ``e`` (B, T, E), ``a`` (B, T, A) -> dict of (B, T, .) tensors:
        ``h``; ``post_mean, post_std, post_sample`` (s_t); ``prior_mean, prior_std, prior_sample``
        (s^_t from the same h_t: the one-step prediction, tau = 1); ``feat_prior`` = D(s^_t, h_t)
        and ``feat_post`` = D(s_t, h_t). Only the recurrence runs step by step; the prior and the
        decoder depend on h_t alone, so they run once over all steps afterwards.
        """
        B, T, _ = e.shape
        h, s = self.initial_state(B, e.device, e.dtype)
        hs, means, stds, samples = [], [], [], []
        for t in range(T):
            h = self.deter_step(h, s, a[:, t])  # (B, H)
            mean, std = self.posterior(h, e[:, t])  # (B, S)
            s = self._draw(mean, std, sample)
            hs.append(h), means.append(mean), stds.append(std), samples.append(s)
        h_seq = torch.stack(hs, dim=1)  # (B, T, H)
        post_sample = torch.stack(samples, dim=1)  # (B, T, S)
        prior_mean, prior_std = self.prior(h_seq)  # (B, T, S)
        prior_sample = self._draw(prior_mean, prior_std, sample)
        return {
            "h": h_seq,
            "post_mean": torch.stack(means, dim=1),
            "post_std": torch.stack(stds, dim=1),
            "post_sample": post_sample,
            "prior_mean": prior_mean,
            "prior_std": prior_std,
            "prior_sample": prior_sample,
            "feat_prior": self.decode(prior_sample, h_seq),  # (B, T, E)
            "feat_post": self.decode(post_sample, h_seq),  # (B, T, E)
        }

    def imagine(self, h_start: Tensor, s_start: Tensor, a: Tensor, sample: bool = True) -> dict[str, Tensor]:
        """Open-loop prior rollout from a given latent (no images).

        ``h_start`` (B, H), ``s_start`` (B, S): the latent at some index k; ``a`` (B, K, A): actions
        ``k+1 .. k+K``. Returns (B, K, .) tensors ``h, prior_mean, prior_std, prior_sample, feat``
        for indices ``k+1 .. k+K`` (``feat`` = D(s^, h)). Each step feeds the prior sample (or mean
        when ``sample=False``) into the next.
        """
        h, s = h_start, s_start
        hs, means, stds, samples = [], [], [], []
        for k in range(a.shape[1]):
            h = self.deter_step(h, s, a[:, k])
            mean, std = self.prior(h)
            s = self._draw(mean, std, sample)
            hs.append(h), means.append(mean), stds.append(std), samples.append(s)
        if not hs:  # K = 0
            empty = h_start.new_zeros(h_start.shape[0], 0, 0)
            return {"h": empty, "prior_mean": empty, "prior_std": empty, "prior_sample": empty, "feat": empty}
        h_seq = torch.stack(hs, dim=1)
        s_seq = torch.stack(samples, dim=1)
        return {
            "h": h_seq,
            "prior_mean": torch.stack(means, dim=1),
            "prior_std": torch.stack(stds, dim=1),
            "prior_sample": s_seq,
            "feat": self.decode(s_seq, h_seq),
        }

    def rollout_from_first(self, e_1: Tensor, a: Tensor, sample: bool = False) -> dict[str, Tensor]:
        """What inference uses: from the initial feature only.

        ``e_1`` (B, E) = feature of frames[0]; ``a`` (B, T, A) the whole plan. The posterior at
        index 0 is ``g(h_1, e_1)`` with ``h_1 = GRU(0, f(0, a[:, 0]))``; the prior then rolls under
        ``a[:, 1:]`` giving e^ for indices 1..T-1. Returns ``h_1`` (B, H), ``post_mean_1``,
        ``post_std_1``, ``s_1`` (B, S), ``prior`` (the :meth:`imagine` dict, (B, T-1, .)) and
        ``features`` (B, T, E) = [e_1, e^_2, ..., e^_T], the sequence the success head reads.
        ``sample=False`` (default) uses means throughout, so a plan always gets the same score.
        """
        B = e_1.shape[0]
        h0, s0 = self.initial_state(B, e_1.device, e_1.dtype)
        h1 = self.deter_step(h0, s0, a[:, 0])
        mean1, std1 = self.posterior(h1, e_1)
        s1 = self._draw(mean1, std1, sample)
        prior = self.imagine(h1, s1, a[:, 1:], sample=sample)
        pred = prior["feat"] if a.shape[1] > 1 else e_1.new_zeros(B, 0, e_1.shape[-1])
        return {
            "h_1": h1,
            "post_mean_1": mean1,
            "post_std_1": std1,
            "s_1": s1,
            "prior": prior,
            "features": torch.cat([e_1.unsqueeze(1), pred], dim=1),
        }

    def overshoot(
        self, h: Tensor, s: Tensor, a: Tensor, tau: int, sample: bool = True, stride: int = 1
    ) -> dict[str, Tensor]:
        """Latent overshooting at distance ``tau``: the prior at target index ``t`` rolled ``tau``
        steps from the filtered latent ``(h, s)`` at ``t - tau``.

        ``h`` (B, T, H), ``s`` (B, T, S) from :meth:`observe` (posterior samples), ``a`` (B, T, A).
        Start points ``0, stride, 2*stride, ... <= T-1-tau`` (n of them) run in parallel as one batch
        of ``B * n``, so the cost is ``tau`` sequential steps of that batch; ``stride > 1`` cuts the
        batch (long distances are expensive: ~tau * (T - tau) rows). Returns (B, n, .) tensors
        ``h, prior_mean, prior_std, prior_sample, feat`` and ``targets`` (n,) long, the target
        indices (``starts + tau``). ``tau = 1, stride = 1`` reproduces the priors of :meth:`observe`.
        """
        B, T, H = h.shape
        if not 1 <= tau < T:
            raise ValueError(f"tau must be in [1, T-1] = [1, {T - 1}], got {tau}")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        starts = torch.arange(0, T - tau, stride, device=h.device)  # (n,)
        n = starts.numel()
        hc = h[:, starts].reshape(B * n, H)
        sc = s[:, starts].reshape(B * n, -1)
        for j in range(1, tau + 1):
            aj = a[:, starts + j].reshape(B * n, -1)  # the action of index start + j
            hc = self.deter_step(hc, sc, aj)
            mean, std = self.prior(hc)
            sc = self._draw(mean, std, sample)
        out = {"h": hc, "prior_mean": mean, "prior_std": std, "prior_sample": sc, "feat": self.decode(sc, hc)}
        out = {k: v.reshape(B, n, v.shape[-1]) for k, v in out.items()}
        out["targets"] = starts + tau
        return out


def sample_overshooting_distances(
    T: int, n: int, max_tau: int | None = None, generator: torch.Generator | None = None
) -> list[int]:
    """Draw ``n`` distinct overshooting distances from ``[2, min(max_tau, T - 1)]``.

    The paper averages ``L^tau`` over every ``tau`` in ``2..T-1``: ~T^2/2 sequential prior steps,
    far too slow for T = 120 on a CPU. A few random ``tau`` per batch is an unbiased estimate of
    that average (up to the constant factor), and the open-loop rollout from the first step, which
    covers every distance once and is what inference runs, is added separately by the model.
    """
    hi = T - 1 if max_tau is None else min(max_tau, T - 1)
    if hi < 2 or n <= 0:
        return []
    pool = torch.arange(2, hi + 1)
    pick = torch.randperm(len(pool), generator=generator)[: min(n, len(pool))]
    return sorted(int(x) for x in pool[pick])
