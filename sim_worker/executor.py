"""Execute a plan in the world: track its joint targets, record one frame per step, judge success.

Timing contract: ``frames[t]`` is the camera image *before* step ``t`` is executed (so
``frames[0]`` is the initial image I_1), and during step ``t`` the position targets move linearly
from step ``t-1``'s targets (the home posture for ``t = 0``) to step ``t``'s over ``1/FPS`` seconds,
updated at the controller rate. After the last step the arm holds its last targets for a settling
period, then the task's success predicate is evaluated on the physics state.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from firp.core.contract import FPS, N_CATEGORIES, PlanLimits, validate_plan
from sim_worker.tasks import Verdict, judge
from sim_worker.world import World


@dataclass(frozen=True)
class ExecutorConfig:
    control_hz: float = 100.0  # how often the interpolated targets reach the actuators
    settle_seconds: float = 1.5  # holding the last targets before judging
    record_frames: bool = True


@dataclass
class ExecutionResult:
    success: bool
    reason: str  # for people: names blocks and numbers
    frames: np.ndarray | None  # (T, H, W, 3) uint8, frames[t] before step t
    states: np.ndarray  # (T, S) physics state before step t
    final_block_poses: np.ndarray  # (n_blocks, 4)
    sim_seconds: float
    unstable: bool = False
    warnings: dict = field(default_factory=dict)
    kind: str = "success"  # sim_worker.tasks.OUTCOME_KINDS: what tests and reports compare


def _physics_unstable(world: World) -> bool:
    d = world.data
    bad_warnings = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQPOS)
    return any(d.warning[w].number > 0 for w in bad_warnings) or not np.isfinite(d.qpos).all()


def control_schedule(timestep: float, control_hz: float) -> tuple[int, int]:
    """Physics steps per control update and control updates per plan step, both exact integers.

    A plan step must last exactly ``1/FPS`` simulated seconds; a timestep or controller rate that
    does not divide it would silently run plans faster or slower than planned.
    """
    per_control = 1.0 / (control_hz * timestep)
    per_step = control_hz / FPS
    if abs(per_control - round(per_control)) > 1e-6 or abs(per_step - round(per_step)) > 1e-6 or per_control < 1:
        raise ValueError(f"timestep {timestep} s and control rate {control_hz} Hz must divide the "
                         f"{1 / FPS} s plan step into whole physics steps and control updates")
    return int(round(per_control)), int(round(per_step))


def execute_plan(world: World, task: str, initial_blocks: np.ndarray, plan: np.ndarray,
                 config: ExecutorConfig = ExecutorConfig()) -> ExecutionResult:
    """Reset ``world`` to ``initial_blocks`` and run ``plan`` (validated against the contract)."""
    plan = validate_plan(plan, PlanLimits())
    model, data, panda = world.model, world.data, world.panda
    world.reset(initial_blocks)
    targets = plan[:, N_CATEGORIES:]  # (T, 9)
    steps_per_control, controls_per_step = control_schedule(model.opt.timestep, config.control_hz)
    t_count = len(plan)
    frames = None
    if config.record_frames:
        h, w = world.render_config.height, world.render_config.width
        frames = np.empty((t_count, h, w, 3), dtype=np.uint8)
    states = np.empty((t_count, world.state_size))

    previous = world.joint_positions()
    unstable = False
    for t in range(t_count):
        states[t] = world.get_state()
        if frames is not None:
            frames[t] = world.render()
        for k in range(1, controls_per_step + 1):
            alpha = k / controls_per_step
            data.ctrl[:] = panda.ctrl_for(previous + alpha * (targets[t] - previous))
            mujoco.mj_step(model, data, nstep=steps_per_control)
        previous = targets[t]
        if _physics_unstable(world):
            unstable = True
            break
    if not unstable:
        data.ctrl[:] = panda.ctrl_for(previous)
        mujoco.mj_step(model, data, nstep=max(1, round(config.settle_seconds / model.opt.timestep)))
        unstable = _physics_unstable(world)
    if unstable:
        if frames is not None:
            frames[t + 1:] = 0
        states[t + 1:] = np.nan
        verdict = Verdict(False, "simulation became unstable", "unstable")
    else:
        verdict = judge(task, world.block_states(), world.layout)
    return ExecutionResult(
        success=verdict.success, reason=verdict.reason, frames=frames, states=states,
        final_block_poses=world.block_poses(), sim_seconds=float(data.time), unstable=unstable,
        warnings={int(w): int(data.warning[w].number) for w in range(len(data.warning)) if data.warning[w].number},
        kind=verdict.kind,
    )
