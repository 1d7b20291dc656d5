"""robosuite's own Panda as a planner needs it: the standalone kinematic model and where it stands.

``robosuite.models.robots.Panda`` with its ``PandaGripper`` compiles on its own (9 joints: 7 arm, 2
fingers). Its base is at the origin there; in a task's world it stands at ``robot_base`` (reported in
each episode's ``scene``), unrotated. IK targets the gripper's ``grip_site`` (between the fingertip
pads); that site's z axis points out of the hand and the fingers close along its x axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GRIP_SITE", "RobotKinematics", "grip_site_poses", "panda_kinematics", "robot_base"]

GRIP_SITE = "gripper0_right_grip_site"
ARM_JOINTS = tuple(f"robot0_joint{i}" for i in range(1, 8))
FINGER_AXIS = 0  # the grip site's x axis


@dataclass(frozen=True)
class RobotKinematics:
    model: object  # mujoco.MjModel of the arm and gripper alone
    tcp_site: int
    qpos: np.ndarray  # (7,) qpos addresses of the arm joints
    dof: np.ndarray  # (7,) dof addresses
    home: np.ndarray  # (7,) robosuite's initial posture
    finger_axis: int = FINGER_AXIS


def panda_kinematics() -> RobotKinematics:
    """The standalone robosuite Panda + gripper, compiled (a fraction of a second)."""
    from robosuite.models.grippers import PandaGripper
    from robosuite.models.robots import Panda

    robot = Panda()
    robot.add_gripper(PandaGripper(idn="0_right"))
    model = robot.get_model(mode="mujoco")
    joints = [model.joint(name) for name in ARM_JOINTS]
    return RobotKinematics(model, model.site(GRIP_SITE).id, np.array([j.qposadr[0] for j in joints]),
                           np.array([j.dofadr[0] for j in joints]), np.asarray(robot.init_qpos, dtype=float))


def robot_base(env) -> list[float]:
    """Where the arm's base (``robot0_link0``) stands in the task's world."""
    return [float(v) for v in env.sim.data.body_xpos[env.sim.model.body_name2id("robot0_link0")]]


def grip_site_poses(kinematics: RobotKinematics, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arm joint angles ``(N, 7)`` -> the grip site's positions ``(N, 3)`` and rotations ``(N, 3, 3)``,
    base frame: what a plan's joint targets put where, on robosuite's own model."""
    import mujoco

    data = mujoco.MjData(kinematics.model)
    positions, rotations = [], []
    for q in np.atleast_2d(joints):
        data.qpos[kinematics.qpos] = q
        mujoco.mj_kinematics(kinematics.model, data)
        positions.append(data.site_xpos[kinematics.tcp_site].copy())
        rotations.append(data.site_xmat[kinematics.tcp_site].reshape(3, 3).copy())
    return np.array(positions), np.array(rotations)
