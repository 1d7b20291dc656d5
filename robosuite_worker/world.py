"""The robosuite world behind the API every world serves: seeded episodes, plans under joint control.

* **Control.** robosuite's Panda with its arm's ``JOINT_POSITION`` part controller in absolute mode
  (``input_type="absolute"``: the action is the seven joint targets, neither scaled nor clipped) at
  robosuite's 20 Hz. A plan step lasts 1/4 s, so each is five control steps; during step ``t`` the
  targets move linearly from step ``t - 1``'s to step ``t``'s, as in our own world. The two finger
  targets (0 closed, 0.04 m open each) become robosuite's one gripper action by their mean: below half
  open is "close" (+1), else "open" (-1). robosuite's Panda gripper moves its fingers towards the
  commanded side at its own speed (a fifth of their range per control step), so a plan's grasp lasts
  as long as the plan keeps the fingers closing.
* **Episodes.** An episode is (task, seed, pose error): the environment's random generator and its
  object samplers are re-seeded and the environment reset, so the same seed gives the same scene in
  every process; the robot starts at robosuite's initial posture (``initialization_noise=None``)
  and holds it for a settling second while the objects, which robosuite's samplers place a little
  above their support, drop and come to rest: that is the episode's initial state, observed and
  imaged. Every execution resets to that state again. Perception reports each object's position and yaw
  with a seeded Gaussian error (in-plane std ``pose_error_mm``, height std at most 1 mm, yaw std
  ``pose_error_deg``); the image always shows the true scene.
* **Outcome.** After the plan the arm holds its last targets for a settling second; the label is the
  environment's own ``_check_success()`` -- robosuite's for its tasks, ours in its style for three
  cubes (:mod:`robosuite_worker.envs`) -- never a predicate of this module. ``sim_seconds`` is the
  episode's simulated time, both settling seconds included.
"""

from __future__ import annotations

import logging

import numpy as np

from firp.core.contract import FPS, N_CATEGORIES, validate_plan
from robosuite_worker.tasks import TASKS, body_pose, check_task
from world_api.backend import EpisodeStart, Outcome

__all__ = ["CONTROL_HZ", "OUTCOME_KINDS", "RobosuiteWorld", "gripper_action", "joint_position_config"]

CONTROL_HZ = 20
STEPS_PER_PLAN_STEP = CONTROL_HZ // FPS  # 5
SETTLE_SECONDS = 1.0
PERCEPTION_STREAM = 7  # separates the perception error's random stream from the scene's
FINGER_OPEN = 0.04
OUTCOME_KINDS = ("success", "not_done", "unstable")


def joint_position_config() -> dict:
    """robosuite's composite controller for the Panda with the arm under absolute joint-position control."""
    from robosuite.controllers import load_composite_controller_config, load_part_controller_config

    config = load_composite_controller_config(controller="BASIC", robot="Panda")
    arm = load_part_controller_config(default_controller="JOINT_POSITION")
    arm["input_type"] = "absolute"
    arm["gripper"] = config["body_parts"]["right"]["gripper"]
    config["body_parts"] = {"right": arm}  # the Panda has no torso, head, base or legs
    return config


def gripper_action(finger_targets: np.ndarray) -> float:
    """robosuite's gripper action for the plan's two finger targets: +1 close, -1 open."""
    return 1.0 if float(np.mean(finger_targets)) < FINGER_OPEN / 2 else -1.0


def _reseed(env, seed: int) -> None:
    """The environment's generator and every object sampler's, so that ``reset`` draws scene ``seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([seed]))
    env.rng = rng
    samplers = [env.placement_initializer]
    while samplers:
        sampler = samplers.pop()
        sampler.rng = rng
        samplers += list(getattr(sampler, "samplers", {}).values())


def _estimates(poses: dict[str, tuple[np.ndarray, float]], seed: int, mm: float, deg: float) -> dict:
    """Perception: each object's position and yaw with a seeded Gaussian error."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, PERCEPTION_STREAM]))
    out = {}
    for name, (pos, yaw) in poses.items():
        noise = rng.normal(0.0, 1.0, 4) * [mm / 1000, mm / 1000, min(mm, 1.0) / 1000, np.radians(deg)]
        out[name] = {"position": (pos + noise[:3]).tolist(), "yaw": float(yaw + noise[3])}
    return out


