"""The plan contract: the one definition of what an action plan is, shared by every part.

A plan is ``T`` steps at ``FPS`` frames per second. Each step is 16 numbers: a one-hot row over the
seven action categories followed by nine joint targets for a Franka Panda (seven arm joints in
radians, two finger positions in metres). Every part of the product (sim worker, planner, datasets,
service) validates plans with :func:`validate_plan`, so there is exactly one copy of the category
list and of the joint limits. numpy only: no torch, no mujoco.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

CONTRACT_VERSION = "1.0"

FPS = 4
DEFAULT_T = 120
T_MIN = 8
T_MAX = 400

#: Action categories in the order of their one-hot columns.
CATEGORIES: tuple[str, ...] = (
    "move",
    "grasp",
    "release",
    "hold",
    "move_before_grasp",
    "hold_before_release",
    "move_after_release",
)
N_CATEGORIES = len(CATEGORIES)
CATEGORY_INDEX: dict[str, int] = {name: i for i, name in enumerate(CATEGORIES)}

#: The natural order of categories for one pick-and-place of one block.
PICK_PLACE_SEQUENCE: tuple[str, ...] = (
    "move_before_grasp",
    "grasp",
    "hold",
    "move",
    "hold_before_release",
    "release",
    "move_after_release",
)

JOINT_NAMES: tuple[str, ...] = (
    "joint1",
    "joint2",
    "joint3",
    "joint4",
    "joint5",
    "joint6",
    "joint7",
    "finger_joint1",
    "finger_joint2",
)
N_TARGETS = len(JOINT_NAMES)
PLAN_WIDTH = N_CATEGORIES + N_TARGETS  # 16

#: Franka Panda joint limits (radians for the arm, metres for the fingers), as in MuJoCo
#: Menagerie's ``franka_emika_panda`` model; a test checks them against the loaded model.
JOINT_LOWER = np.array(
    [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973, 0.0, 0.0]
)
JOINT_UPPER = np.array(
    [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973, 0.04, 0.04]
)
#: Slack allowed on the limits for floating-point round trips (JSON, float32).
LIMIT_TOLERANCE = 1e-4

FINGER_OPEN = 0.04
FINGER_CLOSED = 0.0


class PlanValidationError(ValueError):
    """A plan broke the contract. ``field`` names the offending part, ``rule`` the rule broken."""

    def __init__(self, field: str, rule: str, detail: str):
        self.field = field
        self.rule = rule
        self.detail = detail
        super().__init__(f"{field}: {detail} (rule: {rule})")


@dataclass(frozen=True)
class PlanLimits:
    """Bounds on the plan length accepted by a consumer (a model accepts what it was trained on)."""

    t_min: int = T_MIN
    t_max: int = T_MAX


def validate_plan(plan: object, limits: PlanLimits = PlanLimits(), field: str = "plan") -> np.ndarray:
    """Check ``plan`` against the contract and return it as a float64 ``(T, 16)`` array.

    Raises :class:`PlanValidationError` naming the field (``plan[t][c]`` where it helps) and the
    rule broken: shape/width, length range, finiteness, one-hot categories, joint limits.
    """
    try:
        raw = np.asarray(plan)
        # A plain float64 cast would turn "0.5" into 0.5 and drop imaginary parts with only a
        # warning: only real numbers (bool/int/float, or objects that are such) are a plan.
        if raw.dtype.kind not in "biuf" and not (
            raw.dtype.kind == "O" and all(isinstance(v, (numbers.Real, np.bool_)) for v in raw.flat)
        ):
            raise TypeError(f"got elements of dtype {raw.dtype}")
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PlanValidationError(field, "numeric", f"must be a numeric T x {PLAN_WIDTH} array ({exc})") from None
    if arr.ndim != 2:
        raise PlanValidationError(field, "shape", f"must be 2-D (T x {PLAN_WIDTH}), got {arr.ndim}-D")
    t, width = arr.shape
    if width != PLAN_WIDTH:
        raise PlanValidationError(
            field, "width", f"each step must have {PLAN_WIDTH} numbers "
            f"({N_CATEGORIES} one-hot categories + {N_TARGETS} joint targets), got {width}"
        )
    if not limits.t_min <= t <= limits.t_max:
        raise PlanValidationError(field, "length", f"T must be in [{limits.t_min}, {limits.t_max}], got {t}")
    bad = ~np.isfinite(arr)
    if bad.any():
        step, col = map(int, np.argwhere(bad)[0])
        raise PlanValidationError(f"{field}[{step}][{col}]", "finite", "NaN and infinity are not allowed")
    onehot = arr[:, :N_CATEGORIES]
    not_binary = ~np.isin(onehot, (0.0, 1.0))
    row_bad = not_binary.any(axis=1) | (onehot.sum(axis=1) != 1.0)
    if row_bad.any():
        step = int(np.flatnonzero(row_bad)[0])
        raise PlanValidationError(
            f"{field}[{step}]", "one_hot",
            f"the first {N_CATEGORIES} numbers must be one-hot (exactly one 1, the rest 0), got {onehot[step].tolist()}",
        )
    targets = arr[:, N_CATEGORIES:]
    low = targets < JOINT_LOWER - LIMIT_TOLERANCE
    high = targets > JOINT_UPPER + LIMIT_TOLERANCE
    out = low | high
    if out.any():
        step, j = map(int, np.argwhere(out)[0])
        raise PlanValidationError(
            f"{field}[{step}][{N_CATEGORIES + j}]", "joint_limits",
            f"{JOINT_NAMES[j]} target {targets[step, j]:.4f} is outside [{JOINT_LOWER[j]}, {JOINT_UPPER[j]}]",
        )
    return arr


def make_plan(categories: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Build a ``(T, 16)`` plan from category indices ``(T,)`` and joint targets ``(T, 9)``."""
    categories = np.asarray(categories, dtype=np.int64)
    targets = np.asarray(targets, dtype=np.float64)
    plan = np.zeros((len(categories), PLAN_WIDTH))
    plan[np.arange(len(categories)), categories] = 1.0
    plan[:, N_CATEGORIES:] = targets
    return plan


def split_plan(plan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`make_plan`: category indices ``(T,)`` and joint targets ``(T, 9)``."""
    plan = np.asarray(plan)
    return plan[:, :N_CATEGORIES].argmax(axis=1), plan[:, N_CATEGORIES:]
