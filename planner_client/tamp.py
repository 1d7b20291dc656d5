"""A TAMP-style planner for the two tasks: symbolic pick-and-place steps, then motion by IK.

Given the estimated object poses (what perception reports), a block order and an optional planner
seed, it writes the contract's T x 16 plan: per block the seven categories in their natural order
(move-before-grasp, grasp, hold, move, hold-before-release, release, move-after-release), joint
targets from IK on the real Panda model, time-resampled to exactly T steps.

Its conditions are those a sensible first version has and no more: a clearance height for
transport, a top-down approach aligned with the block's faces, place targets computed from the
estimated poses, a small release gap. It does not check for neighbouring blocks in the fingers'
path, box walls, grasp offsets or tower alignment: those are the failures the product must learn.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import permutations

import numpy as np

from firp.core.contract import CATEGORY_INDEX, DEFAULT_T, FINGER_CLOSED, FINGER_OPEN, FPS, make_plan
from planner_client.ik import ArmIK, IKConfig, PandaIK, rotation_yaw
from sim_worker.robot import HOME_ARM_QPOS

BLOCK_NAMES_DEFAULT = ("red", "green", "blue")
QUARTER = np.pi / 2


@dataclass(frozen=True)
class PickPlaceTiming:
    """How long each phase of a pick-and-place lasts (nominal seconds, before the plan is resampled to T)."""

    speed: float = 0.25  # m/s for transport segments
    min_transport_s: float = 1.0
    descend_s: float = 1.25
    grasp_s: float = 1.0
    lift_s: float = 1.0
    lower_s: float = 1.25
    release_s: float = 0.75
    retreat_s: float = 0.75


@dataclass(frozen=True)
class PlannerConfig:
    """The planner's hand-written conditions and timing."""

    horizon: int = DEFAULT_T
    clearance_z: float = 0.17  # TCP height for transport
    grasp_z_offset: float = 0.0  # TCP height relative to the block centre when grasping
    release_gap: float = 0.005  # the block is released this far above its resting height
    timing: PickPlaceTiming = field(default_factory=PickPlaceTiming)
    replacement_slots: tuple[tuple[float, float], ...] = ((-0.045, -0.035), (0.045, -0.035), (0.0, 0.045))
    ik: IKConfig = field(default_factory=IKConfig)


@dataclass(frozen=True)
class Segment:
    """A straight-line TCP motion ending at ``pos``/``yaw`` with the fingers at ``finger``."""

    category: str
    duration: float
    pos: np.ndarray
    yaw: float
    finger: float


@dataclass
class Plan:
    """A plan with what produced it, so datasets and reports can say why it looks as it does."""

    actions: np.ndarray  # (T, 16)
    order: tuple[str, ...]
    grasp_yaws: list[float]
    place_targets: list[list[float]]
    segments: list[Segment] = field(repr=False, default_factory=list)


