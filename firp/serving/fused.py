"""The fused FIRP rollout: an ensemble's FIRP members of one architecture as one computation.

Why: the recurrence is what costs. A T = 120 plan of the shipped bundle (8 plan steps per
transition) is 15 sequential RSSM transitions per member, each a dozen small ops; at one plan per
call every op costs more in dispatch than in arithmetic, so M members called one by one pay M times
the overhead for the same bytes of weights. :class:`FusedFIRP` stacks the members' weights once at
load into ``(M, in, out)`` tensors and runs every matmul as a ``baddbmm`` over the member axis, with
the algebra rearranged (the action half of the transition MLP's first layer applied to all chunks
before the loop, its second layer folded into the GRU's input weights, the GRU's hidden weights
concatenated with the prior's first layer: three matmuls per step instead of six; the prior's std
never computed; the decoder and the head after the loop).

Measured (``python benchmarks/ensemble_scoring.py --bundle models/stacking --N 1 8 32 --repeats 20``,
``docs/results/ensemble_scoring.json``; the shipped five members, T = 120, one thread, medians): the
members called in turn / fused, 1 plan 28.3 / 6.2 ms, 8 plans 25.9 / 7.0 ms, 32 plans 39.3 / 18.8 ms.
Also tried on the fused loop, and not kept: ``torch.jit.script`` (-1.4 ms, deprecated in torch 2.13)
and ``torch.compile`` (-1.7 ms, but about a minute to compile at start-up, and again for every plan
length, as the loop is unrolled).

``tests/firp/serving/test_fused.py`` holds it to the members' own forward pass (``FIRP.score``).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from firp.model.firp import FIRP, chunk_actions, spread_chunk_weights
from firp.model.ops import safe_unit
from firp.model.plan_events import PlanEvents
from firp.model.plan_geometry import standardise

__all__ = ["SCENES", "FusedFIRP"]

#: Scenes whose projections a fused group keeps (a planner scores many plans for one scene).
SCENES = 4


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


class FusedFIRP:
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
    layer) are kept for the last :data:`SCENES` scenes, matched by value (``torch.equal``): the
    projection reads 1280 x 256 weights per member for one row -- 6.5 MB for five members, measured
    0.8-1.7 ms of a ~10 ms call here -- and a planner scores many plans for one scene.
    """

    def __init__(self, models: Sequence[FIRP]):
        m0 = models[0]
        if not all(isinstance(m, FIRP) for m in models):
            raise TypeError("only FIRP members are fused")
        if len({type(m.geometry) for m in models}) != 1:
            raise TypeError("fused members must all read the plan alike: the hand-built description, the learned "
                            "events, or none")
        if any(isinstance(m.geometry, PlanEvents) and m.geometry.view is not None for m in models):
            raise TypeError("members that read the plan-conditioned view are not fused")
        events = [m.geometry for m in models if isinstance(m.geometry, PlanEvents)]
        if not all(e.reads_like(events[0]) for e in events):
            raise TypeError("fused members must read the plan's events alike (chain, max_events, plan columns)")
        described = [m.geometry for m in models if m.geometry is not None and not isinstance(m.geometry, PlanEvents)]
        if len({(g.max_picks, g.description, g.object_half) for g in described}) > 1:
            raise TypeError("fused members must describe the plan alike (max_picks, description, object_half)")
        if len({isinstance(m.head.context, nn.Linear) for m in models if m.head.context is not None}) > 1:
            raise TypeError("fused members must read the description through as many layers (1 or 2)")
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
            # the head's context: the plan's grasp-frame description, standardised per member (the members describe
            # plans alike, checked above: one of them computes it for all), or each member's learned events; then
            # each member's MLP
            self.events = [m.geometry for m in models] if isinstance(m0.geometry, PlanEvents) else None
            self.describe = m0.geometry.describe if m0.geometry is not None and self.events is None else None
            if self.describe is not None:
                self.g_mean = torch.stack([m.geometry.mean for m in models])[:, None, :]  # (M, 1, G)
                self.g_std = torch.stack([m.geometry.std for m in models])[:, None, :]
            if m0.geometry is not None:
                one_layer = isinstance(m0.head.context, nn.Linear)  # GeometryConfig.layers == 1
                c1 = [m.head.context if one_layer else _linear_parts(m.head.context)[0] for m in models]
                self.w_c1, self.b_c1 = _stack_t([l.weight for l in c1]), _stack_b([l.bias for l in c1])
                self.w_c2 = self.b_c2 = None
                if not one_layer:
                    c2 = [_linear_parts(m.head.context)[1] for m in models]
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
                self._scenes = (self._scenes + [(features.clone(), e1, ge)])[-SCENES:]
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
        if self.describe is not None or self.events is not None:
            if self.describe is not None:  # the description is computed once for every member
                z = standardise(self.describe(actions).unsqueeze(0), self.g_mean, self.g_std)  # (M, N, G)
            else:  # the events' poses and relations once (the members read alike, checked above), each member's
                raw = self.events[0].raw_features(actions)  # own standardisation and networks on them
                z = torch.stack([events.read(*raw) for events in self.events])  # (M, N, C)
            c = torch.baddbmm(self.b_c1, z, self.w_c1)  # (M, N, Hc)
            if self.w_c2 is not None:
                c = torch.baddbmm(self.b_c2, torch.relu(c), self.w_c2)
            pooled = torch.cat([pooled, torch.relu(c)], dim=-1)  # (M, N, Q + Hc)
        logits = torch.baddbmm(self.b_out, pooled, self.w_out).squeeze(-1)  # (M, N)
        return logits, spread_chunk_weights(w.reshape(M * N, Tc), T, k).view(M, N, T)
