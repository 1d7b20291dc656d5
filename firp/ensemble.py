"""Scoring plans with an ensemble bundle: one image, N plans, M members -> probabilities.

Why an ensemble: the members' disagreement (``spread``) tells the planner how much to trust a
probability, and their mean is usually better calibrated than one member's. Why this structure:

* **One backbone, run once per call.** Every member reads the same frozen backbone features of
  the initial image (the bundle enforces one shared backbone + image size), so the image goes
  through the backbone once per call -- not once per plan, not once per member. One
  EfficientNet-Lite0 pass at 224 px took ~51 ms here, a third to a half of an N=1 call; once per
  member it would dominate.
* **Members as one computation.** The recurrence is what costs: a T = 120 plan of the shipped
  bundle (4 plan steps per transition) is 30 sequential RSSM transitions per member, each a dozen
  small ops. Three strategies, all giving the loop's numbers (tests hold them to 1e-5; measured
  max probability difference 6e-7):

  - ``"loop"`` calls each member in turn (the reference);
  - ``"vmap"`` stacks the members' weights (``torch.func.stack_module_state``) and runs one
    ``functional_call`` under ``torch.func.vmap`` over the member axis. PyTorch has no vmap batching
    rule for ``aten::gru_cell`` (it falls back to a per-member loop with a performance warning), so
    the vmapped copy swaps each ``nn.GRUCell`` for the same equations written with ``F.linear``
    (:class:`_GRUCellOps`), with the same parameter names;
  - ``"fused"`` runs FIRP members of one architecture as one hand-batched computation
    (:class:`_FusedFIRP`): weights stacked once at load into ``(M, in, out)`` tensors, every matmul
    a ``baddbmm`` over the member axis, the action half of the transition MLP's first layer applied
    to all chunks before the loop, its second layer folded into the GRU's input weights, the GRU's
    hidden weights concatenated with the prior's first layer (three matmuls per step instead of six),
    the prior's std never computed (scoring uses means), and the decoder and the head after the loop.

  Measured with ``benchmarks/ensemble_scoring.py --bundle models/stacking --N 1 8 32
  --repeats 15`` (the shipped bundle: five members, 128-d RSSM, chunks of 4; T = 120; one thread;
  this project's 2-core CPU shared with two training processes, load average 4, so absolute
  times are inflated and noisy; result in ``docs/results/ensemble_scoring.json``), min over
  repeats, loop / vmap / fused: N=1: 43.0 / 32.0 / 9.2 ms; N=8: 45.4 / 37.7 / 16.3 ms; N=32:
  80.7 / 80.2 / 36.5 ms. With the default ``FIRPConfig`` (200-d, one transition per step: 119
  transitions; ``--N 1 8 32 --repeats 10``): N=1: 106 / 108 / 45 ms; N=8: 303 / 287 / 132 ms;
  N=32: 549 / 622 / 348 ms. Fused wins everywhere, so ``strategy="auto"`` (the default) fuses
  every FIRP group; other vmappable kinds (A-MLP baselines) use vmap up to
  :data:`AUTO_VMAP_MAX_N` plans and the loop above; the GRU baseline always runs one by one.

  Why fusing pays more than vmap: at N = 1 the rollout is bound by per-op dispatch (one member
  alone, fused, took ~4 ms; five took 8-11 ms) and by streaming the weights -- 2.4 MB per step for
  five members, more than this CPU's 2 MB L2, so each step reads them from L3 (a batched matmul of
  cold weights ran at the speed of plain reading them, ~19 GB/s here). Fusing cuts the ops per step
  about four-fold and the bytes by the folded layer; vmap only batches the dispatch of what the
  modules do. Also tried on the fused loop (~8 ms), and not kept: ``torch.jit.script`` (-1.4 ms, but
  deprecated in torch 2.13: a DeprecationWarning) and ``torch.compile`` (-1.7 ms, but 67 s to
  compile at start-up here, and again for every other plan length, as the loop is unrolled).
  Members whose configs differ only in their loss weights (the shipped five) share an architecture
  and are batched together (:func:`_architecture_key`).
* **Everything under ``torch.inference_mode()``**, and every plan checked by the contract's one
  validator against the plan lengths the bundle was trained on.
"""

