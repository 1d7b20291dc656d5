"""A robot arm's kinematics as data: a serial chain of joints, its tool point and where its base stands.

Why data and not code: the scorer reads where the hand goes from the plan alone (forward kinematics of
the joint targets), and it must do so for whatever arm a dataset or bundle was made with. So the chain
travels with the data -- a world writes it into every dataset it collects
(``sim_worker.robot.kinematic_chain`` reads it off the robot's own MuJoCo model), a bundle copies it
into its manifest, and the method's torch forward kinematics (:mod:`firp.model.kinematics`) is built
from it. Nothing about any particular arm is written here.

The chain, URDF-like: joint ``i``'s frame is the previous joint's frame (the base for the first) times
``origin_i`` (a fixed pose), then turned about ``axis_i`` by the joint's value (``revolute``: radians)
or moved along it (``prismatic``: metres). The tool point (between the fingertips, what a grasp closes
on) is the last joint's frame times ``tool``. ``base`` is the robot base in the world, which the
camera's calibration (:mod:`firp.core.camera`) is expressed in.

numpy only (the core imports no torch): :meth:`KinematicChain.tool_pose` is the reference the torch
version is tested against.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["CHAIN_FORMAT", "ChainJoint", "KinematicChain", "KinematicsError", "Pose", "quat_to_matrix"]

CHAIN_FORMAT = "firp-serial-chain-v1"
JOINT_TYPES = ("revolute", "prismatic")


class KinematicsError(ValueError):
    """A kinematic chain description broke a rule; the message names the field and the rule."""


def _vector(value: Any, n: int, where: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise KinematicsError(f"{where}: must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise KinematicsError(f"{where}: must be {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def quat_to_matrix(quat: Sequence[float]) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` -> rotation matrix (3, 3)."""
    w, x, y, z = np.asarray(quat, dtype=float) / np.linalg.norm(quat)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@dataclass(frozen=True)
