"""The plan contract's validator: every rule it enforces, with the field and rule it reports.

Every part of the product relies on these error fields to tell a caller what is wrong with a plan,
so the table below pins the exact ``field`` and ``rule`` for each kind of bad plan.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from firp.core.contract import (
    CATEGORIES,
    CATEGORY_INDEX,
    DEFAULT_T,
    JOINT_LOWER,
    JOINT_NAMES,
    JOINT_UPPER,
    LIMIT_TOLERANCE,
    N_CATEGORIES,
    PICK_PLACE_SEQUENCE,
    PLAN_WIDTH,
    T_MAX,
    T_MIN,
    PlanLimits,
    PlanValidationError,
    make_plan,
    split_plan,
    validate_plan,
)

MID = (JOINT_LOWER + JOINT_UPPER) / 2


def good_plan(t: int = 12) -> np.ndarray:
    """A valid plan cycling through the pick-and-place categories at mid-range joint targets."""
    cats = np.array([CATEGORY_INDEX[PICK_PLACE_SEQUENCE[i % len(PICK_PLACE_SEQUENCE)]] for i in range(t)])
    return make_plan(cats, np.tile(MID, (t, 1)))


def _set(t: int, c: int, value: float) -> Callable[[np.ndarray], np.ndarray]:
    def edit(p: np.ndarray) -> np.ndarray:
        p = p.copy()
        p[t, c] = value
        return p

    return edit


def _row(t: int, row: list[float]) -> Callable[[np.ndarray], np.ndarray]:
    def edit(p: np.ndarray) -> np.ndarray:
        p = p.copy()
        p[t, :N_CATEGORIES] = row
        return p

    return edit


BAD_PLANS: list[tuple[str, Callable[[np.ndarray], object], str, str]] = [
    ("width_15", lambda p: p[:, :15], "plan", "width"),
    ("width_17", lambda p: np.hstack([p, np.zeros((len(p), 1))]), "plan", "width"),
    ("one_d", lambda p: p[0], "plan", "shape"),
    ("three_d", lambda p: p[None], "plan", "shape"),
    ("too_short", lambda p: good_plan(T_MIN - 1), "plan", "length"),
    ("too_long", lambda p: good_plan(T_MAX + 1), "plan", "length"),
    ("empty", lambda p: np.zeros((0, PLAN_WIDTH)), "plan", "length"),
    ("ragged", lambda p: [list(r) for r in p[:-1]] + [list(p[-1][:-1])], "plan", "numeric"),
    ("strings", lambda p: p.astype(str), "plan", "numeric"),
    ("complex", lambda p: p + 0j, "plan", "numeric"),
    ("nan_target", _set(3, 9, np.nan), "plan[3][9]", "finite"),
    ("inf_category", _set(5, 0, np.inf), "plan[5][0]", "finite"),
    ("neg_inf_finger", _set(0, 15, -np.inf), "plan[0][15]", "finite"),
    ("two_ones", _row(2, [1, 1, 0, 0, 0, 0, 0]), "plan[2]", "one_hot"),
    ("half", _row(4, [0.5, 0, 0, 0, 0, 0.5, 0]), "plan[4]", "one_hot"),
    ("all_zero", _row(1, [0] * 7), "plan[1]", "one_hot"),
    ("negative_one", _row(6, [1, -1, 1, 0, 0, 0, 0]), "plan[6]", "one_hot"),
]
# Each joint, both sides, just past the tolerance: the limits are per joint, fingers included.
for _j, _name in enumerate(JOINT_NAMES):
    _c = N_CATEGORIES + _j
    BAD_PLANS.append((f"{_name}_low", _set(7, _c, JOINT_LOWER[_j] - 2 * LIMIT_TOLERANCE), f"plan[7][{_c}]", "joint_limits"))
    BAD_PLANS.append((f"{_name}_high", _set(7, _c, JOINT_UPPER[_j] + 2 * LIMIT_TOLERANCE), f"plan[7][{_c}]", "joint_limits"))


@pytest.mark.parametrize(("edit", "field", "rule"), [b[1:] for b in BAD_PLANS], ids=[b[0] for b in BAD_PLANS])
def test_bad_plan_names_field_and_rule(edit: Callable[[np.ndarray], object], field: str, rule: str) -> None:
    with pytest.raises(PlanValidationError) as info:
        validate_plan(edit(good_plan()))
    assert (info.value.field, info.value.rule) == (field, rule)
    assert rule in str(info.value) and field in str(info.value)


def test_error_uses_callers_field_name() -> None:
    with pytest.raises(PlanValidationError) as info:
        validate_plan(_set(0, 8, np.nan)(good_plan()), field="actions")
    assert info.value.field == "actions[0][8]"


def test_error_is_a_value_error() -> None:
    """Callers that only know ValueError (argparse, pydantic validators) still catch it."""
    with pytest.raises(ValueError):
        validate_plan(np.zeros((3, 3)))


@pytest.mark.parametrize("t", [T_MIN, DEFAULT_T, T_MAX])
def test_good_plan_passes_and_comes_back_float64(t: int) -> None:
    plan = good_plan(t)
    out = validate_plan(plan.tolist())
    assert out.dtype == np.float64 and out.shape == (t, PLAN_WIDTH)
    np.testing.assert_array_equal(out, plan)


def test_limits_are_inclusive_with_tolerance() -> None:
    """Exact limits and float32 round-off at the limits must pass (plans travel as JSON/float32)."""
    t = 10
    cats = np.zeros(t, dtype=int)
    at_low = make_plan(cats, np.tile(JOINT_LOWER - LIMIT_TOLERANCE / 2, (t, 1)))
    at_high = make_plan(cats, np.tile(JOINT_UPPER, (t, 1))).astype(np.float32)
    validate_plan(at_low)
    validate_plan(at_high)


def test_custom_length_limits() -> None:
    limits = PlanLimits(t_min=20, t_max=30)
    validate_plan(good_plan(25), limits)
    with pytest.raises(PlanValidationError) as info:
        validate_plan(good_plan(12), limits)
    assert info.value.rule == "length" and "[20, 30]" in str(info.value)


def test_make_split_round_trip() -> None:
    rng = np.random.default_rng(0)
    t = 50
    cats = rng.integers(0, N_CATEGORIES, size=t)
    targets = rng.uniform(JOINT_LOWER, JOINT_UPPER, size=(t, len(JOINT_NAMES)))
    plan = make_plan(cats, targets)
    assert plan.shape == (t, PLAN_WIDTH)
    np.testing.assert_array_equal(plan[:, :N_CATEGORIES].sum(axis=1), np.ones(t))
    validate_plan(plan)
    cats_back, targets_back = split_plan(plan)
    np.testing.assert_array_equal(cats_back, cats)
    np.testing.assert_array_equal(targets_back, targets)


def test_category_tables_agree() -> None:
    assert len(CATEGORIES) == N_CATEGORIES == 7
    assert PLAN_WIDTH == 16
    assert set(PICK_PLACE_SEQUENCE) == set(CATEGORIES)
    assert all(CATEGORIES[i] == name for name, i in CATEGORY_INDEX.items())
    assert np.all(JOINT_LOWER < JOINT_UPPER)