from __future__ import annotations

import copy
import json
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.func import functional_call, stack_module_state, vmap

from firp.bundle import Bundle, backbone_key
from firp.core.contract import PLAN_WIDTH, T_MIN, PlanValidationError, validate_plan
from firp.model.config import FIRPConfig
from firp.model.encoder import ImageEncoder
from firp.model.firp import FIRP, chunk_actions, spread_chunk_weights
from firp.model.ops import safe_unit
from firp.model.plan_geometry import plan_geometry, standardise

__all__ = ["AUTO_VMAP_MAX_N", "EnsembleResult", "EnsembleScorer", "Strategy"]

Strategy = Literal["auto", "fused", "loop", "vmap"]

#: ``strategy="auto"`` runs vmappable members that are not fused (A-MLP baselines) with vmap for at
#: most this many plans, the loop above (for FIRP members vmap was faster up to 8 plans, the loop
#: from 12 on, before they were fused). Machine-dependent.
AUTO_VMAP_MAX_N = 8

#: Kinds whose every op has a vmap batching rule once GRUCell is decomposed. The GRU baseline's
#: ``nn.GRU`` has none either; such members are called one by one whatever the strategy.
_VMAP_KINDS = ("firp", "a_mlp", "a_mlp_image")

#: Scenes whose projections a fused group keeps (a planner scores many plans for one scene).
_SCENES = 4

#: Kinds with a hand-fused ensemble computation (:class:`_FusedFIRP`).
_FUSED_KINDS = ("firp",)


def _architecture_key(kind: str, cfg: FIRPConfig) -> str:
    """Members with equal keys run the same code on equally shaped weights, so they can be stacked.

    The loss weights are left out: they shape training, not the computation. (Keying on the whole
    config, as this module once did, put each of the shipped bundle's five members -- which differ
    only in their loss weights -- in a group of its own, so they were never batched.)
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


# ------------------------------------------------------------------------------------------------
# The fused FIRP rollout
# ------------------------------------------------------------------------------------------------


def _linear_parts(mlp: nn.Module) -> tuple[nn.Linear, nn.Linear]:
    """The two Linear layers of a :func:`firp.model.ops.mlp2` (Linear-ReLU-Linear); anything else
    is refused, because the fused rollout hard-codes that shape."""
    if not (isinstance(mlp, nn.Sequential) and len(mlp) == 3 and isinstance(mlp[0], nn.Linear)
            and isinstance(mlp[1], nn.ReLU) and isinstance(mlp[2], nn.Linear)):
        raise TypeError(f"the fused rollout expects Linear-ReLU-Linear, got {mlp}")
    return mlp[0], mlp[2]


def _stack_t(weights: list[Tensor]) -> Tensor:
    """M ``nn.Linear`` weights ``(out, in)`` -> ``(M, in, out)``, the layout ``baddbmm(b, x, W)`` reads."""
    return torch.stack([w.detach().t() for w in weights]).contiguous()


def _stack_b(biases: list[Tensor]) -> Tensor:
    """M biases ``(out,)`` -> ``(M, 1, out)``: broadcast over the rows of each member's batch."""
    return torch.stack([b.detach() for b in biases]).unsqueeze(1).contiguous()