def wrap_angle(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def wrap_half_turn(a: float) -> float:
    """A gripper yaw is the same grasp after half a turn: map to [-pi/2, pi/2)."""
    return float((a + np.pi / 2) % np.pi - np.pi / 2)


def nearest_equivalent(yaw: float, reference: float, period: float = QUARTER) -> float:
    """The angle ``yaw + k * period`` closest to ``reference``."""
    return float(yaw + period * np.round((reference - yaw) / period))


def block_orders(names: tuple[str, ...] = BLOCK_NAMES_DEFAULT) -> list[tuple[str, ...]]:
    """All block orders, the default (name order) first: the replanning loop walks this list."""
    return list(permutations(names))


def pick_and_place(cfg: PickPlaceTiming, start: np.ndarray, pick: tuple[np.ndarray, np.ndarray, float],
                   place: tuple[np.ndarray, np.ndarray, float]) -> list[Segment]:
    """The eight TCP segments of one pick-and-place, the seven categories in their natural order.

    ``pick`` and ``place`` are (above point, point, yaw): the hand goes from ``start`` above the object,
    descends open, closes, lifts, carries it above the place, lowers, opens and rises."""
    def transport(a: np.ndarray, b: np.ndarray) -> float:
        return max(cfg.min_transport_s, float(np.linalg.norm(b - a)) / cfg.speed)

    (above_grasp, grasp, grasp_yaw), (above_release, release, release_yaw) = pick, place
    steps = [("move_before_grasp", transport(start, above_grasp), above_grasp, grasp_yaw, FINGER_OPEN),
             ("move_before_grasp", cfg.descend_s, grasp, grasp_yaw, FINGER_OPEN),
             ("grasp", cfg.grasp_s, grasp, grasp_yaw, FINGER_CLOSED),
             ("hold", cfg.lift_s, above_grasp, grasp_yaw, FINGER_CLOSED),
             ("move", transport(above_grasp, above_release), above_release, release_yaw, FINGER_CLOSED),
             ("hold_before_release", cfg.lower_s, release, release_yaw, FINGER_CLOSED),
             ("release", cfg.release_s, release, release_yaw, FINGER_OPEN),
             ("move_after_release", cfg.retreat_s, above_release, release_yaw, FINGER_OPEN)]
    return [Segment(category, duration, np.asarray(pos, dtype=float), yaw, finger)
            for category, duration, pos, yaw, finger in steps]


def trajectory(segments: list[Segment], start_pos: np.ndarray, start_yaw: float, horizon: int, ik: ArmIK,
               q_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plan's ``horizon`` steps along ``segments``: category indices ``(T,)`` and joint targets ``(T, 9)``.

    All segments are scaled uniformly so that the plan spans exactly T steps at 4 FPS; within a segment
    the TCP position, yaw and finger opening move linearly from the previous segment's end, and IK
    (warm-started from the previous step) gives each step's arm joints.
    """
    durations = np.array([seg.duration for seg in segments])
    ends = np.cumsum(durations) * (horizon / FPS) / durations.sum()
    starts = np.concatenate([[0.0], ends[:-1]])
    categories = np.empty(horizon, dtype=np.int64)
    targets = np.empty((horizon, 9))
    seg_start_state = [(start_pos, start_yaw, FINGER_OPEN)] + [(seg.pos, seg.yaw, seg.finger) for seg in segments[:-1]]
    q = q_start
    for t in range(horizon):
        time = (t + 1) / FPS  # the target is reached at the end of step t
        i = min(int(np.searchsorted(ends, time - 1e-9)), len(segments) - 1)
        seg = segments[i]
        a = np.clip((time - starts[i]) / (ends[i] - starts[i]), 0.0, 1.0)
        p0, y0, f0 = seg_start_state[i]
        q = ik.solve(p0 + a * (seg.pos - p0), y0 + a * (seg.yaw - y0), q)
        categories[t] = CATEGORY_INDEX[seg.category]
        targets[t, :7] = q
        targets[t, 7:] = f0 + a * (seg.finger - f0)
    return categories, targets


class TampPlanner:
    """Plans pick-and-place sequences for ``stacking`` and ``replacement`` from an observation."""

    def __init__(self, config: PlannerConfig = PlannerConfig()):
        self.config = config
        self.ik = PandaIK(config.ik)

    # -- what the trial loop replans over (planner_client.loop.Planner) ---------------------------
    def candidates(self, task: str, observation: dict) -> list[tuple[str, ...]]:
        """The block orders the loop tries, the default first (the same for every scene)."""
        return block_orders()

    def horizon(self, task: str) -> int:
        return self.config.horizon

    @staticmethod
    def describe(order: tuple[str, ...]) -> list[str]:
        return list(order)

    # -- symbolic level: which block goes where ------------------------------------------------
    def _place_targets(self, task: str, observation: dict, order: tuple[str, ...]) -> list[tuple[np.ndarray, float]]:
        """Resting pose (TCP position at the block centre, block yaw) for each block in ``order``."""
        scene = observation["scene"]
        h = scene["block_half"]
        blocks = observation["blocks"]
        targets = []
        if task == "stacking":
            base = np.asarray(blocks[order[0]]["position"], dtype=float)
            base_yaw = float(blocks[order[0]]["yaw"])
            for level in range(1, len(order)):
                targets.append((base + np.array([0.0, 0.0, 2 * h * level]), base_yaw))
        elif task == "replacement":
            box = scene["boxes"]["box_b"]
            centre = np.asarray(box["centre"], dtype=float)
            for i in range(len(order)):
                dx, dy = self.config.replacement_slots[i]
                targets.append((np.array([centre[0] + dx, centre[1] + dy, box["floor_top"] + h]), 0.0))
        else:
            raise ValueError(f"task: unknown task {task!r}")
        return targets

    def _moved_blocks(self, task: str, order: tuple[str, ...]) -> tuple[str, ...]:
        return order[1:] if task == "stacking" else order

    # -- geometric level: the TCP path -----------------------------------------------------------
    def _segments(self, task: str, observation: dict, order: tuple[str, ...], rng: np.random.Generator | None,
                  start_pos: np.ndarray) -> tuple[list[Segment], list[float], list[list[float]]]:
        cfg = self.config
        blocks = observation["blocks"]
        segments: list[Segment] = []
        pos = start_pos
        grasp_yaws, place_list = [], []

        for name, (place_pos, place_block_yaw) in zip(self._moved_blocks(task, order),
                                                     self._place_targets(task, observation, order)):
            block_pos = np.asarray(blocks[name]["position"], dtype=float)
            block_yaw = float(blocks[name]["yaw"])
            # top-down grasp across a pair of faces: two finger axes; default = least wrist rotation
            options = sorted((wrap_half_turn(block_yaw + k * QUARTER) for k in (0, 1)), key=abs)
            grasp_yaw = options[0] if rng is None else options[int(rng.integers(len(options)))]
            grasp_pos = block_pos + np.array([0.0, 0.0, cfg.grasp_z_offset])
            above_block = np.array([grasp_pos[0], grasp_pos[1], cfg.clearance_z])
            # the block keeps its yaw relative to the fingers; any face may point anywhere (cube)
            place_yaw = nearest_equivalent(place_block_yaw, grasp_yaw)
            release_pos = place_pos + np.array([0.0, 0.0, cfg.release_gap + cfg.grasp_z_offset])
            above_place = np.array([release_pos[0], release_pos[1], cfg.clearance_z])
            segments += pick_and_place(cfg.timing, pos, (above_block, grasp_pos, grasp_yaw),
                                       (above_place, release_pos, place_yaw))
            pos = above_place
            grasp_yaws.append(grasp_yaw)
            place_list.append([*release_pos.tolist(), place_yaw])
        return segments, grasp_yaws, place_list

    # -- resampling and IK ---------------------------------------------------------------------------
    def plan(self, task: str, observation: dict, order: tuple[str, ...] | None = None,
             planner_seed: int | None = None) -> Plan:
        """The T-step plan for ``task`` from ``observation`` with blocks handled in ``order``."""
        cfg = self.config
        names = tuple(observation["blocks"].keys())
        order = tuple(order) if order is not None else names
        if sorted(order) != sorted(names):
            raise ValueError(f"order: must be a permutation of {list(names)}, got {list(order)}")
        rng = None if planner_seed is None else np.random.default_rng(planner_seed)
        q = HOME_ARM_QPOS.copy()
        start_pos, start_rot = self.ik.forward(q)
        segments, grasp_yaws, places = self._segments(task, observation, order, rng, start_pos)

        categories, targets = trajectory(segments, start_pos, rotation_yaw(start_rot), cfg.horizon, self.ik, q)
        return Plan(make_plan(categories, targets), order, grasp_yaws, places, segments)
