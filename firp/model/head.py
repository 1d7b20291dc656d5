"""Success-or-failure head: attention pooling of a feature sequence (paper eq. 5) + a linear score.

    q_t    = MLP2(e^_t)                                                      (B, T, Q)
    w_t    = 1/M sum_i  exp(cos(phi_i, q_t) / L) / sum_j exp(cos(phi_i, q_j) / L)   (B, T)
    pooled = sum_t w_t q_t                                                   (B, Q)
    logit  = Linear(pooled)                                                  (B,)

The weights sum to 1 over t for every sequence; the service shows them to point at the step where
a failure becomes evident, which is why the head returns them.

With ``context_dim > 0`` the head also reads a per-sequence context vector (the plan's grasp-frame
description, :mod:`firp.model.plan_geometry`) through a two-layer MLP (or one ReLU layer,
``GeometryConfig.layers``), concatenated to ``pooled``
before the linear score; off (0) it is exactly the paper's head.

About the temperature ``L``: the paper writes ``e^{cos / L}`` with ``L = 20``. As ``cos`` lies in
[-1, 1], ``cos / 20`` lies in [-0.05, 0.05], so no weight can exceed another by more than a factor
``e^{0.1} = 1.105``: at ``L = 20`` the pooling is practically the plain mean over time (checked in
``tests/firp/test_head.py``: for T = 50 every weight is within 10% of 1/T). A cosine classifier's
"temperature 20" usually is a *scale*, ``cos * 20``, which is ``L = 0.05`` here and gives peaked
weights. ``L`` is therefore :attr:`HeadConfig.temperature`: the paper's value is the default, a
product may prefer ``L ~ 0.05 - 0.1``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from firp.model.config import FIRPConfig, HeadConfig
from firp.model.ops import mlp2, safe_unit
from firp.model.plan_geometry import PlanGeometry

__all__ = ["SuccessHead"]


class SuccessHead(nn.Module):
    """Attention-pooled success classifier over a sequence of features ``(B, T, E)``."""

    def __init__(self, cfg: HeadConfig, feature_dim: int, context_dim: int = 0, context_hidden: int = 64,
                 context_layers: int = 2):
        super().__init__()
        self.cfg = cfg
        self.q = mlp2(feature_dim, cfg.hidden, cfg.q_dim)
        self.prototypes = nn.Parameter(torch.randn(cfg.n_prototypes, cfg.q_dim))  # phi_i (M, Q)
        # optional per-sequence context (the plan's grasp-frame description), read beside the pooled q
        # (``context_layers`` 1: one linear layer; the ReLU in forward makes it one hidden layer)
        if not context_dim:
            self.context = None
        elif context_layers == 1:
            self.context = nn.Linear(context_dim, context_hidden)
        else:
            self.context = mlp2(context_dim, context_hidden, context_hidden)
        self.out = nn.Linear(cfg.q_dim + (context_hidden if context_dim else 0), 1)

    @classmethod
    def with_geometry(cls, cfg: FIRPConfig, feature_dim: int, geometry: PlanGeometry | None) -> SuccessHead:
        """The head of a model that owns ``geometry`` (or None): its context is the plan's description."""
        return cls(cfg.head, feature_dim, context_dim=geometry.dim if geometry is not None else 0,
                   context_hidden=cfg.geometry.hidden, context_layers=cfg.geometry.layers)

    @classmethod
    def with_plan_reader(cls, cfg: FIRPConfig, feature_dim: int, reader: nn.Module | None) -> SuccessHead:
        """The head of a model whose plan reader (:func:`firp.model.plan_events.build_plan_reader`: the hand-built
        description or the learned events, or None) gives its context."""
        if reader is None or cfg.geometry.enabled:
            return cls.with_geometry(cfg, feature_dim, reader)
        return cls(cfg.head, feature_dim, context_dim=reader.dim, context_hidden=cfg.events.hidden)

    def attention(self, q: Tensor, mask: Tensor | None = None) -> Tensor:
        """Eq. (5): ``q`` (B, T, Q) -> ``w`` (B, T), rows sum to 1 over the valid steps."""
        cos = torch.einsum("mq,btq->bmt", safe_unit(self.prototypes), safe_unit(q))  # (B, M, T)
        logits = cos / self.cfg.temperature
        if mask is not None:
            logits = logits.masked_fill(~mask.bool().unsqueeze(1), float("-inf"))
        return torch.softmax(logits, dim=-1).mean(dim=1)  # softmax over t, mean over prototypes

    def description_logit(self, context: Tensor) -> Tensor:
        """The description's own score ``context`` (B, C) -> (B,): the output layer's weights on the
        description's hidden units, and its bias -- the head's logit with the pooled sequence's share left
        out (the head's logit is this plus ``w_q . pooled``)."""
        if self.context is None:
            raise ValueError("this head was built without a context input: it has no description score")
        hidden = torch.relu(self.context(context))  # (B, Hc)
        w = self.out.weight[:, self.cfg.q_dim:]  # (1, Hc)
        return (hidden @ w.T).squeeze(-1) + self.out.bias  # (B,)

    def forward(self, features: Tensor, mask: Tensor | None = None, context: Tensor | None = None
                ) -> tuple[Tensor, Tensor]:
        """``features`` (B, T, E), ``mask`` (B, T) bool (True = real step, at least one per row),
        ``context`` (B, C) when the head was built with ``context_dim = C``
        -> ``logits`` (B,) and ``weights`` (B, T) (0 on masked steps)."""
        if (context is None) != (self.context is None):
            raise ValueError("this head was built " + ("with" if self.context is not None else "without")
                             + " a context input; pass context accordingly")
        q = self.q(features)  # (B, T, Q)
        w = self.attention(q, mask)  # (B, T)
        pooled = torch.einsum("bt,btq->bq", w, q)  # (B, Q)
        if self.context is not None:
            pooled = torch.cat([pooled, torch.relu(self.context(context))], dim=-1)  # (B, Q + Hc)
        return self.out(pooled).squeeze(-1), w
