"""A camera's calibration: pinhole intrinsics and where it stands, so 3-D points land on pixels.

The scorer reads the scene where the plan's hand meets it (:mod:`firp.model.plan_view`): the hand's
positions come from the plan by forward kinematics (:mod:`firp.core.kinematics`), and this module
puts them on the image. A world records its camera's calibration in every dataset it collects, a
bundle carries it as the deployment's default, and a scoring request may override it.

Conventions (OpenCV's): the camera frame has x to the right, y down and z forward; pixel ``(u, v)`` has
u to the right and v down from the image's top-left corner, pixel centres at ``k + 0.5``.
``world_from_camera`` is a 4x4 transform from the camera frame to the world frame, the frame the robot
base's pose (:attr:`firp.core.kinematics.KinematicChain.base`) is given in.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["CameraCalibration", "CalibrationError"]


class CalibrationError(ValueError):
    """A calibration broke a rule; the message names the field and the rule."""


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole intrinsics (pixels) at ``width`` x ``height`` and the camera's pose in the world."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_from_camera: tuple[tuple[float, ...], ...]  # 4x4, rows

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 8 <= value <= 4096:
                raise CalibrationError(f"calibration.{name}: must be an integer in [8, 4096] pixels, got {value!r}")
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not np.isfinite(value):
                raise CalibrationError(f"calibration.{name}: must be a finite number, got {value!r}")
        if not (self.fx > 0 and self.fy > 0):
            raise CalibrationError(f"calibration.fx/fy: focal lengths must be > 0 pixels, got {self.fx}, {self.fy}")
        m = np.asarray(self.world_from_camera, dtype=float)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise CalibrationError("calibration.world_from_camera: must be a 4x4 matrix of finite numbers")
        r = m[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0 or not np.allclose(m[3], [0, 0, 0, 1]):
            raise CalibrationError("calibration.world_from_camera: must be a rigid transform (a rotation, a "
                                   "translation, last row 0 0 0 1)")
        object.__setattr__(self, "world_from_camera", tuple(tuple(float(v) for v in row) for row in m))

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float, world_from_camera: np.ndarray) -> CameraCalibration:
        """A camera with square pixels, its principal point at the image centre and vertical field of view
        ``fovy_deg`` (MuJoCo's and robosuite's cameras)."""
        f = (height / 2) / np.tan(np.radians(fovy_deg) / 2)
        return cls(int(width), int(height), float(f), float(f), width / 2, height / 2,
                   tuple(map(tuple, np.asarray(world_from_camera, dtype=float))))

    @property
    def matrix(self) -> np.ndarray:
        """The intrinsic matrix K (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def camera_from_world(self) -> np.ndarray:
        """(4, 4): world points into the camera frame."""
        m = np.asarray(self.world_from_camera)
        r, t = m[:3, :3], m[:3, 3]
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ t
        return out

    def resized(self, width: int, height: int) -> CameraCalibration:
        """The same camera read at another image size (the pixels scale, the pose stays)."""
        sx, sy = width / self.width, height / self.height
        return CameraCalibration(int(width), int(height), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                                 self.world_from_camera)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points ``(..., 3)`` -> pixels ``(..., 2)`` (u right, v down) and depth ``(...)`` (metres
        in front of the camera; <= 0 behind it)."""
        p = np.asarray(points_world, dtype=float)
        cam = p @ self.camera_from_world[:3, :3].T + self.camera_from_world[:3, 3]
        z = cam[..., 2]
        safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = np.stack([self.fx * cam[..., 0] / safe + self.cx, self.fy * cam[..., 1] / safe + self.cy], axis=-1)
        return uv, z

    def projection(self, world_from_frame: np.ndarray | None = None) -> np.ndarray:
        """The 3x4 matrix that takes homogeneous points of a frame (the robot base's, given its pose in the world;
        default the world's) to homogeneous pixels: ``K [R | t] world_from_frame``."""
        frame = np.eye(4) if world_from_frame is None else np.asarray(world_from_frame, dtype=float)
        return self.matrix @ (self.camera_from_world @ frame)[:3]

    def to_dict(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "world_from_camera": [list(row) for row in self.world_from_camera]}

    @classmethod
    def from_dict(cls, data: Any, where: str = "calibration") -> CameraCalibration:
        """Read (and check) what :meth:`to_dict` wrote; errors name the field and the rule."""
        fields = ("width", "height", "fx", "fy", "cx", "cy", "world_from_camera")
        if not isinstance(data, Mapping):
            raise CalibrationError(f"{where}: must be an object with {', '.join(fields)}")
        missing, unknown = set(fields) - set(data), set(data) - set(fields)
        if missing or unknown:
            raise CalibrationError(f"{where}: missing {sorted(missing)}, unknown {sorted(unknown)}; the fields are "
                                   f"{', '.join(fields)}")
        try:
            matrix = np.asarray(data["world_from_camera"], dtype=float)
        except (TypeError, ValueError):
            raise CalibrationError(f"{where}.world_from_camera: must be a 4x4 matrix of numbers") from None
        try:
            return cls(data["width"], data["height"], data["fx"], data["fy"], data["cx"], data["cy"],
                       tuple(map(tuple, matrix)) if matrix.ndim == 2 else matrix)
        except CalibrationError as exc:
            raise CalibrationError(str(exc).replace("calibration.", f"{where}.", 1)) from None