class UnknownCamera(ValueError):
    """The world's camera is not one of the task's (the message names the task's cameras)."""


class RobosuiteWorld:
    """robosuite environments, one per task, made lazily (on the runner's thread, which owns their GL context)."""

    name = "robosuite_worker"
    outcome_kinds = OUTCOME_KINDS

    def __init__(self, image_size: int = 84, camera: str = "agentview", settle_seconds: float = SETTLE_SECONDS,
                 tasks: tuple[str, ...] | None = None):
        self.image_size = image_size
        self.camera = camera
        self.tasks = tuple(check_task(task).name for task in tasks) if tasks else tuple(TASKS)  # the ones served
        self.settle_steps = int(round(settle_seconds * CONTROL_HZ))
        self._envs: dict[str, object] = {}

    def env(self, task: str):
        spec = check_task(task)
        if task not in self._envs:
            import robosuite

            import robosuite_worker.envs  # noqa: F401  (registers StackThree with robosuite)

            logging.getLogger("robosuite").setLevel(logging.ERROR)
            env = robosuite.make(
                spec.env, robots="Panda", controller_configs=joint_position_config(), has_renderer=False,
                has_offscreen_renderer=True, use_camera_obs=False, control_freq=CONTROL_HZ, hard_reset=False,
                ignore_done=True, horizon=10**9, initialization_noise=None, seed=0, **dict(spec.env_kwargs))
            cameras = env.sim.model.camera_names
            if self.camera not in cameras:
                _close_env(env)
                raise UnknownCamera(f"camera: {self.camera!r} is not a camera of the {task} task; one of "
                                 f"{', '.join(cameras)}")
            # Render without mirror reflections (the table's): 32 ms a frame instead of 71 under software GL
            # (measured at 84 px), and nothing the planner or the label depends on.
            env.sim.model.mat_reflectance[:] = 0.0
            self._envs[task] = env
        return self._envs[task]

    def warm_up(self) -> None:
        for task in self.tasks:
            env = self.env(task)
            env.reset()
            self.render(env)

    def render(self, env) -> np.ndarray:
        # One GL context per environment, and robosuite does not make an environment's current before it
        # renders: measured with three environments, the first one made rendered a stale frame.
        _make_own_context_current(env)
        image = env.sim.render(camera_name=self.camera, height=self.image_size, width=self.image_size)
        return np.ascontiguousarray(image[::-1])  # OpenGL's rows run bottom-up

    @staticmethod
    def joint_positions(env) -> np.ndarray:
        """The contract's nine joints: seven arm joints, then both fingers' openings (m, >= 0)."""
        robot = env.robots[0]
        qpos = env.sim.data.qpos
        fingers = np.abs(qpos[robot._ref_gripper_joint_pos_indexes["right"]])
        return np.concatenate([qpos[robot._ref_joint_pos_indexes], fingers]).astype(float)

    def _reset(self, task: str, seed: int):
        """Scene ``seed`` at rest: robosuite's samplers place objects a little above their support (1 cm for
        the cubes, 6 cm for the nut), so the arm holds its initial posture while they drop and settle."""
        env = self.env(task)
        _reseed(env, seed)
        env.reset()
        hold = np.concatenate([self.joint_positions(env)[:7], [gripper_action(np.full(2, FINGER_OPEN))]])
        for _ in range(self.settle_steps):
            env.step(hold)
        return env

    def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float) -> EpisodeStart:
        spec = check_task(task)
        env = self._reset(task, seed)
        poses = {name: body_pose(env, body) for name, body in spec.objects(env).items()}
        observation = {"blocks": _estimates(poses, seed, pose_error_mm, pose_error_deg), "scene": spec.scene(env)}
        return EpisodeStart(task, seed, observation, self.render(env), self.joint_positions(env), seed)

    def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool,
                shift: dict[str, tuple[float, float, float]] | None = None) -> Outcome:
        """Execute ``plan`` from the episode's initial state; ``shift`` (object name -> dx, dy in metres, dyaw in
        radians) first moves objects of the scene at rest -- what a scene a few millimetres away would be, for
        measuring how much of an outcome the initial state's last millimetres decide."""
        plan = validate_plan(plan)
        spec = check_task(start.task)
        env = self._reset(start.task, start.seed)
        if shift:
            _shift_objects(env, spec.objects(env), shift)
        targets = plan[:, N_CATEGORIES:]  # (T, 9)
        frames = np.empty((len(plan), self.image_size, self.image_size, 3), np.uint8) if record_frames else None
        states = np.zeros((len(plan), env.sim.model.nq + env.sim.model.nv)) if record_frames else None
        previous = self.joint_positions(env)
        unstable = False
        for t, target in enumerate(targets):
            if frames is not None:
                frames[t] = self.render(env)
                states[t] = np.concatenate([env.sim.data.qpos, env.sim.data.qvel])
            for k in range(1, STEPS_PER_PLAN_STEP + 1):
                q = previous + (k / STEPS_PER_PLAN_STEP) * (target - previous)
                env.step(np.concatenate([q[:7], [gripper_action(q[7:])]]))
            previous = target
            if not (np.isfinite(env.sim.data.qpos).all() and np.isfinite(env.sim.data.qvel).all()):
                unstable = True
                if frames is not None:
                    frames[t + 1:] = 0
                break
        if not unstable:
            hold = np.concatenate([previous[:7], [gripper_action(previous[7:])]])
            for _ in range(self.settle_steps):
                env.step(hold)
            unstable = not np.isfinite(env.sim.data.qpos).all()
        poses = {name: body_pose(env, body) for name, body in spec.objects(env).items()}
        final = {name: {"position": [float(v) if np.isfinite(v) else None for v in pos],
                        "yaw": yaw if np.isfinite(yaw) else None} for name, (pos, yaw) in poses.items()}
        if unstable:
            return Outcome(False, "unstable", "simulation became unstable", final, float(env.sim.data.time), True,
                           frames, np.nan_to_num(states) if states is not None else None)
        success = bool(env._check_success())
        reason = f"{spec.env}: success" if success else f"{spec.env}: not done ({spec.describe(env)})"
        return Outcome(success, "success" if success else "not_done", reason, final, float(env.sim.data.time), False,
                       frames, states)

    def close(self) -> None:
        """Free every environment. Close a world you are done with: one left to the garbage collector frees its
        render contexts in whatever GL context is current then (see :func:`_close_env`)."""
        for env in self._envs.values():
            _close_env(env)
        self._envs.clear()


