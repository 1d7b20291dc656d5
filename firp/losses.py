"""FIRP's losses and regularisers as pure functions: tensors in, scalar tensor out.

Shapes: B batch, T steps, E feature, S stochastic latent. Time is 0-based here (index k is the
paper's t = k + 1, see :mod:`firp.model.rssm`). Every function takes an optional ``mask`` (B, T)
bool, True for real steps, for batches of plans padded to a common length (valid steps must form a
prefix of each row).

Paper references: eq. 6-9 (future prediction, classification, overshooting), eq. 10-14 (TCR).
Deviations, each explained where it happens: the reconstruction averages over the T-1 terms it
sums (paper: divides by T); TTC sums c_t over t = 4..T-1 because c_3 needs theta_2, which does not
exist; overshooting averages the *given* distances (the caller samples a few) instead of all 2..T-1.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from firp.model.config import LossConfig
from firp.model.ops import EPS, masked_mean, plan_categories, safe_angle, safe_cosine, safe_norm

__all__ = [
    "atc",
    "classification_loss",
    "feature_reconstruction",
    "firp_loss",
    "kl_gaussian",
    "overshooting_kl",
    "overshooting_reconstruction",
    "tcr",
    "transition_directions",
    "ttc",
    "ttc_terms",
]


# --------------------------------------------------------------------------------------------
# Future prediction (eq. 6-8) and classification
# --------------------------------------------------------------------------------------------


def kl_gaussian(
    mean_q: Tensor, std_q: Tensor, mean_p: Tensor, std_p: Tensor, mask: Tensor | None = None, free_nats: float = 0.0
) -> Tensor:
    """``KL(q || p)`` of diagonal Gaussians (posterior q, prior p), summed over the latent dimension
    and averaged over batch and time: the paper's ``L_KL = 1/(NT) sum_{t,n} KL(s_t || s^_t)``.

    All inputs (B, T, S) (or any (..., S)); ``mask`` (B, T). ``free_nats`` > 0 floors each step's KL
    (dreamer): below it the prior is good enough and the posterior is not pulled further.
    """
    var_ratio = (std_q / std_p).pow(2)
    t1 = ((mean_q - mean_p) / std_p).pow(2)
    kl = 0.5 * (var_ratio + t1 - 1.0 - torch.log(var_ratio))  # (..., S)
    kl = kl.sum(dim=-1)  # (...,)
    if free_nats > 0:
        kl = kl.clamp_min(free_nats)
    return masked_mean(kl, mask)


def feature_reconstruction(e: Tensor, e_hat: Tensor, mask: Tensor | None = None, squared: bool = False) -> Tensor:
    """The paper's ``L_re``: the L2 *norm* ``||e_t - e^_t||_2`` (not squared, although the text
    says "mean square error"; the equation is the norm), averaged over batch and the given steps.

    ``e``, ``e_hat`` (B, T', E) aligned; pass t = 2..T, i.e. ``e[:, 1:]`` and the predictions of
    indices 1..T-1 (the first frame is observed, not predicted). The paper divides the sum over
    t = 2..T by T; we divide by the number of terms (T - 1), a constant factor. ``squared=True``
    gives the squared error instead. The norm is smoothed at 0 (``sqrt(x^2 + 1e-12)``) so a perfect
    prediction has a finite gradient.
    """
    diff = e - e_hat
    err = diff.pow(2).sum(dim=-1) if squared else safe_norm(diff, dim=-1)  # (B, T')
    return masked_mean(err, mask)


def classification_loss(logits: Tensor, labels: Tensor, pos_weight: float | Tensor | None = None) -> Tensor:
    """Binary cross-entropy of success logits (B,) against labels (B,) (bool or {0, 1}).

    ``pos_weight`` multiplies the loss of successes (use ``n_fail / n_success`` on a skewed set).
    """
    pw = None
    if pos_weight is not None:
        pw = torch.as_tensor(pos_weight, dtype=logits.dtype, device=logits.device)
    return F.binary_cross_entropy_with_logits(logits, labels.to(logits.dtype), pos_weight=pw)


def _at_targets(x: Tensor | None, target: int | Tensor, length: int) -> Tensor | None:
    """``x`` (B, T, ...) at the target steps: a slice from ``target`` (int) or the given indices."""
    if x is None:
        return None
    if isinstance(target, Tensor):
        return x[:, target]
    return x[:, target : target + length]


def overshooting_kl(
    post_mean: Tensor,
    post_std: Tensor,
    prior_means: Sequence[Tensor],
    prior_stds: Sequence[Tensor],
    target_starts: Sequence[int | Tensor],
    mask: Tensor | None = None,
    stop_posterior_grad: bool = True,
    free_nats: float = 0.0,
) -> Tensor:
    """Latent overshooting KL: mean over the given prediction sets of ``L_KL`` against the posterior.

    ``post_mean, post_std`` (B, T, S) from filtering. Each ``prior_means[k]`` / ``prior_stds[k]``
    (B, L_k, S) predicts the posterior at indices ``target_starts[k] .. target_starts[k] + L_k - 1``
    (an int), or at the indices listed by ``target_starts[k]`` (a (L_k,) long tensor, e.g. the
    ``targets`` of a strided ``RSSM.overshoot``):

    * distance ``tau`` from every start (``RSSM.overshoot``): start ``tau``, L = T - tau;
    * the open loop from index 0 (``RSSM.imagine`` / what inference runs): start 1, L = T - 1.
      It holds one prediction of each distance 1..T-1 and must be among the terms, since it is the
      only one that trains the exact computation scoring uses.

    The caller picks the distances (e.g. :func:`firp.model.rssm.sample_overshooting_distances`):
    the paper's full ``1/(T-1) sum_{tau=2}^{T-1}`` costs ~T^2/2 sequential steps. As in PlaNet the
    posterior is a fixed target here (``stop_posterior_grad``): multi-step priors should learn to
    reach the posterior, not drag it towards their own errors. Returns 0 for no terms.
    """
    if not (len(prior_means) == len(prior_stds) == len(target_starts)):
        raise ValueError("prior_means, prior_stds and target_starts must have the same length")
    if stop_posterior_grad:
        post_mean, post_std = post_mean.detach(), post_std.detach()
    terms = []
    for mean_p, std_p, start in zip(prior_means, prior_stds, target_starts):
        n = mean_p.shape[1]
        if n == 0:
            continue
        q_mean, q_std = _at_targets(post_mean, start, n), _at_targets(post_std, start, n)
        terms.append(kl_gaussian(q_mean, q_std, mean_p, std_p, _at_targets(mask, start, n), free_nats))
    return torch.stack(terms).mean() if terms else post_mean.new_zeros(())


def overshooting_reconstruction(
    e: Tensor, predictions: Sequence[Tensor], target_starts: Sequence[int | Tensor], mask: Tensor | None = None
) -> Tensor:
    """``L_re^tau`` for the same prediction sets as :func:`overshooting_kl`, averaged over sets.

    ``e`` (B, T, E) real features; ``predictions[k]`` (B, L_k, E) decoded from the overshooting
    priors, aligned to indices ``target_starts[k] ..`` (int) or to the listed indices (tensor).
    """
    if len(predictions) != len(target_starts):
        raise ValueError("predictions and target_starts must have the same length")
    terms = []
    for pred, start in zip(predictions, target_starts):
        n = pred.shape[1]
        if n == 0:
            continue
        terms.append(feature_reconstruction(_at_targets(e, start, n), pred, _at_targets(mask, start, n)))
    return torch.stack(terms).mean() if terms else e.new_zeros(())


# --------------------------------------------------------------------------------------------
# TCR (eq. 10-14)
# --------------------------------------------------------------------------------------------


def transition_directions(e: Tensor) -> Tensor:
    """``d`` (B, T-1, E) with ``d[:, k-1] = e[:, k] - e[:, k-1]`` for k = 1..T-1: the paper's
    ``d_t = e_t - e_{t-1}``, t = 2..T (so ``d[:, j]`` is paper ``d_{j+2}``)."""
    return e[:, 1:] - e[:, :-1]


def _window_valid(mask: Tensor, width: int) -> Tensor:
    """(B, T) -> (B, T - width + 1): True where all ``width`` consecutive steps are valid."""
    return mask.bool().unfold(1, width, 1).all(dim=-1)


def ttc_terms(e: Tensor, mask: Tensor | None = None, eps: float = EPS) -> tuple[Tensor, Tensor]:
    """Smoothness ``R_sm`` and sparseness ``R_sp`` of TTC, each summed over t, averaged over batch.

    Index bookkeeping (paper, 1-based): ``d_t`` exists for t = 2..T; ``theta_t = angle(d_t, d_{t-1})``
    for t = 3..T; ``c_t = 2 theta_t - theta_{t-1} - theta_{t+1}`` needs theta_{t-1} and theta_{t+1},
    so it exists for **t = 4..T-1** (T - 4 terms). The paper writes sum_{t=3}^{T-1}, but c_3 would
    need theta_2 = angle(d_2, d_1) and d_1 does not exist; we sum over the c_t that exist (0 for
    T < 5). In tensors: ``theta[:, j]`` is paper theta_{j+3} and ``c[:, j]`` is paper c_{j+4}.

    Angles use Kahan's formula on smoothed unit vectors (:func:`firp.model.ops.safe_angle`): a
    zero-length ``d_t`` (two identical frames) gives theta = pi/2, finite, with finite gradients.
    A c_t with a padded step among the frames it depends on (frames t-4..t, 0-based j..j+4) is
    left out.
    """
    d = transition_directions(e)  # (B, T-1, E)
    theta = safe_angle(d[:, 1:], d[:, :-1], eps=eps)  # (B, T-2)
    c = 2.0 * theta[:, 1:-1] - theta[:, :-2] - theta[:, 2:]  # (B, T-4)
    B = e.shape[0]
    if c.shape[1] <= 0:
        zero = e.new_zeros(()) + 0.0 * e.sum()  # keep the graph connected
        return zero, zero
    weight = _window_valid(mask, 5).to(c.dtype) if mask is not None else torch.ones_like(c)
    r_sm = (c.pow(2) * weight).sum() / B
    r_sp = (c.abs() * weight).sum() / B
    return r_sm, r_sp


def ttc(e: Tensor, mask: Tensor | None = None, eps: float = EPS) -> Tensor:
    """``R_TTC = R_sm + R_sp`` (eq. 13), summed over time, averaged over the batch; ``e`` (B, T, E)."""
    r_sm, r_sp = ttc_terms(e, mask, eps)
    return r_sm + r_sp


def atc(
    e: Tensor,
    categories: Tensor,
    mask: Tensor | None = None,
    alignment: Literal["cause", "paper"] = "cause",
    eps: float = EPS,
) -> Tensor:
    """``R_ATC = S_b - S_w`` (eq. 14), averaged over the batch.

    ``e`` (B, T, E); ``categories`` (B, T) long, the category of each plan step (aligned with
    actions; see :func:`firp.model.ops.plan_categories`); negative values mark padding.

    Which category does a transition ``d`` (frame k-1 -> frame k) belong to? The paper says "d_t is
    induced by a_t". In our datasets action k-1 leads from frame k-1 to frame k, so the cause is
    step k-1: ``alignment="cause"`` (default) uses ``categories[:, :-1]``; ``"paper"`` uses
    ``categories[:, 1:]`` (the paper's indices taken literally).

    Segments are maximal runs of one category; a category that occurs in several runs counts as
    several segments, as the paper prescribes. With ``C`` runs, ``mu_i`` the mean ``d`` of run i:
    ``S_w = 1/C sum_i 1/|A_i| sum_{t in A_i} cos(mu_i, d_t)`` and
    ``S_b = 1/C sum_{i<j} cos(mu_i, mu_j)``. Note the paper's ``1/C`` in front of a sum of
    C(C-1)/2 pairs: S_b grows like (C-1)/2 while S_w stays in [-1, 1]; kept as written. A run of
    length 1 has ``mu = d`` (cos 1); zero vectors have cos 0 with finite gradients (smoothed norms).
    """
    if alignment not in ("cause", "paper"):
        raise ValueError(f"alignment must be cause|paper, got {alignment!r}")
    d = transition_directions(e)  # (B, K, E), K = T-1
    B, K, _ = d.shape
    if K == 0:
        return e.new_zeros(()) + 0.0 * e.sum()
    cat = categories[:, :-1] if alignment == "cause" else categories[:, 1:]  # (B, K)
    valid = cat >= 0
    if mask is not None:
        valid = valid & mask[:, 1:].bool() & mask[:, :-1].bool()
    prev_valid = F.pad(valid[:, :-1], (1, 0), value=False)
    prev_cat = F.pad(cat[:, :-1], (1, 0), value=-1)
    start = valid & (~prev_valid | (cat != prev_cat))  # (B, K) a run begins here
    run_id = torch.cumsum(start.long(), dim=1) - 1  # (B, K)
    runs = torch.arange(K, device=d.device)
    assign = ((run_id.unsqueeze(-1) == runs) & valid.unsqueeze(-1)).to(d.dtype)  # (B, K, R)
    counts = assign.sum(dim=1)  # (B, R)
    run_valid = counts > 0
    n_runs = run_valid.sum(dim=1).to(d.dtype).clamp_min(1.0)  # (B,) C
    mu = torch.einsum("bkr,bke->bre", assign, d) / counts.clamp_min(1.0).unsqueeze(-1)  # (B, R, E)

    mu_of_step = torch.einsum("bkr,bre->bke", assign, mu)  # (B, K, E)
    cos_in = safe_cosine(mu_of_step, d, eps=eps) * valid.to(d.dtype)  # (B, K)
    s_w_run = torch.einsum("bkr,bk->br", assign, cos_in) / counts.clamp_min(1.0)  # (B, R)
    s_w = s_w_run.sum(dim=1) / n_runs  # (B,)

    cos_between = safe_cosine(mu.unsqueeze(2), mu.unsqueeze(1), eps=eps)  # (B, R, R)
    pair = torch.triu(torch.ones(K, K, dtype=torch.bool, device=d.device), diagonal=1)
    pair = pair & run_valid.unsqueeze(2) & run_valid.unsqueeze(1)
    s_b = (cos_between * pair.to(d.dtype)).sum(dim=(1, 2)) / n_runs  # (B,)
    return (s_b - s_w).mean()


def tcr(
    e: Tensor,
    categories: Tensor,
    alpha: float,
    beta: float,
    mask: Tensor | None = None,
    alignment: Literal["cause", "paper"] = "cause",
) -> Tensor:
    """``R_TCR = alpha R_TTC + beta R_ATC`` (eq. 10) on the real features ``e`` (B, T, E)."""
    return alpha * ttc(e, mask) + beta * atc(e, categories, mask, alignment)


# --------------------------------------------------------------------------------------------
# The whole objective
# --------------------------------------------------------------------------------------------


def firp_loss(out: Mapping[str, Any], actions: Tensor, labels: Tensor, cfg: LossConfig = LossConfig()) -> dict[str, Tensor]:
    """Eq. 9 + TCR from the dict of :meth:`firp.model.firp.FIRP.forward_train`.

    ``total = ce_real * L_ce + ce_open_loop * L_ce(open loop) + prediction * (L_KL^1 + L_re^1)
    + lambda * (L_KL^os + L_re^os) + alpha * R_TTC + beta * R_ATC + description * L_ce(description)`` where ``os`` averages the open
    loop from index 0 and the sampled distances in ``out["overshoot"]``. ``L_re^1`` compares
    ``e[:, 1:]`` with the decoded one-step priors (the paper decodes from s^_t). Returns every term
    (for logging) and ``"total"``.
    """
    mask = out.get("mask")
    e = out["e"]
    target = out.get("e_target", e)  # (B, T, E) the prediction target (detached by default)
    terms: dict[str, Tensor] = {}
    terms["ce"] = classification_loss(out["logits"], labels, cfg.pos_weight)
    terms["ce_open_loop"] = classification_loss(out["logits_open_loop"], labels, cfg.pos_weight)
    terms["kl"] = kl_gaussian(out["post_mean"], out["post_std"], out["prior_mean"], out["prior_std"], mask, cfg.free_nats)
    m1 = mask[:, 1:] if mask is not None else None
    terms["re"] = feature_reconstruction(target[:, 1:], out["feat_prior"][:, 1:], m1)

    sets = [(out["open_loop"], 1)] + [(pred, pred["targets"]) for _, pred in sorted(out["overshoot"].items())]
    sets = [(p, s) for p, s in sets if p["prior_mean"].shape[1] > 0]
    starts = [s for _, s in sets]
    terms["kl_overshoot"] = overshooting_kl(
        out["post_mean"], out["post_std"], [p["prior_mean"] for p, _ in sets], [p["prior_std"] for p, _ in sets],
        starts, mask, free_nats=cfg.free_nats,
    )
    terms["re_overshoot"] = overshooting_reconstruction(target, [p["feat"] for p, _ in sets], starts, mask)

    categories = out["categories"] if "categories" in out else plan_categories(actions)  # aligned with e
    terms["ttc"] = ttc(e, mask) if cfg.alpha > 0 else e.new_zeros(())
    terms["atc"] = atc(e, categories, mask, cfg.atc_alignment) if cfg.beta > 0 else e.new_zeros(())
    if cfg.description > 0:
        if "logits_description" not in out:
            raise ValueError("LossConfig.description > 0 asks for the description's own score, and this model "
                             "reads no plan description (enable the plan's description)")
        terms["ce_description"] = classification_loss(out["logits_description"], labels, cfg.pos_weight)
    else:
        terms["ce_description"] = e.new_zeros(())
    terms["total"] = sum(w * terms[k] for k, w in loss_weights(cfg).items())
    return terms


def loss_weights(cfg: LossConfig) -> dict[str, float]:
    """Weight of each term of :func:`firp_loss` in ``total``."""
    return {"ce": cfg.ce_real, "ce_open_loop": cfg.ce_open_loop, "kl": cfg.prediction, "re": cfg.prediction,
            "kl_overshoot": cfg.overshooting, "re_overshoot": cfg.overshooting, "ttc": cfg.alpha, "atc": cfg.beta,
            "ce_description": cfg.description}
