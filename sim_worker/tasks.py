"""The two tasks: seeded initial-state samplers and success predicates on the final physics state.

A block pose is ``(x, y, z, yaw)``: blocks always start resting flat, so four numbers describe them.
Success is judged only from the physics state after the plan and a settling period, never from the
plan, so every failure is one the physics produced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_worker.scene import BLOCK_NAMES, SceneLayout

TASK_NAMES: tuple[str, ...] = ("stacking", "replacement")


@dataclass(frozen=True)
class BlockState:
    """Final pose and motion of one block, read from the physics state."""

    pos: np.ndarray  # (3,)
    up_tilt_deg: float  # angle between the block's local z (or any face normal) and world z
    speed: float  # linear speed, m/s


#: Kinds of outcome, one per check of the success predicates (and the executor's "unstable"). The
#: reason text names blocks and numbers; the kind is what tests and reports compare, since which of
#: two tied blocks a reason names, or its last digit, may differ between machines.
OUTCOME_KINDS: dict[str, str] = {
    "success": "",
    "not_at_rest": "not at rest",
    "wrong_height": "at height",
    "tilted": "tilted",
    "off_block_below": "off the block below",
    "not_inside": "not inside",
    "unstable": "simulation became unstable",
}


@dataclass(frozen=True)
class Verdict:
    """A success label with its kind and the reason, so failed episodes can be explained and tested."""

    success: bool
    reason: str
    kind: str = "success"

    def __post_init__(self) -> None:
        if self.kind not in OUTCOME_KINDS:
            raise ValueError(f"kind: {self.kind!r} is none of {list(OUTCOME_KINDS)}")
        if self.success != (self.kind == "success"):
            raise ValueError(f"kind: {self.kind!r} contradicts success={self.success}")


def reason_kind(success: bool, reason: str) -> str:
    """The outcome kind of a recorded ``(success, reason)`` pair (records written before kinds existed)."""
    if success:
        return "success"
    for kind, marker in OUTCOME_KINDS.items():
        if marker and marker in reason:
            return kind
    raise ValueError(f"reason: {reason!r} matches no outcome kind of {list(OUTCOME_KINDS)}")


@dataclass(frozen=True)
class SamplerConfig:
    """How initial block poses are drawn. The area sizes set how often the planner's conditions fail."""

    stack_half_extent: float = 0.04  # blocks uniform in a square of this half size
    stack_min_gap: float = 0.015  # face to face between blocks on the table
    box_min_gap: float = 0.006  # face to face between blocks packed in box A
    box_wall_clearance: float = 0.066  # block centre to the box's inner walls at the start
    max_tries: int = 10_000


@dataclass(frozen=True)
class SuccessConfig:
    """Tolerances of the success predicates."""

    rest_speed: float = 0.02  # m/s: every block must be (nearly) at rest
    max_tilt_deg: float = 10.0
    stack_xy_tolerance: float = 0.015  # between consecutive blocks of the tower
    stack_z_tolerance: float = 0.008
    #: blocks whose heights differ by less than this are the same level for ordering the tower (by block
    #: index), so two blocks lying on the table are not told apart by the last bits of the physics
    height_tie: float = 0.002


def square_gap(p1: np.ndarray, yaw1: float, p2: np.ndarray, yaw2: float, half: float) -> float:
    """Largest separation between two squares (centres, yaws, half size) over their edge normals.

    Separating-axis test in the plane: negative means they overlap. For squares the four edge
    normals are the only candidate axes, so this is exact.
    """
    d = np.asarray(p2, dtype=float) - np.asarray(p1, dtype=float)
    best = -np.inf
    for theta in (yaw1, yaw1 + np.pi / 2, yaw2, yaw2 + np.pi / 2):
        u = np.array([np.cos(theta), np.sin(theta)])
        r1 = half * (abs(np.cos(yaw1 - theta)) + abs(np.sin(yaw1 - theta)))
        r2 = half * (abs(np.cos(yaw2 - theta)) + abs(np.sin(yaw2 - theta)))
        best = max(best, abs(float(d @ u)) - r1 - r2)
    return best