def _close_env(env) -> None:
    """Close a robosuite environment without harming the others of the process.

    robosuite frees an environment's MuJoCo render context (its framebuffers, textures) in whichever GL context is
    current -- possibly another environment's, in this world or another one, whose objects have the same names --
    and that one then renders garbage (measured: every pixel of its next frame wrong). So the render context is
    freed in its own GL context first; robosuite's own free afterwards finds nothing left to free.
    """
    context = _make_own_context_current(env)
    if context is not None:
        context.con.free()
    env.close()


def _make_own_context_current(env):
    """Make the environment's own GL context the current one; returns its render context (None: none made yet)."""
    context = getattr(env.sim, "_render_context_offscreen", None)
    if context is not None:
        context.gl_ctx.make_current()
    return context


def _shift_objects(env, bodies: dict[str, int], shift: dict[str, tuple[float, float, float]]) -> None:
    """Move each named object's free joint in the plane and turn it about world z, at rest (velocities zero)."""
    model, data = env.sim.model, env.sim.data
    for name, (dx, dy, dyaw) in shift.items():
        if name not in bodies:
            raise ValueError(f"shift: {name!r} is not an object of this task; one of {sorted(bodies)}")
        joint = int(model.body_jntadr[bodies[name]])
        if joint < 0 or int(model.jnt_type[joint]) != 0:  # mjJNT_FREE
            raise ValueError(f"shift: {name!r} has no free joint to move")
        adr, vadr = int(model.jnt_qposadr[joint]), int(model.jnt_dofadr[joint])
        data.qpos[adr] += dx
        data.qpos[adr + 1] += dy
        w, x, y, z = data.qpos[adr + 3:adr + 7]
        c, s = np.cos(dyaw / 2.0), np.sin(dyaw / 2.0)  # (c, 0, 0, s) * q: a turn about world z
        data.qpos[adr + 3:adr + 7] = [c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w]
        data.qvel[vadr:vadr + 6] = 0.0
    env.sim.forward()
