"""The paper's baselines, behind the same two calls as :class:`~firp.model.firp.FIRP`.

Every model has

* ``forward_train(features (B, T, Db), actions (B, T, A), mask=None, **kw) -> dict`` with at least
  ``"logits"`` (B,) -- what the classification loss reads -- so one training loop trains all; and
* ``score(features, actions, mask=None) -> Score``, where ``features`` is (B, Db) or (B, T, Db).
  Models with ``requires_future_frames = False`` read frame 0 only (a test checks that changing
  the later frames changes nothing), so an evaluation loop can pass the same batch to every model.

Baselines:

* :class:`AMLP` -- plan only, 3-layer MLP;
* :class:`AMLPImage` -- plan + feature of the initial image, 3-layer MLP;
* :class:`GRUBaseline` -- FIRP with the RSSM replaced by a plain GRU over the actions, initialised
  from ``e_1``, then FIRP's attention head;
* :class:`Oracle` -- features of the frames actually executed (not available before execution:
  an upper bound) + a 2-layer MLP.

With ``cfg.geometry.enabled`` every plan-reading model also gets the plan's grasp-frame
description (:mod:`firp.model.plan_geometry`): the MLPs in their input, the GRU baseline in its
head, as FIRP does; the Oracle reads no plan and ignores it.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn

from firp.model.normalize import ActionNormalizer
from firp.model.config import FIRPConfig
from firp.model.encoder import FeatureProjection
from firp.model.firp import FIRP, Score, first_step
from firp.model.head import SuccessHead
from firp.model.ops import last_valid_index
from firp.model.plan_events import build_plan_reader, read_plan

__all__ = ["AMLP", "AMLPImage", "GRUBaseline", "MODEL_KINDS", "ModelKind", "Oracle", "build_model", "plan_vector"]

ModelKind = Literal["firp", "a_mlp", "a_mlp_image", "gru", "oracle"]
MODEL_KINDS: tuple[str, ...] = ("firp", "a_mlp", "a_mlp_image", "gru", "oracle")


def plan_vector(actions: Tensor, mask: Tensor | None, pooling: str, max_T: int) -> Tensor:
    """``actions`` (B, T, A) -> (B, max_T * A) ("flatten", zero-padded), (B, A) ("mean") or (B, 0) ("none").

    Masked (padded) steps are zeroed / left out, so padding never changes the result.
    """
    B, T, A = actions.shape
    if pooling == "none":
        return actions.new_zeros(B, 0)
    if mask is not None:
        actions = actions * mask.unsqueeze(-1).to(actions.dtype)
    if pooling == "mean":
        n = mask.sum(dim=1, keepdim=True).clamp_min(1).to(actions.dtype) if mask is not None else actions.new_tensor(T)
        return actions.sum(dim=1) / n
    if T > max_T:
        raise ValueError(f"plan has T={T} steps but this model flattens at most max_T={max_T}")
    padded = actions.new_zeros(B, max_T, A)
    padded[:, :T] = actions
    return padded.reshape(B, max_T * A)


def _mlp3(d_in: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1))


class _PlanMLP(nn.Module):
    """Shared by the A-MLP baselines: the standardised (flattened or pooled) plan into a 3-layer MLP."""

    requires_future_frames = False

    def __init__(self, cfg: FIRPConfig, extra_dim: int = 0):
        super().__init__()
        self.cfg = cfg
        b = cfg.baseline
        d_plan = {"flatten": cfg.action_dim * b.max_T, "mean": cfg.action_dim, "none": 0}[b.plan_pooling]
        if b.plan_pooling == "none" and not (cfg.geometry.enabled or cfg.events.enabled):
            raise ValueError("baseline.plan_pooling='none' leaves the MLP no input: enable geometry or events")
        self.geometry = build_plan_reader(cfg)
        d_geometry = self.geometry.dim if self.geometry is not None else 0
        self.mlp = _mlp3(d_plan + d_geometry + extra_dim, b.hidden)
        self.action_norm = ActionNormalizer(cfg.action_dim)

    def _plan(self, actions: Tensor, mask: Tensor | None) -> Tensor:
        """(B, D_plan [+ G]): the standardised plan, and its grasp-frame description when enabled."""
        b = self.cfg.baseline
        plan = plan_vector(self.action_norm(actions), mask, b.plan_pooling, b.max_T)
        if self.geometry is None:
            return plan
        return torch.cat([plan, self.geometry(actions, mask)], dim=-1)


class AMLP(_PlanMLP):
    """A-MLP: success from the plan alone (no image). 3-layer MLP over the (flattened) plan."""

    def __init__(self, cfg: FIRPConfig = FIRPConfig()):
        super().__init__(cfg)

    def _logits(self, actions: Tensor, mask: Tensor | None) -> Tensor:
        return self.mlp(self._plan(actions, mask)).squeeze(-1)  # (B,)

    def forward_train(self, features: Tensor | None, actions: Tensor, mask: Tensor | None = None, **_: object) -> dict[str, Tensor]:
        """``features`` are ignored (may be None); returns ``{"logits": (B,)}``."""
        return {"logits": self._logits(actions, mask)}

    def score(self, features: Tensor | None, actions: Tensor, mask: Tensor | None = None) -> Score:
        return Score(self._logits(actions, mask), None, None)


class AMLPImage(_PlanMLP):
    """A-MLP+image: plan + projected feature of the initial image, 3-layer MLP."""

    def __init__(self, cfg: FIRPConfig = FIRPConfig()):
        super().__init__(cfg, extra_dim=cfg.encoder.feature_dim)
        self.projection = FeatureProjection(cfg.encoder)

    def _logits(self, features: Tensor, actions: Tensor, mask: Tensor | None) -> Tensor:
        e1 = self.projection(first_step(features))  # (B, E)
        return self.mlp(torch.cat([self._plan(actions, mask), e1], dim=-1)).squeeze(-1)

    def forward_train(self, features: Tensor, actions: Tensor, mask: Tensor | None = None, **_: object) -> dict[str, Tensor]:
        """Reads frame 0 of ``features`` only; returns ``{"logits": (B,)}``."""
        return {"logits": self._logits(features, actions, mask)}

    def score(self, features: Tensor, actions: Tensor, mask: Tensor | None = None) -> Score:
        return Score(self._logits(features, actions, mask), None, None)


class GRUBaseline(nn.Module):
    """FIRP with the RSSM replaced by a deterministic GRU over the actions.

    Same information as FIRP's open loop: ``h_1 = tanh(W [e_1, a_1])``, then a GRU over
    ``a_2..a_T``; ``e^_t = Linear(h_t)``; the head reads [e_1, e^_2, ..., e^_T].
    ``forward_train`` also returns ``features_pred`` and the real ``e`` so a reconstruction loss
    can be added (the paper's GRU baseline is described only as "future prediction by a GRU").
    """

    requires_future_frames = False

    def __init__(self, cfg: FIRPConfig = FIRPConfig()):
        super().__init__()
        self.cfg = cfg
        E, A, Hg = cfg.encoder.feature_dim, cfg.action_dim, cfg.baseline.gru_hidden
        self.projection = FeatureProjection(cfg.encoder)
        self.init = nn.Linear(E + A, Hg)
        self.gru = nn.GRU(A, Hg, batch_first=True)
        self.readout = nn.Linear(Hg, E)
        self.geometry = build_plan_reader(cfg)
        self.head = SuccessHead.with_plan_reader(cfg, E, self.geometry)
        self.action_norm = ActionNormalizer(A)

    def _predict(self, e1: Tensor, actions: Tensor) -> Tensor:
        """``e1`` (B, E), ``actions`` (B, T, A) -> [e_1, e^_2..e^_T] (B, T, E)."""
        actions = self.action_norm(actions)
        h1 = torch.tanh(self.init(torch.cat([e1, actions[:, 0]], dim=-1)))  # (B, Hg)
        if actions.shape[1] == 1:
            return e1.unsqueeze(1)
        out, _ = self.gru(actions[:, 1:], h1.unsqueeze(0).contiguous())  # (B, T-1, Hg)
        return torch.cat([e1.unsqueeze(1), self.readout(out)], dim=1)

    def forward_train(self, features: Tensor, actions: Tensor, mask: Tensor | None = None, **_: object) -> dict[str, Tensor]:
        """``features`` (B, T, Db): frame 0 drives the prediction, all frames give targets ``e``."""
        e = self.projection(features)  # (B, T, E)
        seq = self._predict(e[:, 0], actions)
        logits, weights = self.head(seq, mask, read_plan(self.geometry, actions, mask))
        return {"logits": logits, "weights": weights, "features_pred": seq, "e": e}

    def score(self, features: Tensor, actions: Tensor, mask: Tensor | None = None) -> Score:
        seq = self._predict(self.projection(first_step(features)), actions)
        logits, weights = self.head(seq, mask, read_plan(self.geometry, actions, mask))
        return Score(logits, weights, seq)


class Oracle(nn.Module):
    """Upper bound: features of the *executed* frames + a 2-layer MLP.

    The sequence ``e`` (B, T, E) is summarised as [first, masked mean, last valid] (3E) -- the
    last frame carries the outcome, the mean the course of the episode -- then Linear-ReLU-Linear.
    """

    requires_future_frames = True

    def __init__(self, cfg: FIRPConfig = FIRPConfig()):
        super().__init__()
        self.cfg = cfg
        E = cfg.encoder.feature_dim
        self.projection = FeatureProjection(cfg.encoder)
        self.mlp = nn.Sequential(nn.Linear(3 * E, cfg.baseline.hidden), nn.ReLU(), nn.Linear(cfg.baseline.hidden, 1))

    def _logits(self, features: Tensor, mask: Tensor | None) -> Tensor:
        if features.ndim != 3:
            raise ValueError("the Oracle needs features of every executed frame, (B, T, Db)")
        e = self.projection(features)  # (B, T, E)
        B, T, _ = e.shape
        m = mask.to(e.dtype).unsqueeze(-1) if mask is not None else e.new_ones(B, T, 1)
        mean = (e * m).sum(dim=1) / m.sum(dim=1).clamp_min(1.0)
        last = e[torch.arange(B, device=e.device), last_valid_index(mask, T, B, e.device)]
        return self.mlp(torch.cat([e[:, 0], mean, last], dim=-1)).squeeze(-1)

    def forward_train(self, features: Tensor, actions: Tensor | None = None, mask: Tensor | None = None, **_: object) -> dict[str, Tensor]:
        return {"logits": self._logits(features, mask)}

    def score(self, features: Tensor, actions: Tensor | None = None, mask: Tensor | None = None) -> Score:
        return Score(self._logits(features, mask), None, None)


def build_model(kind: str, cfg: FIRPConfig = FIRPConfig()) -> nn.Module:
    """One of :data:`MODEL_KINDS` by name (for CLI flags and manifests)."""
    models: dict[str, type[nn.Module]] = {
        "firp": FIRP, "a_mlp": AMLP, "a_mlp_image": AMLPImage, "gru": GRUBaseline, "oracle": Oracle,
    }
    if kind not in models:
        raise ValueError(f"unknown model kind {kind!r}; one of {MODEL_KINDS}")
    return models[kind](cfg)