class Pose:
    """A rigid transform: position (metres) and unit quaternion ``(w, x, y, z)``."""

    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    @classmethod
    def parse(cls, value: Any, where: str) -> Pose:
        if isinstance(value, Pose):
            return value
        if not isinstance(value, Mapping) or set(value) != {"pos", "quat"}:
            raise KinematicsError(f"{where}: must be an object with exactly 'pos' and 'quat', got {value!r}")
        pos = _vector(value["pos"], 3, f"{where}.pos")
        quat = _vector(value["quat"], 4, f"{where}.quat")
        norm = math.sqrt(sum(q * q for q in quat))
        if abs(norm - 1.0) > 1e-3:
            raise KinematicsError(f"{where}.quat: must be a unit quaternion (w, x, y, z), its norm is {norm:.4f}")
        return cls(pos, tuple(q / norm for q in quat))  # type: ignore[arg-type]

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Pose:
        """A 4x4 homogeneous transform -> a pose (the quaternion with w >= 0)."""
        m = np.asarray(matrix, dtype=float)
        r = m[:3, :3]
        w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
        x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
        y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
        z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
        q = np.array([w, x, y, z])
        q /= np.linalg.norm(q)
        return cls(tuple(float(v) for v in m[:3, 3]), tuple(float(v) for v in q))  # type: ignore[arg-type]

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous transform."""
        out = np.eye(4)
        out[:3, :3] = quat_to_matrix(self.quat)
        out[:3, 3] = self.pos
        return out

    def to_dict(self) -> dict[str, list[float]]:
        return {"pos": list(self.pos), "quat": list(self.quat)}


@dataclass(frozen=True)
class ChainJoint:
    """One actuated joint of the chain (see the module docstring for how frames compose)."""

    name: str
    origin: Pose
    axis: tuple[float, float, float]
    type: str = "revolute"

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "type": self.type, "origin": self.origin.to_dict(), "axis": list(self.axis)}


@dataclass(frozen=True)
class KinematicChain:
    """The arm from its base to its tool point; ``joints`` in the order of the plan's joint targets."""

    joints: tuple[ChainJoint, ...]
    tool: Pose = field(default_factory=Pose)
    base: Pose = field(default_factory=Pose)  # the robot base in the world frame

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    def __len__(self) -> int:
        return len(self.joints)

    def to_dict(self) -> dict[str, Any]:
        return {"format": CHAIN_FORMAT, "joints": [j.to_dict() for j in self.joints], "tool": self.tool.to_dict(),
                "base": self.base.to_dict()}

    @classmethod
    def from_dict(cls, data: Any, where: str = "kinematics") -> KinematicChain:
        """Read (and check) a description written by :meth:`to_dict`; errors name the field and the rule."""
        if not isinstance(data, Mapping):
            raise KinematicsError(f"{where}: must be an object, got {type(data).__name__}")
        if data.get("format") != CHAIN_FORMAT:
            raise KinematicsError(f"{where}.format: must be {CHAIN_FORMAT!r}, got {data.get('format')!r}")
        unknown = set(data) - {"format", "joints", "tool", "base"}
        if unknown:
            raise KinematicsError(f"{where}: unknown fields {sorted(unknown)}")
        raw_joints = data.get("joints")
        if not isinstance(raw_joints, Sequence) or isinstance(raw_joints, str) or not raw_joints:
            raise KinematicsError(f"{where}.joints: must be a non-empty list of joints")
        joints = []
        for i, raw in enumerate(raw_joints):
            at = f"{where}.joints[{i}]"
            if not isinstance(raw, Mapping) or set(raw) != {"name", "type", "origin", "axis"}:
                raise KinematicsError(f"{at}: must have exactly name, type, origin and axis")
            if not isinstance(raw["name"], str) or not raw["name"]:
                raise KinematicsError(f"{at}.name: must be a non-empty string")
            if raw["type"] not in JOINT_TYPES:
                raise KinematicsError(f"{at}.type: must be one of {JOINT_TYPES}, got {raw['type']!r}")
            axis = np.asarray(_vector(raw["axis"], 3, f"{at}.axis"))
            if abs(np.linalg.norm(axis) - 1.0) > 1e-3:
                raise KinematicsError(f"{at}.axis: must be a unit vector, its norm is {np.linalg.norm(axis):.4f}")
            joints.append(ChainJoint(raw["name"], Pose.parse(raw["origin"], f"{at}.origin"),
                                     tuple(float(v) for v in axis / np.linalg.norm(axis)), raw["type"]))
        names = [j.name for j in joints]
        if len(set(names)) != len(names):
            raise KinematicsError(f"{where}.joints: names must be unique, got {names}")
        return cls(tuple(joints), Pose.parse(data.get("tool", Pose().to_dict()), f"{where}.tool"),
                   Pose.parse(data.get("base", Pose().to_dict()), f"{where}.base"))

    def tool_pose(self, q: np.ndarray) -> np.ndarray:
        """Joint values ``(..., n)`` -> the tool point's pose in the **base** frame, ``(..., 4, 4)``."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1] != len(self.joints):
            raise KinematicsError(f"joint values: the chain has {len(self.joints)} joints, got {q.shape[-1]} values")
        out = np.broadcast_to(np.eye(4), (*q.shape[:-1], 4, 4)).copy()
        for i, joint in enumerate(self.joints):
            out = out @ joint.origin.matrix()
            out = out @ _joint_motion(joint, q[..., i])
        return out @ self.tool.matrix()


def _joint_motion(joint: ChainJoint, value: np.ndarray) -> np.ndarray:
    """The joint's own motion ``(..., 4, 4)``: a turn about its axis or a slide along it."""
    value = np.asarray(value, dtype=float)
    out = np.broadcast_to(np.eye(4), (*value.shape, 4, 4)).copy()
    axis = np.asarray(joint.axis)
    if joint.type == "prismatic":
        out[..., :3, 3] = value[..., None] * axis
        return out
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(value)[..., None, None], np.cos(value)[..., None, None]
    out[..., :3, :3] = np.eye(3) + s * k + (1 - c) * (k @ k)  # Rodrigues
    return out