def _sample_separated(rng: np.random.Generator, low: np.ndarray, high: np.ndarray, n: int,
                      half: float, min_gap: float, max_tries: int) -> np.ndarray:
    """Rejection-sample ``n`` block poses (x, y, yaw) uniformly in a rectangle with random yaw,
    every pair at least ``min_gap`` apart face to face."""
    for _ in range(max_tries):
        xy = rng.uniform(low, high, size=(n, 2))
        yaw = rng.uniform(-np.pi / 4, np.pi / 4, size=n)
        if all(square_gap(xy[i], yaw[i], xy[j], yaw[j], half) >= min_gap
               for i in range(n) for j in range(i + 1, n)):
            return np.column_stack([xy, yaw])
    raise RuntimeError("could not place the blocks apart; the sampling area is too small")


def sample_initial_blocks(task: str, seed: int, layout: SceneLayout = SceneLayout(),
                          config: SamplerConfig = SamplerConfig()) -> np.ndarray:
    """Block poses ``(3, 4)`` = (x, y, z, yaw) for ``task`` and ``seed``, in BLOCK_NAMES order."""
    check_task(task)
    rng = np.random.default_rng(np.random.SeedSequence([seed, TASK_NAMES.index(task)]))
    h = layout.block_half
    n = len(BLOCK_NAMES)
    if task == "stacking":
        c = np.asarray(layout.stack_area_centre)
        e = config.stack_half_extent
        xy_yaw = _sample_separated(rng, c - e, c + e, n, h, config.stack_min_gap, config.max_tries)
        z = np.full(n, h)
    else:
        box = layout.box("box_a")
        room = np.asarray(box.inner_half) - config.box_wall_clearance
        c = np.asarray(box.centre)
        xy_yaw = _sample_separated(rng, c - room, c + room, n, h, config.box_min_gap, config.max_tries)
        z = np.full(n, box.floor_top + h)
    return np.column_stack([xy_yaw[:, :2], z, xy_yaw[:, 2]])


def check_task(task: str) -> None:
    if task not in TASK_NAMES:
        raise ValueError(f"task: unknown task {task!r}; expected one of {list(TASK_NAMES)}")


def tower_order(heights: list[float], tie: float) -> list[int]:
    """Block indices from the lowest to the highest; heights within ``tie`` of the lowest block of
    their group count as one level and keep index order, so the result does not depend on sub-mm noise."""
    by_height = sorted(range(len(heights)), key=lambda i: (heights[i], i))
    groups: list[list[int]] = []
    for i in by_height:
        if groups and heights[i] - heights[groups[-1][0]] < tie:
            groups[-1].append(i)
        else:
            groups.append([i])
    return [i for group in groups for i in sorted(group)]


def judge(task: str, blocks: list[BlockState], layout: SceneLayout = SceneLayout(),
          config: SuccessConfig = SuccessConfig()) -> Verdict:
    """Success predicate of ``task`` on the final block states (in BLOCK_NAMES order)."""
    check_task(task)
    moving = [BLOCK_NAMES[i] for i, b in enumerate(blocks) if b.speed > config.rest_speed]
    if moving:
        return Verdict(False, f"not at rest: {', '.join(moving)}", "not_at_rest")
    h = layout.block_half
    if task == "stacking":
        order = tower_order([float(b.pos[2]) for b in blocks], config.height_tie)
        tower = [blocks[i] for i in order]
        for level, (i, b) in enumerate(zip(order, tower)):
            expected_z = h + 2 * h * level
            if abs(b.pos[2] - expected_z) > config.stack_z_tolerance:
                return Verdict(False, f"{BLOCK_NAMES[i]} at height {b.pos[2]:.3f}, expected {expected_z:.3f} "
                                      f"for level {level} of a tower", "wrong_height")
            if b.up_tilt_deg > config.max_tilt_deg:
                return Verdict(False, f"{BLOCK_NAMES[i]} tilted {b.up_tilt_deg:.1f} deg", "tilted")
            if level and np.linalg.norm(b.pos[:2] - tower[level - 1].pos[:2]) > config.stack_xy_tolerance:
                return Verdict(False, f"{BLOCK_NAMES[i]} off the block below by "
                                      f"{100 * np.linalg.norm(b.pos[:2] - tower[level - 1].pos[:2]):.1f} cm",
                               "off_block_below")
        return Verdict(True, "tower of three")
    box = layout.box("box_b")
    c = np.asarray(box.centre)
    for i, b in enumerate(blocks):
        inside = np.all(np.abs(b.pos[:2] - c) <= np.asarray(box.inner_half))
        if not inside or b.pos[2] > box.rim_height:
            return Verdict(False, f"{BLOCK_NAMES[i]} not inside {box.name}", "not_inside")
    return Verdict(True, "all blocks in box_b")
