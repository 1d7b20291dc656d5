"""Inverse kinematics for top-down gripper poses: damped least squares on ``mj_jacSite``.

Top-down grasps need nothing more elaborate: the solver is warm-started from the previous step
of the trajectory, so consecutive solutions stay on one branch, and a null-space pull towards
the home posture keeps the elbow up. :class:`ArmIK` solves any seven-joint arm a world describes
(:class:`ArmModel`: its MuJoCo model, the site IK targets, which axis of that site the fingers close
along); :class:`PandaIK` is it on our world's Panda.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from firp.core.contract import JOINT_LOWER, JOINT_UPPER


@dataclass(frozen=True)
class IKConfig:
    max_iterations: int = 200
    position_tolerance: float = 5e-4  # metres
    rotation_tolerance: float = 2e-3  # radians
    damping: float = 1e-4
    posture_gain: float = 0.05
    max_step: float = 0.2  # radians per iteration, for stability far from the solution


class IKFailure(RuntimeError):
    """The target pose could not be reached within tolerance (out of reach or at a limit)."""


def top_down_rotation(yaw: float, finger_axis: int = 1) -> np.ndarray:
    """TCP frame with z pointing down and the finger axis (column ``finger_axis``: 1 = y, 0 = x) at ``yaw``
    in the table plane."""
    c, s = np.cos(yaw), np.sin(yaw)
    if finger_axis == 1:
        return np.column_stack([[-s, c, 0.0], [c, s, 0.0], [0.0, 0.0, -1.0]])
    return np.column_stack([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


def rotation_yaw(mat: np.ndarray, finger_axis: int = 1) -> float:
    """Finger-axis yaw of a top-down TCP frame."""
    return float(np.arctan2(mat[1, finger_axis], mat[0, finger_axis]))


@dataclass(frozen=True)
class ArmModel:
    """What IK needs of a world's arm: a kinematic MuJoCo model, the TCP site, the arm's qpos and dof
    addresses (7 each), the posture the null space pulls towards, the finger axis of the site frame."""

    model: mujoco.MjModel
    tcp_site: int
    qpos: np.ndarray
    dof: np.ndarray
    home: np.ndarray
    finger_axis: int = 1
    base: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the base in the world: targets are world positions


def menagerie_panda() -> ArmModel:
    """Our world's Panda (MuJoCo Menagerie's, as ``sim_worker.robot`` adapts it)."""
    from sim_worker.robot import HOME_ARM_QPOS, PandaIndices, panda_spec

    model = panda_spec().compile()
    ix = PandaIndices.of(model)
    return ArmModel(model, ix.tcp_site, np.asarray(ix.qpos[:7]), np.asarray(ix.dof), HOME_ARM_QPOS.copy())


class ArmIK:
    """Kinematic seven-joint arm for solving TCP poses; one instance per thread."""

    def __init__(self, arm: ArmModel, config: "IKConfig | None" = None):
        self.config = config or IKConfig()
        self.arm = arm
        self.model = arm.model
        self.data = mujoco.MjData(self.model)
        self.lower = JOINT_LOWER[:7]
        self.upper = JOINT_UPPER[:7]
        self._jacp = np.zeros((3, self.model.nv))
        self._jacr = np.zeros((3, self.model.nv))

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and rotation matrix for arm joints ``q`` (7,)."""
        self.data.qpos[self.arm.qpos] = q
        mujoco.mj_kinematics(self.model, self.data)
        site = self.arm.tcp_site
        return self.data.site_xpos[site] + self.arm.base, self.data.site_xmat[site].reshape(3, 3).copy()

    def solve(self, pos: np.ndarray, yaw: float, q_start: np.ndarray) -> np.ndarray:
        """Arm joints (7,) placing the TCP at ``pos`` pointing down with finger axis at ``yaw``."""
        cfg = self.config
        target_rot = top_down_rotation(yaw, self.arm.finger_axis)
        q = np.clip(np.asarray(q_start, dtype=float).copy(), self.lower, self.upper)
        dof = self.arm.dof
        err = np.zeros(6)
        for _ in range(cfg.max_iterations):
            cur_pos, cur_rot = self.forward(q)
            err[:3] = pos - cur_pos
            # small-angle rotation error in the world frame
            err[3:] = 0.5 * sum(np.cross(cur_rot[:, i], target_rot[:, i]) for i in range(3))
            if np.linalg.norm(err[:3]) < cfg.position_tolerance and np.linalg.norm(err[3:]) < cfg.rotation_tolerance:
                return q
            mujoco.mj_comPos(self.model, self.data)
            mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.arm.tcp_site)
            jac = np.vstack([self._jacp[:, dof], self._jacr[:, dof]])  # (6, 7)
            jjt = jac @ jac.T + cfg.damping * np.eye(6)
            dq = jac.T @ np.linalg.solve(jjt, err)
            pinv = jac.T @ np.linalg.solve(jjt, np.eye(6))
            dq += (np.eye(7) - pinv @ jac) @ (cfg.posture_gain * (self.arm.home - q))
            scale = np.abs(dq).max() / cfg.max_step
            if scale > 1.0:
                dq /= scale
            q = np.clip(q + dq, self.lower, self.upper)
        raise IKFailure(
            f"no IK solution for position {np.round(pos, 4).tolist()} yaw {yaw:.3f} "
            f"(residual {np.linalg.norm(err[:3]) * 1000:.1f} mm, {np.degrees(np.linalg.norm(err[3:])):.2f} deg)"
        )


class PandaIK(ArmIK):
    """:class:`ArmIK` on our world's Panda."""

    def __init__(self, config: IKConfig = IKConfig()):
        super().__init__(menagerie_panda(), config)
