"""Scoring plans with an ensemble bundle: one image, N plans, M members -> probabilities.

Why an ensemble: the members' disagreement (``spread``) tells the planner how much to trust a
probability, and their mean is usually better calibrated than one member's. Why this structure:

* **One backbone, run once per call.** Every member reads the same frozen backbone features of
  the initial image (the bundle enforces one shared backbone + image size), so the image goes
  through the backbone once per call -- not once per plan, not once per member.
* **FIRP members as one computation** (:mod:`firp.serving.fused`) with ``strategy="fused"`` (the
  default): members of one architecture -- the shipped five differ only in their loss weights, which
  shape training, not the computation (:func:`architecture_key`) -- run as one batched rollout. Other
  kinds (the baselines, which no shipped bundle holds) are called one by one.
  ``strategy="loop"`` calls every member's own ``score`` in turn: the reference the fused path is
  tested against.
* **Everything under ``torch.inference_mode()``**, and every plan checked by the contract's one
  validator against the plan lengths the bundle was trained on.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from firp.bundle import Bundle, backbone_key
from firp.core.contract import PLAN_WIDTH, PlanValidationError, validate_plan
from firp.model.config import FIRPConfig
from firp.model.encoder import ImageEncoder
from firp.serving.fused import FusedFIRP

__all__ = ["EnsembleResult", "EnsembleScorer", "Strategy", "architecture_key"]

Strategy = Literal["fused", "loop"]

#: Kinds with a fused ensemble computation.
FUSED_KINDS = ("firp",)

#: How a unit of members runs: their own ``score`` one by one (None), or fused.
Unit = tuple[list[int], "FusedFIRP | None"]


def architecture_key(kind: str, cfg: FIRPConfig) -> str:
    """Members with equal keys run the same code on equally shaped weights, so they can be stacked.

    The loss weights are left out: they shape training, not the computation. (Keying on the whole
    config put each of the shipped bundle's five members -- which differ only in their loss weights --
    in a group of its own, so they were never batched.)
    """
    arch = cfg.to_dict()
    arch.pop("loss", None)
    return json.dumps([kind, arch], sort_keys=True)


@dataclass(frozen=True)
class EnsembleResult:
    """Scores of N plans by an M-member ensemble (numpy, ready for JSON)."""

    probabilities: np.ndarray  # (N,) mean over members of sigmoid(logit)
    member_probabilities: np.ndarray  # (M, N)
    spread: np.ndarray  # (N,) std over members (ddof=0: defined for M = 1, where it is 0)
    weights: np.ndarray | None  # (N, T) mean attention over the members that have one; None if none
    success: np.ndarray  # (N,) bool, probabilities >= threshold
    threshold: float


class EnsembleScorer:
    """Scores plans for one initial image with every member of a :class:`~firp.bundle.Bundle`."""

    def __init__(self, bundle: Bundle, strategy: Strategy = "fused", device: str = "cpu"):
        """``device``: ``cpu``, ``cuda`` or ``auto`` (:func:`firp.train.resolve_device`): where the members and
        the backbone run; inputs and results stay numpy on the host."""
        if strategy not in ("fused", "loop"):
            raise ValueError(f"strategy must be 'fused' or 'loop', got {strategy!r}")
        from firp.train import resolve_device

        self.device = resolve_device(device)
        keys = {json.dumps(backbone_key(c.encoder), sort_keys=True) for c in bundle.configs}
        assert len(keys) == 1, f"members must share one backbone and image size, got {sorted(keys)}"
        assert backbone_key(bundle.encoder_config) == backbone_key(bundle.configs[0].encoder)
        self.bundle = bundle
        self.models = [m.to(self.device) for m in bundle.models]
        self.threshold = float(bundle.threshold)
        self.t_range = bundle.t_range
        self.strategy: Strategy = strategy
        # The one frozen backbone (its projection is unused: each member owns its projection).
        self.encoder = ImageEncoder(bundle.encoder_config, backbone=bundle.backbone).eval().to(self.device)
        self.encoder.requires_grad_(False)
        # The members as units (member indices, how they run): FIRP members of one architecture form
        # one fused group; every other member runs on its own.
        self.units: list[Unit] = []
        groups: dict[str, list[int]] = {}
        for i, (kind, cfg) in enumerate(zip(bundle.kinds, bundle.configs)):
            if strategy == "fused" and kind in FUSED_KINDS:
                groups.setdefault(architecture_key(kind, cfg), []).append(i)
            else:
                self.units.append(([i], None))
        self.units = [(idx, FusedFIRP([self.models[i] for i in idx])) for idx in groups.values()] + self.units

    @property
    def n_members(self) -> int:
        return len(self.models)

    def _check_image(self, image: np.ndarray) -> np.ndarray:
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 3:
            desc = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"image must be a uint8 numpy array (H, W, 3), got {desc}")
        return image

    def _check_plans(self, plans: object) -> np.ndarray:
        arr = plans if isinstance(plans, np.ndarray) else np.asarray(plans)
        if arr.ndim != 3 or arr.shape[0] == 0:
            raise PlanValidationError("plans", "shape", f"must be a non-empty (N, T, {PLAN_WIDTH}) array, "
                                      f"got shape {arr.shape}")
        return np.stack([validate_plan(p, self.t_range, field=f"plans[{i}]") for i, p in enumerate(arr)])

    def _check_inputs(self, image: np.ndarray, plans: object) -> tuple[np.ndarray, np.ndarray]:
        return self._check_image(image), self._check_plans(plans)

    @property
    def uses_fused(self) -> bool:
        """Whether FIRP members run as one fused computation per group of equal architecture."""
        return self.strategy == "fused"

    def _run_members(self, features: Tensor, actions: Tensor) -> tuple[Tensor, list[Tensor | None]]:
        """(M, N) logits and per-member (N, T) weights (or None), in member order.

        ``features`` (1, Db) (one scene for every plan) or (N, Db) (a scene per plan). The fused
        groups take them as they are (one projection per scene, not per plan); the modules want a row
        per plan.
        """
        M, N = len(self.models), actions.shape[0]
        per_plan = features.expand(N, -1) if features.shape[0] == 1 else features
        logits: list[Tensor | None] = [None] * M
        weights: list[Tensor | None] = [None] * M
        for idx, runner in self.units:
            if runner is None:
                for i in idx:
                    score = self.models[i].score(per_plan, actions)
                    logits[i], weights[i] = score.logits, score.weights
            else:
                lg, wt = runner(features, actions)
                for j, i in enumerate(idx):
                    logits[i] = lg[j]
                    weights[i] = wt[j]
        return torch.stack(logits), weights  # type: ignore[arg-type]

    def score(self, image: np.ndarray, plans: np.ndarray) -> EnsembleResult:
        """Score ``plans`` (N, T, 16) for the scene in ``image`` (uint8 (H, W, 3)).

        Raises :class:`~firp.core.contract.PlanValidationError` (from the contract's validator, field
        ``plans[i]...``) for the first plan that breaks the contract or the bundle's T range.
        """
        image, checked = self._check_inputs(image, plans)  # everything checked before any compute
        return self._score_checked(self.image_features(image), checked)

    def image_features(self, image: np.ndarray) -> Tensor:
        """Backbone features ``(1, backbone_dim)`` of one uint8 ``(H, W, 3)`` image.

        :meth:`score` = :meth:`score_features` of these. Split out so that a caller scoring several
        plan sets for the same scene (a planner ranking and re-ranking candidates; the scoring
        service's feature cache) can run the backbone once instead of once per call.
        """
        image = self._check_image(image)
        with torch.inference_mode():
            return self.encoder.backbone_features(image[None])

    def score_features(self, features: Tensor, plans: np.ndarray) -> EnsembleResult:
        """Like :meth:`score`, from the :meth:`image_features` of the scene instead of its image.

        ``features`` is ``(1, backbone_dim)`` (one scene for all plans) or ``(N, backbone_dim)``
        (row i is the scene of plan i: the service batches concurrent requests for different
        scenes into one call this way).
        """
        checked = self._check_plans(plans)
        dim, n = self.encoder.backbone_dim, checked.shape[0]
        if not isinstance(features, Tensor) or features.ndim != 2 or features.shape[1] != dim \
                or features.shape[0] not in (1, n):
            desc = tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__
            raise ValueError(f"features must be a (1, {dim}) tensor from image_features, or ({n}, {dim}) with one "
                             f"row per plan, got {desc}")
        return self._score_checked(features, checked)

    def _score_checked(self, features: Tensor, checked: np.ndarray) -> EnsembleResult:
        with torch.inference_mode():
            actions = torch.from_numpy(checked).to(torch.float32).to(self.device)
            # (1, Db) stays one row: the backbone ran once, and fused members project it once
            logits, weights = self._run_members(features.to(self.device), actions)
            logits, weights = logits.cpu(), [w.cpu() if w is not None else None for w in weights]
            member_probs = torch.sigmoid(logits.double())  # (M, N)
            probs = member_probs.mean(dim=0)
            spread = member_probs.std(dim=0, unbiased=False)
            have = [w for w in weights if w is not None]
            mean_w = torch.stack(have).double().mean(dim=0).numpy() if have else None
        probs_np = probs.numpy()
        return EnsembleResult(
            probabilities=probs_np,
            member_probabilities=member_probs.numpy(),
            spread=spread.numpy(),
            weights=mean_w,
            success=probs_np >= self.threshold,
            threshold=self.threshold,
        )
