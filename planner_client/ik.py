"""Inverse kinematics for top-down gripper poses: damped least squares on ``mj_jacSite``.

Top-down grasps need nothing more elaborate: the solver is warm-started from the previous step
of the trajectory, so consecutive solutions stay on one branch, and a null-space pull towards
the home posture keeps the elbow up.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from firp.core.contract import JOINT_LOWER, JOINT_UPPER
from sim_worker.robot import HOME_ARM_QPOS, PandaIndices, panda_spec


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


def top_down_rotation(yaw: float) -> np.ndarray:
    """TCP frame with z pointing down and the finger axis (y) at ``yaw`` in the table plane."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.column_stack([[-s, c, 0.0], [c, s, 0.0], [0.0, 0.0, -1.0]])


def rotation_yaw(mat: np.ndarray) -> float:
    """Finger-axis yaw of a top-down TCP frame."""
    return float(np.arctan2(mat[1, 1], mat[0, 1]))


class PandaIK:
    """Kinematic Panda (arm only) for solving TCP poses; one instance per thread."""

    def __init__(self, config: IKConfig = IKConfig()):
        self.config = config
        self.model = panda_spec().compile()
        self.data = mujoco.MjData(self.model)
        self.ix = PandaIndices.of(self.model)
        self.lower = JOINT_LOWER[:7]
        self.upper = JOINT_UPPER[:7]
        self._jacp = np.zeros((3, self.model.nv))
        self._jacr = np.zeros((3, self.model.nv))

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and rotation matrix for arm joints ``q`` (7,)."""
        self.data.qpos[self.ix.qpos[:7]] = q
        mujoco.mj_kinematics(self.model, self.data)
        site = self.ix.tcp_site
        return self.data.site_xpos[site].copy(), self.data.site_xmat[site].reshape(3, 3).copy()

    def solve(self, pos: np.ndarray, yaw: float, q_start: np.ndarray) -> np.ndarray:
        """Arm joints (7,) placing the TCP at ``pos`` pointing down with finger axis at ``yaw``."""
        cfg = self.config
        target_rot = top_down_rotation(yaw)
        q = np.clip(np.asarray(q_start, dtype=float).copy(), self.lower, self.upper)
        dof = self.ix.dof
        err = np.zeros(6)
        for _ in range(cfg.max_iterations):
            cur_pos, cur_rot = self.forward(q)
            err[:3] = pos - cur_pos
            # small-angle rotation error in the world frame
            err[3:] = 0.5 * sum(np.cross(cur_rot[:, i], target_rot[:, i]) for i in range(3))
            if np.linalg.norm(err[:3]) < cfg.position_tolerance and np.linalg.norm(err[3:]) < cfg.rotation_tolerance:
                return q
            mujoco.mj_comPos(self.model, self.data)
            mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.ix.tcp_site)
            jac = np.vstack([self._jacp[:, dof], self._jacr[:, dof]])  # (6, 7)
            jjt = jac @ jac.T + cfg.damping * np.eye(6)
            dq = jac.T @ np.linalg.solve(jjt, err)
            pinv = jac.T @ np.linalg.solve(jjt, np.eye(6))
            dq += (np.eye(7) - pinv @ jac) @ (cfg.posture_gain * (HOME_ARM_QPOS - q))
            scale = np.abs(dq).max() / cfg.max_step
            if scale > 1.0:
                dq /= scale
            q = np.clip(q + dq, self.lower, self.upper)
        raise IKFailure(
            f"no IK solution for position {np.round(pos, 4).tolist()} yaw {yaw:.3f} "
            f"(residual {np.linalg.norm(err[:3]) * 1000:.1f} mm, {np.degrees(np.linalg.norm(err[3:])):.2f} deg)"
        )