def _prior_rollout(pre: Tensor, s: Tensor, h: Tensor, w_s: Tensor, w_u: Tensor, b_u: Tensor, w_hp: Tensor,
                   b_hp: Tensor, w_p2: Tensor, b_p2: Tensor) -> tuple[Tensor, Tensor]:
    """The sequential part of :meth:`RSSM.imagine` on means, for M members and N plans at once.

    ``pre`` (Tc, M, N, hid): the action half of f's first layer (+ its bias) for every chunk, ``s``
    (M, N, S) and ``h`` (M, N, H): the latent at index 0. Per step, three batched matmuls:
    ``u = relu(pre_t + s W_s)`` (f's first layer), ``gi = u W_u + b_u`` (f's second layer folded
    into the GRU's input weights), ``[gh | p] = h W_hp + b_hp`` (the GRU's hidden weights and the
    prior's first layer share their input ``h``; ``gh`` is kept for the next step), then the GRU
    gates and ``s = relu(p) W_p2 + b_p2`` (the prior mean only: scoring never samples).
    Returns ``h`` (M, N, Tc-1, H) and ``s`` (M, N, Tc-1, S) for indices 1..Tc-1.
    """
    H = h.shape[-1]
    ghp = torch.baddbmm(b_hp, h, w_hp)
    hs: list[Tensor] = []
    ss: list[Tensor] = []
    for t in range(1, pre.shape[0]):
        u = torch.relu(torch.baddbmm(pre[t], s, w_s))
        gi = torch.baddbmm(b_u, u, w_u)
        rz = torch.sigmoid(gi[..., : 2 * H] + ghp[..., : 2 * H])
        n = torch.tanh(gi[..., 2 * H:] + rz[..., :H] * ghp[..., 2 * H: 3 * H])
        h = torch.lerp(n, h, rz[..., H:])  # (1 - z) * n + z * h, GRUCell's update
        ghp = torch.baddbmm(b_hp, h, w_hp)
        s = torch.baddbmm(b_p2, torch.relu(ghp[..., 3 * H:]), w_p2)
        hs.append(h)
        ss.append(s)
    return torch.stack(hs, dim=2), torch.stack(ss, dim=2)


