"""Scoring plans with an ensemble bundle: one image, N plans, M members -> probabilities.

Why an ensemble: the members' disagreement (``spread``) tells the planner how much to trust a
probability, and their mean is usually better calibrated than one member's. Why this structure:

* **One backbone, run once per call.** Every member reads the same frozen backbone features of
  the initial image (the bundle enforces one shared backbone + image size), so the image goes
  through the backbone once per call -- not once per plan, not once per member. One
  EfficientNet-Lite0 pass at 224 px took ~51 ms here, a third to a half of an N=1 call; once per
  member it would dominate.
* **Members as one computation where it pays.** ``"vmap"`` stacks the members' weights
  (``torch.func.stack_module_state``) and runs one ``functional_call`` under ``torch.func.vmap``
  over the member axis; ``"loop"`` calls each member in turn. Both give the same numbers (max
  difference ~6e-8; a test holds them to 1e-5). PyTorch has no vmap batching rule for
  ``aten::gru_cell`` (it falls back to a per-member loop with a performance warning), so the
  vmapped copy swaps each ``nn.GRUCell`` for the same equations written with ``F.linear``
  (:class:`_GRUCellOps`), with the same parameter names.

  Measured with ``benchmarks/ensemble_scoring.py`` (default FIRPConfig, M=5, T=120, one thread,
  this project's 2-core CPU with another process busy, so +-20% noise between runs; the last run
  is in ``docs/results/ensemble_scoring.json``), min over repeats, vmap vs loop, several runs:
  N=1: 98-165 vs 103-184 ms (vmap 3-19% faster in all seven interleaved runs); N=2: 106 vs 112;
  N=4: 196-212 vs 225-256; N=6: 249 vs 247; N=8: 252-277 vs 281-283; N=12: 368 vs 334;
  N=32: 407-576 vs 354-503 ms (loop 12-19% faster in all four runs).
  Neither wins everywhere, so ``strategy="auto"`` (the default) uses vmap up to
  :data:`AUTO_VMAP_MAX_N` plans and the loop above. Why the gains are small: the ~1,200 ops of a
  T=120 rollout are matrix-vector products over ~1.4 MB of weights per member, bound by moving
  those bytes at N=1 (the same bytes either way; vmap saves only the per-op dispatch of M-1
  members), and compute-bound at N=32, where a CPU ``bmm`` over the member axis is slower than M
  separate ``addmm`` calls.
* **Everything under ``torch.inference_mode()``**, and every plan checked by the contract's one
  validator against the plan lengths the bundle was trained on.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.func import functional_call, stack_module_state, vmap

from firp.bundle import Bundle, backbone_key
from firp.contract import PLAN_WIDTH, T_MIN, PlanValidationError, validate_plan
from firp.model.encoder import ImageEncoder

__all__ = ["AUTO_VMAP_MAX_N", "EnsembleResult", "EnsembleScorer", "Strategy"]

Strategy = Literal["auto", "loop", "vmap"]

#: ``strategy="auto"`` runs the members with vmap for at most this many plans, the loop above
#: (vmap was faster up to 8 plans, the loop from 12 on; see above). Machine-dependent.
AUTO_VMAP_MAX_N = 8

#: Kinds whose every op has a vmap batching rule once GRUCell is decomposed. The GRU baseline's
#: ``nn.GRU`` has none either; such members are called one by one whatever the strategy.
_VMAP_KINDS = ("firp", "a_mlp", "a_mlp_image")


@dataclass(frozen=True)
class EnsembleResult:
    """Scores of N plans by an M-member ensemble (numpy, ready for JSON)."""

    probabilities: np.ndarray  # (N,) mean over members of sigmoid(logit)
    member_probabilities: np.ndarray  # (M, N)
    spread: np.ndarray  # (N,) std over members (ddof=0: defined for M = 1, where it is 0)
    weights: np.ndarray | None  # (N, T) mean attention over the members that have one; None if none
    success: np.ndarray  # (N,) bool, probabilities >= threshold
    threshold: float


class _ScoreCall(nn.Module):
    """``forward`` = the member's ``score`` -> ``(logits,)`` or ``(logits, weights)``:
    ``functional_call`` needs a ``forward``, and vmap only returns tensors (no None)."""

    def __init__(self, model: nn.Module, with_weights: bool):
        super().__init__()
        self.model = model
        self.with_weights = with_weights

    def forward(self, features: Tensor, actions: Tensor) -> tuple[Tensor, ...]:
        score = self.model.score(features, actions)
        return (score.logits, score.weights) if self.with_weights else (score.logits,)


class _GRUCellOps(nn.Module):
    """``nn.GRUCell``'s equations with ``F.linear`` (which vmap batches); same parameter names.

    r = sigma(W_ir x + b_ir + W_hr h + b_hr); z likewise; n = tanh(W_in x + b_in + r * (W_hn h + b_hn));
    h' = (1 - z) * n + z * h  -- PyTorch's gate order (r, z, n) in the stacked weights.
    """

    def __init__(self, cell: nn.GRUCell):
        super().__init__()
        if cell.bias_ih is None or cell.bias_hh is None:
            raise ValueError("only GRUCell(bias=True) is decomposed")
        self.weight_ih, self.weight_hh = cell.weight_ih, cell.weight_hh
        self.bias_ih, self.bias_hh = cell.bias_ih, cell.bias_hh

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        i_r, i_z, i_n = F.linear(x, self.weight_ih, self.bias_ih).chunk(3, dim=-1)
        h_r, h_z, h_n = F.linear(h, self.weight_hh, self.bias_hh).chunk(3, dim=-1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return (1.0 - z) * n + z * h


def _decompose_gru_cells(module: nn.Module) -> nn.Module:
    for name, child in list(module.named_children()):
        if isinstance(child, nn.GRUCell):
            setattr(module, name, _GRUCellOps(child))
        else:
            _decompose_gru_cells(child)
    return module


class _VmappedGroup:
    """Members of one kind and one config (so one code path and equal shapes), stacked for vmap."""

    def __init__(self, models: list[nn.Module], backbone_dim: int):
        # Whether this kind returns attention weights: ask it (one tiny call) rather than keep a list.
        with torch.inference_mode():
            probe = models[0].score(torch.zeros(1, backbone_dim), torch.zeros(1, T_MIN, PLAN_WIDTH))
        self.with_weights = probe.weights is not None
        wrapped = [_ScoreCall(m, self.with_weights) for m in models]
        self.params, self.buffers = stack_module_state(wrapped)
        # A weightless copy that supplies the code; functional_call supplies the stacked weights.
        self.base = _decompose_gru_cells(copy.deepcopy(wrapped[0]).to("meta"))

        def one(params: dict[str, Tensor], buffers: dict[str, Tensor], features: Tensor, actions: Tensor):
            return functional_call(self.base, (params, buffers), (features, actions))

        self._call = vmap(one, in_dims=(0, 0, None, None))

    def __call__(self, features: Tensor, actions: Tensor) -> tuple[Tensor, Tensor | None]:
        out = self._call(self.params, self.buffers, features, actions)
        return out[0], (out[1] if self.with_weights else None)  # (m, N), (m, N, T) | None


class EnsembleScorer:
    """Scores plans for one initial image with every member of a :class:`~firp.bundle.Bundle`."""

    def __init__(self, bundle: Bundle, strategy: Strategy = "auto"):
        if strategy not in ("auto", "loop", "vmap"):
            raise ValueError(f"strategy must be 'auto', 'loop' or 'vmap', got {strategy!r}")
        keys = {json.dumps(backbone_key(c.encoder), sort_keys=True) for c in bundle.configs}
        assert len(keys) == 1, f"members must share one backbone and image size, got {sorted(keys)}"
        assert backbone_key(bundle.encoder_config) == backbone_key(bundle.configs[0].encoder)
        self.bundle = bundle
        self.models = bundle.models
        self.threshold = float(bundle.threshold)
        self.t_range = bundle.t_range
        self.strategy: Strategy = strategy
        # The one frozen backbone (its projection is unused: each member owns its projection).
        self.encoder = ImageEncoder(bundle.encoder_config, backbone=bundle.backbone).eval()
        self.encoder.requires_grad_(False)
        # Two execution plans over the same members: one call each, or vmapped groups of members
        # with one kind and one config (same code, same shapes); kinds vmap cannot batch, and
        # groups of one, run as plain calls in both.
        self._loop: list[tuple[list[int], _VmappedGroup | None]] = [([i], None) for i in range(len(self.models))]
        self._vmap: list[tuple[list[int], _VmappedGroup | None]] = []
        if strategy != "loop":
            by_config: dict[str, list[int]] = {}
            for i, (kind, cfg) in enumerate(zip(bundle.kinds, bundle.configs)):
                key = json.dumps([kind, cfg.to_dict()], sort_keys=True) if kind in _VMAP_KINDS else f"loop-{i}"
                by_config.setdefault(key, []).append(i)
            for idx in by_config.values():
                group = (_VmappedGroup([self.models[i] for i in idx], bundle.encoder_config.backbone_dim)
                         if len(idx) > 1 else None)
                self._vmap.append((idx, group))

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

    def uses_vmap(self, n_plans: int) -> bool:
        """Whether a call with ``n_plans`` plans runs the members with vmap."""
        return self.strategy == "vmap" or (self.strategy == "auto" and n_plans <= AUTO_VMAP_MAX_N)

    def _run_members(self, features: Tensor, actions: Tensor) -> tuple[Tensor, list[Tensor | None]]:
        """(M, N) logits and per-member (N, T) weights (or None), in member order."""
        M = len(self.models)
        logits: list[Tensor | None] = [None] * M
        weights: list[Tensor | None] = [None] * M
        for idx, group in self._vmap if self.uses_vmap(actions.shape[0]) else self._loop:
            if group is None:
                for i in idx:
                    score = self.models[i].score(features, actions)
                    logits[i], weights[i] = score.logits, score.weights
            else:
                lg, wt = group(features, actions)
                for j, i in enumerate(idx):
                    logits[i] = lg[j]
                    weights[i] = None if wt is None else wt[j]
        return torch.stack(logits), weights  # type: ignore[arg-type]

    def score(self, image: np.ndarray, plans: np.ndarray) -> EnsembleResult:
        """Score ``plans`` (N, T, 16) for the scene in ``image`` (uint8 (H, W, 3)).

        Raises :class:`~firp.contract.PlanValidationError` (from the contract's validator, field
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
        """Like :meth:`score`, from the :meth:`image_features` of the scene instead of its image."""
        dim = self.encoder.backbone_dim
        if not isinstance(features, Tensor) or tuple(features.shape) != (1, dim):
            desc = tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__
            raise ValueError(f"features must be a (1, {dim}) tensor from image_features, got {desc}")
        return self._score_checked(features, self._check_plans(plans))

    def _score_checked(self, features: Tensor, checked: np.ndarray) -> EnsembleResult:
        N = checked.shape[0]
        with torch.inference_mode():
            feats = features.expand(N, -1)  # the backbone ran once, for the one image
            actions = torch.from_numpy(checked).to(torch.float32)
            logits, weights = self._run_members(feats, actions)
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
