"""What the plan says about where the hand meets the scene, learned: a relation network over the plan's events.

Why: the outcome of a pick-and-place plan is decided by geometry -- where a grasp closes relative to the
other objects the plan touches, how a release lines up with an earlier one -- and that geometry is in
the plan, through the arm's kinematics. Hand-built descriptions compute it with the task's object
sizes and the gripper's dimensions (``experiments/plan_descriptions``); this module computes only what
holds for any arm and any task, and leaves the rest to learning:

* **events**: the first step of every run of one action category (where the hand arrives to grasp,
  where the grasp has closed, where a release opens, ...), up to ``max_events`` per plan;
* **the hand at each event**: the tool point's pose in the robot base's frame, by forward kinematics
  of the joint targets (:class:`~firp.model.kinematics.ChainFK`; the chain comes from the dataset), and
  the gripper's targets;
* **relations**: every other event's hand pose *in this event's hand frame* (offset, relative rotation)
  and which category it is, how much later or earlier.

A shared MLP reads each (event, other event) relation; max- and mean-pooling over the other events
give each event what is near it (a max over learned functions of offsets can express "the nearest
thing on the fingers' path"); a second MLP and pooling over events give the plan's vector, which the
success head reads beside the pooled sequence (:class:`~firp.model.head.SuccessHead`'s context).
Inputs are standardised with training-set statistics (:meth:`PlanEvents.fit`), so no scale is chosen
by hand. Shapes: B plans, T steps, E events, D features.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from firp.core.contract import N_CATEGORIES
from firp.core.kinematics import KinematicChain
from firp.model.config import FIRPConfig, PlanEventsConfig
from firp.model.kinematics import ChainFK, rotation_6d
from firp.model.ops import mlp2, plan_categories
from firp.model.plan_geometry import STANDARD_CLIP, build_plan_geometry
from firp.model.plan_view import PlanView

__all__ = ["PlanEvents", "build_plan_events", "build_plan_reader", "event_steps", "read_plan"]


def event_steps(actions: Tensor, mask: Tensor | None, max_events: int) -> tuple[Tensor, Tensor]:
    """The first step of every category run, in plan order: indices ``(B, E)`` (0 where absent) and a presence
    mask ``(B, E)``, E the most events of any plan in the batch (at most ``max_events``). Step 0 always starts a
    run; a run beyond ``max_events`` is left out."""
    categories = plan_categories(actions)  # (B, T)
    B, T = categories.shape
    starts = torch.ones(B, T, dtype=torch.bool, device=actions.device)
    starts[:, 1:] = categories[:, 1:] != categories[:, :-1]
    if mask is not None:
        starts &= mask.bool()
    rank = torch.cumsum(starts.long(), dim=1) - 1  # (B, T)
    keep = starts & (rank < max_events)
    index = torch.zeros(B, max_events, dtype=torch.long, device=actions.device)
    present = torch.zeros(B, max_events, dtype=torch.bool, device=actions.device)
    rows, steps = keep.nonzero(as_tuple=True)
    index[rows, rank[rows, steps]] = steps
    present[rows, rank[rows, steps]] = True
    used = max(1, int(present.sum(dim=1).max()))  # no plan in the batch has more: the rest is padding
    return index[:, :used], present[:, :used]


class PlanEvents(nn.Module):
    """Raw plans ``(B, T, A)`` -> the plan's learned event vector ``(B, dim)`` (see the module docstring)."""

    def __init__(self, cfg: PlanEventsConfig, chain: KinematicChain, action_dim: int,
                 n_categories: int = N_CATEGORIES):
        super().__init__()
        self.cfg = cfg
        self.n_categories = n_categories
        self.n_joints = len(chain)
        self.n_gripper = action_dim - n_categories - self.n_joints  # the plan's columns after the joints
        if self.n_gripper < 0:
            raise ValueError(f"plans of width {action_dim} cannot hold {n_categories} categories and "
                             f"{self.n_joints} joints")
        self.fk = ChainFK(chain)
        H = cfg.hidden
        # position, rotation, category, time, run length, gripper
        self.token_dim = 3 + 6 + n_categories + 2 + self.n_gripper
        # offset, distance, relative rotation, category, time, gripper
        self.pair_dim = 3 + 1 + 6 + n_categories + 1 + self.n_gripper
        self.view = PlanView(cfg) if cfg.view else None
        view_dim = self.view.dim if self.view is not None else 0
        self.pair = mlp2(self.pair_dim, H, H)
        self.token = mlp2(self.token_dim + view_dim + 2 * H, H, H)
        self.dim = 2 * H
        self.register_buffer("token_mean", torch.zeros(self.token_dim))
        self.register_buffer("token_std", torch.ones(self.token_dim))
        self.register_buffer("pair_mean", torch.zeros(self.pair_dim))
        self.register_buffer("pair_std", torch.ones(self.pair_dim))

    def raw_features(self, actions: Tensor, mask: Tensor | None = None, hand: list | None = None
                     ) -> tuple[Tensor, Tensor, Tensor]:
        """Unstandardised token ``(B, E, Dt)`` and pair ``(B, E, E, Dp)`` features, and the events' presence
        ``(B, E)``; ``hand``, a list, receives the hand's poses at the events (for the view)."""
        C, J = self.n_categories, self.n_joints
        B, T, _ = actions.shape
        index, present = event_steps(actions, mask, self.cfg.max_events)  # (B, E)
        rows = torch.arange(B, device=actions.device).unsqueeze(-1)
        at = actions[rows, index]  # (B, E, A)
        pos, rot = self.fk(at[..., C:C + J])  # (B, E, 3), (B, E, 3, 3)
        if hand is not None:
            hand += [pos, rot]
        category = at[..., :C]
        gripper = at[..., C + J:]
        length = (mask.sum(dim=1) if mask is not None else torch.full((B,), T, device=actions.device)).to(actions.dtype)
        time = index.to(actions.dtype) / length.unsqueeze(-1)  # (B, E) in [0, 1)
        next_index = torch.cat([index[:, 1:], index.new_zeros(B, 1)], dim=1)
        next_index = torch.where(torch.cat([present[:, 1:], present.new_zeros(B, 1)], dim=1), next_index,
                                 length.long().unsqueeze(-1).expand_as(index))
        run = (next_index - index).to(actions.dtype) / length.unsqueeze(-1)
        tokens = torch.cat([pos, rotation_6d(rot), category, time.unsqueeze(-1), run.unsqueeze(-1), gripper], dim=-1)
        # every event j in event i's hand frame: R_i^T (p_j - p_i) and R_i^T R_j
        offset = torch.einsum("biyx,bijy->bijx", rot, pos.unsqueeze(1) - pos.unsqueeze(2))  # (B, E, E, 3)
        relative = torch.einsum("biyx,bjyz->bijxz", rot, rot)  # (B, E, E, 3, 3)
        E = index.shape[1]
        pairs = torch.cat([
            offset, offset.norm(dim=-1, keepdim=True), rotation_6d(relative),
            category.unsqueeze(1).expand(B, E, E, C), (time.unsqueeze(1) - time.unsqueeze(2)).unsqueeze(-1),
            gripper.unsqueeze(1).expand(B, E, E, gripper.shape[-1]),
        ], dim=-1)
        return tokens, pairs, present

    @torch.no_grad()
    def fit(self, actions: Tensor, mask: Tensor | None = None, batch_size: int = 512) -> None:
        """Per-feature statistics over the training plans' present events and event pairs."""
        t_sum = t_sq = p_sum = p_sq = None
        n_t = n_p = 0
        for start in range(0, actions.shape[0], batch_size):
            sl = slice(start, start + batch_size)
            tokens, pairs, present = self.raw_features(actions[sl].double(), None if mask is None else mask[sl])
            both = present.unsqueeze(1) & present.unsqueeze(2)
            t, p = tokens[present], pairs[both]
            t_sum = t.sum(0) if t_sum is None else t_sum + t.sum(0)
            t_sq = (t ** 2).sum(0) if t_sq is None else t_sq + (t ** 2).sum(0)
            p_sum = p.sum(0) if p_sum is None else p_sum + p.sum(0)
            p_sq = (p ** 2).sum(0) if p_sq is None else p_sq + (p ** 2).sum(0)
            n_t, n_p = n_t + t.shape[0], n_p + p.shape[0]
        for name, s, sq, n in (("token", t_sum, t_sq, n_t), ("pair", p_sum, p_sq, n_p)):
            mean = s / max(n, 1)
            std = (sq / max(n, 1) - mean ** 2).clamp(min=0).sqrt()
            std = torch.where(std < 1e-3, torch.ones_like(std), std)  # (nearly) constant in training: leave unscaled
            getattr(self, f"{name}_mean").copy_(mean.float())
            getattr(self, f"{name}_std").copy_(std.float())

    def forward(self, actions: Tensor, mask: Tensor | None = None, view: Tensor | None = None,
                projection: Tensor | None = None, augment: bool = False) -> Tensor:
        """Raw plans ``(B, T, A)`` -> the plan's vector ``(B, 2 H)``; with the view, also the initial images at
        the view's resolution ``(B, H', W', 3)`` uint8 and their base-frame projections ``(B, 3, 4)``."""
        if (self.view is not None) != (view is not None and projection is not None):
            raise ValueError("this model " + ("reads" if self.view is not None else "does not read")
                             + " the plan-conditioned view: pass view and projection accordingly")
        hand: list[Tensor] = []
        raw = self.raw_features(actions, mask, hand)
        return self.read(*raw, hand=hand, view=view, projection=projection, augment=augment)

    def reads_like(self, other: PlanEvents) -> bool:
        """Whether ``other`` computes the same :meth:`raw_features` (same chain, events and plan columns), so an
        ensemble computes them once for every member."""
        return (self.cfg.kinematics == other.cfg.kinematics and self.cfg.max_events == other.cfg.max_events
                and (self.n_categories, self.n_joints, self.n_gripper)
                == (other.n_categories, other.n_joints, other.n_gripper))

    def read(self, tokens: Tensor, pairs: Tensor, present: Tensor, hand: list | None = None,
             view: Tensor | None = None, projection: Tensor | None = None, augment: bool = False) -> Tensor:
        """:meth:`raw_features`' output -> the plan's vector ``(B, 2 H)``: this model's standardisation and
        networks (``hand`` as :meth:`raw_features` filled it, where the view is read)."""
        tokens = ((tokens - self.token_mean) / self.token_std).clamp(-STANDARD_CLIP, STANDARD_CLIP)
        pairs = ((pairs - self.pair_mean) / self.pair_std).clamp(-STANDARD_CLIP, STANDARD_CLIP)
        if self.view is not None:
            seen = self.view(view, projection, hand[0], hand[1], augment=augment)  # (B, E, Dv)
            tokens = torch.cat([tokens, seen * present.unsqueeze(-1)], dim=-1)
        both = (present.unsqueeze(1) & present.unsqueeze(2)).unsqueeze(-1)  # (B, E, E, 1)
        h = self.pair(pairs)  # (B, E, E, H)
        near_max = h.masked_fill(~both, float("-inf")).amax(dim=2).nan_to_num(0.0, neginf=0.0)  # (B, E, H)
        near_mean = (h * both).sum(dim=2) / both.sum(dim=2).clamp(min=1)
        z = self.token(torch.cat([tokens, near_max, near_mean], dim=-1))  # (B, E, H)
        keep = present.unsqueeze(-1)
        pooled_max = z.masked_fill(~keep, float("-inf")).amax(dim=1).nan_to_num(0.0, neginf=0.0)  # (B, H)
        pooled_mean = (z * keep).sum(dim=1) / keep.sum(dim=1).clamp(min=1)
        return torch.cat([pooled_max, pooled_mean], dim=-1)


def build_plan_events(cfg: PlanEventsConfig, action_dim: int) -> PlanEvents | None:
    """The event module a model owns when ``cfg.enabled`` (its chain from ``cfg.kinematics``), else None."""
    if not cfg.enabled:
        return None
    if cfg.kinematics is None:
        raise ValueError("events.kinematics: the plan's events need the arm's kinematics, which the dataset carries "
                         "(collect it again with this version, or give the chain in the recipe)")
    return PlanEvents(cfg, KinematicChain.from_dict(cfg.kinematics), action_dim)


def build_plan_reader(cfg: FIRPConfig) -> nn.Module | None:
    """What a model reads the plan's geometry with: the hand-built description (``cfg.geometry``), the learned
    events (``cfg.events``), or nothing (the paper's models)."""
    if cfg.geometry.enabled:
        return build_plan_geometry(cfg.geometry)
    return build_plan_events(cfg.events, cfg.action_dim)


def read_plan(reader: nn.Module | None, actions: Tensor, mask: Tensor | None = None) -> Tensor | None:
    """A success head's context from raw plans ``(B, T, A)``: the reader's vector ``(B, C)``, or None."""
    return reader(actions, mask) if reader is not None else None