class _FusedFIRP:
    """FIRP members of one architecture as one computation: ``FIRP.score`` with the member axis as
    a batch axis of every matmul.

    Why: a T = 120 plan in chunks of 4 is 30 sequential RSSM transitions, each a dozen small ops
    per member; at N = 1 each op costs more in dispatch than in arithmetic, so M members in a
    Python loop pay M times the overhead for the same bytes of weights (see the module docstring
    for the measured gain). What is rearranged, all exact algebra on :mod:`firp.model.rssm`'s
    equations with ``sample=False`` (the weights are stacked once here, at load):

    * f's first layer on ``concat(s, a)`` is split into ``W_s s + W_a a``; the action part for every
      chunk of every plan is one matmul before the loop;
    * f's second layer is folded into the GRU's input weights (``W_ih (W_2 u + b_2) + b_ih``, the
      product formed in float64), and the GRU's hidden weights are concatenated with the prior's
      first layer, which reads the same ``h``: three matmuls per step instead of six;
    * only the mean half of the Gaussian heads is computed (std is unused without sampling);
    * the decoder, the head's query MLP and the attention run once on the stacked states after the
      loop, not inside it.

    Rounding differs from the per-member modules (other summation orders), by ~1e-6 in a logit;
    tests hold the probabilities and weights to the loop's within 1e-5.

    Holds only plain tensors (no parameter swapping), so it is safe to call from any thread.

    The members' projections of a scene's features (and the scene's part of the posterior's first
    layer) are kept for the last :data:`_SCENES` scenes, matched by value (``torch.equal``): the
    projection reads 1280 x 256 weights per member for one row -- 6.5 MB for five members, measured
    0.8-1.7 ms of a ~10 ms call here -- and a planner scores many plans for one scene.
    """

    def __init__(self, models: Sequence[FIRP]):
        m0 = models[0]
        if not all(isinstance(m, FIRP) for m in models):
            raise TypeError("only FIRP members are fused")
        if len({m.geometry is None for m in models}) != 1:
            raise TypeError("fused members must all read the plan's grasp-frame description, or none")
        rssm_cfg = m0.rssm.cfg
        self.members = list(models)
        self.chunk = m0.cfg.action_chunk
        self.H, self.S = rssm_cfg.deter_dim, rssm_cfg.stoch_dim
        self.temperature = m0.head.cfg.temperature
        S, H = self.S, self.H
        with torch.no_grad():
            self.norm_mean = torch.stack([m.action_norm.mean for m in models])[:, None, None, :]  # (M, 1, 1, A)
            self.norm_std = torch.stack([m.action_norm.std for m in models])[:, None, None, :]
            f1 = [_linear_parts(m.rssm.f)[0] for m in models]
            f2 = [_linear_parts(m.rssm.f)[1] for m in models]
            self.w_s = _stack_t([l.weight[:, :S] for l in f1])  # (M, S, hid): f on s_{t-1}
            self.w_a = _stack_t([l.weight[:, S:] for l in f1])  # (M, k*A, hid): f on a_t
            self.b_a = _stack_b([l.bias for l in f1])
            cells = [m.rssm.rnn for m in models]
            if any(c.bias_ih is None or c.bias_hh is None for c in cells):
                raise TypeError("the fused rollout expects GRUCell(bias=True)")
            w_ih, b_ih = _stack_t([c.weight_ih for c in cells]), _stack_b([c.bias_ih for c in cells])
            w_2, b_2 = _stack_t([l.weight for l in f2]), _stack_b([l.bias for l in f2])
            self.w_u = torch.bmm(w_2.double(), w_ih.double()).float()  # (M, hid, 3H)
            self.b_u = (torch.bmm(b_2.double(), w_ih.double()) + b_ih.double()).float()  # (M, 1, 3H)
            p1 = [_linear_parts(m.rssm.g_hat)[0] for m in models]
            p2 = [_linear_parts(m.rssm.g_hat)[1] for m in models]
            self.w_hp = torch.cat([_stack_t([c.weight_hh for c in cells]), _stack_t([l.weight for l in p1])], 2)
            self.b_hp = torch.cat([_stack_b([c.bias_hh for c in cells]), _stack_b([l.bias for l in p1])], 2)
            self.w_p2 = _stack_t([l.weight[:S] for l in p2])  # the mean rows only
            self.b_p2 = _stack_b([l.bias[:S] for l in p2])
            g1 = [_linear_parts(m.rssm.g)[0] for m in models]
            g2 = [_linear_parts(m.rssm.g)[1] for m in models]
            self.w_gh = _stack_t([l.weight[:, :H] for l in g1])  # posterior g(h, e) split on (h, e)
            self.w_ge = _stack_t([l.weight[:, H:] for l in g1])
            self.b_g1 = _stack_b([l.bias for l in g1])
            self.w_g2 = _stack_t([l.weight[:S] for l in g2])
            self.b_g2 = _stack_b([l.bias[:S] for l in g2])
            d1 = [_linear_parts(m.rssm.decoder)[0] for m in models]
            d2 = [_linear_parts(m.rssm.decoder)[1] for m in models]
            self.w_d1, self.b_d1 = _stack_t([l.weight for l in d1]), _stack_b([l.bias for l in d1])
            self.w_d2, self.b_d2 = _stack_t([l.weight for l in d2]), _stack_b([l.bias for l in d2])
            q1 = [_linear_parts(m.head.q)[0] for m in models]
            q2 = [_linear_parts(m.head.q)[1] for m in models]
            self.w_q1, self.b_q1 = _stack_t([l.weight for l in q1]), _stack_b([l.bias for l in q1])
            self.w_q2, self.b_q2 = _stack_t([l.weight for l in q2]), _stack_b([l.bias for l in q2])
            self.prototypes = torch.stack([safe_unit(m.head.prototypes) for m in models])  # (M, P, Q)
            self.w_out = _stack_t([m.head.out.weight for m in models])  # (M, Q [+ Hc], 1)
            self.b_out = _stack_b([m.head.out.bias for m in models])
            # the head's context: the plan's grasp-frame description, standardised per member, through an MLP
            self.max_picks = m0.geometry.max_picks if m0.geometry is not None else None
            if self.max_picks is not None:
                self.g_mean = torch.stack([m.geometry.mean for m in models])[:, None, :]  # (M, 1, G)
                self.g_std = torch.stack([m.geometry.std for m in models])[:, None, :]
                c1 = [_linear_parts(m.head.context)[0] for m in models]
                c2 = [_linear_parts(m.head.context)[1] for m in models]
                self.w_c1, self.b_c1 = _stack_t([l.weight for l in c1]), _stack_b([l.bias for l in c1])
                self.w_c2, self.b_c2 = _stack_t([l.weight for l in c2]), _stack_b([l.bias for l in c2])
        self._lock = threading.Lock()
        self._scenes: list[tuple[Tensor, Tensor, Tensor]] = []  # (features, e_1, ge), most recent last

    def _scene(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """``e_1`` (M, 1 or N, E) = each member's projection of ``features``, and the posterior's
        first layer on it (+ bias) (M, 1 or N, hid); cached for one-row features (see above)."""
        single = features.shape[0] == 1
        if single:
            with self._lock:
                for i, (seen, e1, ge) in enumerate(self._scenes):
                    if torch.equal(seen, features):
                        self._scenes.append(self._scenes.pop(i))  # most recent last
                        return e1, ge
        e1 = torch.stack([m.projection(features) for m in self.members])  # (M, 1 or N, E): per member
        ge = torch.baddbmm(self.b_g1, e1, self.w_ge)
        if single:
            with self._lock:
                self._scenes = (self._scenes + [(features.clone(), e1, ge)])[-_SCENES:]
        return e1, ge

    def __call__(self, features: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """``features`` (1 or N, Db) backbone features, ``actions`` (N, T, A) plans ->
        logits (M, N) and attention weights (M, N, T), as each member's ``score`` gives them."""
        members, k, H = self.members, self.chunk, self.H
        M, (N, T, A) = len(members), actions.shape
        e1, ge = self._scene(features)  # (M, 1 or N, E), (M, 1 or N, hid)
        a = (actions.unsqueeze(0) - self.norm_mean) / self.norm_std  # (M, N, T, A)
        a = chunk_actions(a.reshape(M * N, T, A), k)  # (M*N, Tc, k*A)
        Tc = a.shape[1]
        pre = torch.baddbmm(self.b_a, a.reshape(M, N * Tc, k * A), self.w_a)  # (M, N*Tc, hid)
        pre = pre.view(M, N, Tc, -1).permute(2, 0, 1, 3).contiguous()  # (Tc, M, N, hid)
        # index 0: h_0 = s_0 = 0, so f sees the action alone and the GRU's hidden part is its bias
        gi = torch.baddbmm(self.b_u, torch.relu(pre[0]), self.w_u)  # (M, N, 3H)
        gh = self.b_hp[..., : 3 * H]
        rz = torch.sigmoid(gi[..., : 2 * H] + gh[..., : 2 * H])
        n = torch.tanh(gi[..., 2 * H:] + rz[..., :H] * gh[..., 2 * H:])
        h = (1.0 - rz[..., H:]) * n  # GRUCell's (1 - z) * n + z * h with h = 0
        # the posterior mean at index 0 from g(h_1, e_1) (its e_1 part: ge)
        s = torch.baddbmm(self.b_g2, torch.relu(torch.baddbmm(ge, h, self.w_gh)), self.w_g2)  # (M, N, S)
        seq = e1.expand(M, N, -1).unsqueeze(2)  # (M, N, 1, E): e_1 starts the head's sequence
        if Tc > 1:
            hs, ss = _prior_rollout(pre, s, h, self.w_s, self.w_u, self.b_u, self.w_hp, self.b_hp, self.w_p2,
                                    self.b_p2)
            d = torch.cat([ss, hs], dim=-1).view(M, N * (Tc - 1), -1)  # D(s, h) on every predicted step
            pred = torch.baddbmm(self.b_d2, torch.relu(torch.baddbmm(self.b_d1, d, self.w_d1)), self.w_d2)
            seq = torch.cat([seq, pred.view(M, N, Tc - 1, -1)], dim=2)  # (M, N, Tc, E)
        q = torch.baddbmm(self.b_q1, seq.reshape(M, N * Tc, -1), self.w_q1)
        q = torch.baddbmm(self.b_q2, torch.relu(q), self.w_q2).view(M, N, Tc, -1)  # (M, N, Tc, Q)
        cos = torch.einsum("mpq,mntq->mnpt", self.prototypes, safe_unit(q))  # (M, N, P, Tc)
        w = torch.softmax(cos / self.temperature, dim=-1).mean(dim=2)  # (M, N, Tc)
        pooled = torch.einsum("mnt,mntq->mnq", w, q)
        if self.max_picks is not None:  # the description is computed once for every member
            z = standardise(plan_geometry(actions, None, self.max_picks).unsqueeze(0), self.g_mean, self.g_std)  # (M, N, G)
            c = torch.baddbmm(self.b_c2, torch.relu(torch.baddbmm(self.b_c1, z, self.w_c1)), self.w_c2)
            pooled = torch.cat([pooled, torch.relu(c)], dim=-1)  # (M, N, Q + Hc)
        logits = torch.baddbmm(self.b_out, pooled, self.w_out).squeeze(-1)  # (M, N)
        return logits, spread_chunk_weights(w.reshape(M * N, Tc), T, k).view(M, N, T)


# ------------------------------------------------------------------------------------------------
# The scorer
# ------------------------------------------------------------------------------------------------

#: How a unit of members runs: plain calls one by one (None), vmapped, or fused.
_Unit = tuple[list[int], "_VmappedGroup | _FusedFIRP | None"]


class EnsembleScorer:
    """Scores plans for one initial image with every member of a :class:`~firp.bundle.Bundle`."""

    def __init__(self, bundle: Bundle, strategy: Strategy = "auto"):
        if strategy not in ("auto", "fused", "loop", "vmap"):
            raise ValueError(f"strategy must be 'auto', 'fused', 'loop' or 'vmap', got {strategy!r}")
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
        # Execution plans over the same members, as units (member indices, how they run): members of
        # one kind and one architecture (same code, same shapes) form a group; FIRP groups run fused,
        # other vmappable groups vmapped, the rest (GRU baseline) one by one. ``_small`` serves calls
        # of at most AUTO_VMAP_MAX_N plans, ``_large`` the others (they differ only for "auto").
        groups: dict[str, list[int]] = {}
        for i, (kind, cfg) in enumerate(zip(bundle.kinds, bundle.configs)):
            groups.setdefault(_architecture_key(kind, cfg), []).append(i)
        loop: list[_Unit] = [([i], None) for i in range(len(self.models))]
        if strategy == "loop":
            self._small, self._large = loop, loop
            return
        vmapped: list[_Unit] = []
        fused: list[_Unit] = []  # the fused FIRP groups only
        rest_vmapped: list[_Unit] = []
        rest_loop: list[_Unit] = []
        dim = bundle.encoder_config.backbone_dim
        for idx in groups.values():
            kind, members = bundle.kinds[idx[0]], [self.models[i] for i in idx]
            one_by_one: list[_Unit] = [([i], None) for i in idx]
            batched: list[_Unit] = [(idx, _VmappedGroup(members, dim))] if kind in _VMAP_KINDS and len(idx) > 1 \
                else one_by_one
            if strategy == "vmap":
                vmapped += batched
            elif kind in _FUSED_KINDS:
                fused.append((idx, _FusedFIRP(members)))  # type: ignore[arg-type]
            else:
                rest_vmapped += batched
                rest_loop += one_by_one
        if strategy == "vmap":
            self._small, self._large = vmapped, vmapped
        elif strategy == "fused":
            self._small, self._large = fused + rest_vmapped, fused + rest_vmapped
        else:
            self._small, self._large = fused + rest_vmapped, fused + rest_loop

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
        """Whether a call with ``n_plans`` plans runs the vmappable members that are not fused
        (or, with ``strategy="vmap"``, all vmappable members) with vmap."""
        return self.strategy in ("vmap", "fused") or (self.strategy == "auto" and n_plans <= AUTO_VMAP_MAX_N)

    @property
    def uses_fused(self) -> bool:
        """Whether FIRP members run as one fused computation per group of equal architecture."""
        return self.strategy in ("auto", "fused")

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
        for idx, runner in self._small if N <= AUTO_VMAP_MAX_N else self._large:
            if runner is None:
                for i in idx:
                    score = self.models[i].score(per_plan, actions)
                    logits[i], weights[i] = score.logits, score.weights
            else:
                lg, wt = runner(features if isinstance(runner, _FusedFIRP) else per_plan, actions)
                for j, i in enumerate(idx):
                    logits[i] = lg[j]
                    weights[i] = None if wt is None else wt[j]
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
            actions = torch.from_numpy(checked).to(torch.float32)
            # (1, Db) stays one row: the backbone ran once, and fused members project it once
            logits, weights = self._run_members(features, actions)
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
