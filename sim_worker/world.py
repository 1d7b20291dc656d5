"""A live simulation: compiled scene, physics data, renderer, and the state helpers around them.

One :class:`World` per process (or per worker thread); it is reset to a task's seeded initial
state before every execution, which is what makes executions repeatable.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from firp.core.camera import CameraCalibration
from sim_worker.robot import PandaIndices
from sim_worker.scene import BLOCK_NAMES, CAMERA, RenderConfig, SceneLayout, build_spec
from sim_worker.tasks import BlockState

STATE_SPEC = mujoco.mjtState.mjSTATE_PHYSICS  # qpos, qvel, act: enough to restore the physics


def yaw_quat(yaw: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation by ``yaw`` about world z."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def quat_yaw(quat: np.ndarray) -> float:
    """Yaw of a (nearly upright) body's quaternion, wrapped to a cube's symmetry [-pi/4, pi/4)."""
    w, x, y, z = quat
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return float((yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)


@dataclass(frozen=True)
class BlockHandles:
    qpos: np.ndarray  # (n_blocks,) start of each free joint's qpos (x y z qw qx qy qz)
    qvel: np.ndarray  # (n_blocks,)
    body: np.ndarray  # (n_blocks,)


class World:
    """Model + data + renderer for one scene. Not thread-safe: use one per thread or process."""

    def __init__(self, layout: SceneLayout = SceneLayout(), render: RenderConfig = RenderConfig()):
        self.layout = layout
        self.render_config = render
        self.model = build_spec(layout, render).compile()
        self.data = mujoco.MjData(self.model)
        self.panda = PandaIndices.of(self.model)
        joints = [self.model.joint(f"block_{n}_joint").id for n in BLOCK_NAMES]
        self.blocks = BlockHandles(
            qpos=np.array([self.model.jnt_qposadr[j] for j in joints]),
            qvel=np.array([self.model.jnt_dofadr[j] for j in joints]),
            body=np.array([self.model.body(f"block_{n}").id for n in BLOCK_NAMES]),
        )
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self.state_size = mujoco.mj_stateSize(self.model, STATE_SPEC)

    # -- state -------------------------------------------------------------------------------
    def reset(self, block_poses: np.ndarray) -> None:
        """Robot at home with fingers open; blocks at ``block_poses`` (n, 4) = x, y, z, yaw."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("home").id)
        for adr, pose in zip(self.blocks.qpos, np.asarray(block_poses, dtype=float)):
            self.data.qpos[adr:adr + 3] = pose[:3]
            self.data.qpos[adr + 3:adr + 7] = yaw_quat(pose[3])
        mujoco.mj_forward(self.model, self.data)

    def get_state(self) -> np.ndarray:
        state = np.empty(self.state_size)
        mujoco.mj_getState(self.model, self.data, state, STATE_SPEC)
        return state

    def joint_positions(self) -> np.ndarray:
        """The nine contract joints' current positions."""
        return self.data.qpos[self.panda.qpos].copy()

    def block_poses(self) -> np.ndarray:
        """Current block poses (n, 4) = x, y, z, yaw (yaw modulo the cube's 90 deg symmetry)."""
        out = np.empty((len(BLOCK_NAMES), 4))
        for i, adr in enumerate(self.blocks.qpos):
            out[i, :3] = self.data.qpos[adr:adr + 3]
            out[i, 3] = quat_yaw(self.data.qpos[adr + 3:adr + 7])
        return out

    def block_states(self) -> list[BlockState]:
        """Position, tilt of the most upright face normal, and speed of each block."""
        states = []
        for body, vadr in zip(self.blocks.body, self.blocks.qvel):
            mat = self.data.xmat[body].reshape(3, 3)
            # a cube is "flat" when any of its face normals points up: take the best one
            tilt = float(np.degrees(np.arccos(np.clip(np.abs(mat[2]).max(), -1.0, 1.0))))
            speed = float(np.linalg.norm(self.data.qvel[vadr:vadr + 3]))
            states.append(BlockState(self.data.xpos[body].copy(), tilt, speed))
        return states

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self.data.site_xpos[self.panda.tcp_site].copy(), self.data.site_xmat[self.panda.tcp_site].reshape(3, 3).copy()

    # -- pictures ------------------------------------------------------------------------------
    @property
    def renderer(self) -> mujoco.Renderer:
        return self._renderer_at(self.render_config.height, self.render_config.width)

    def _renderer_at(self, height: int, width: int) -> mujoco.Renderer:
        if (height, width) not in self._renderers:
            self._renderers[(height, width)] = mujoco.Renderer(self.model, height, width)
        return self._renderers[(height, width)]

    def render(self, camera: str = CAMERA, size: int | None = None) -> np.ndarray:
        """The camera image (H, W, 3) uint8 of the current state; ``size``: a square image of that many pixels
        instead of the world's render size (the plan-conditioned view's higher resolution)."""
        renderer = self.renderer if size is None else self._renderer_at(size, size)
        renderer.update_scene(self.data, camera=camera)
        return renderer.render().copy()

    def camera_calibration(self, camera: str = CAMERA, width: int | None = None,
                           height: int | None = None) -> CameraCalibration:
        """The fixed camera's calibration for images of ``width`` x ``height`` (default: this world's renders).

        MuJoCo's camera frame looks along -z with y up; the calibration's (OpenCV's) looks along +z with y
        down, so the two differ by a half turn about x."""
        cam = self.model.camera(camera).id
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        pose = np.eye(4)
        pose[:3, :3] = self.data.cam_xmat[cam].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = self.data.cam_xpos[cam]
        return CameraCalibration.from_fovy(width or self.render_config.width, height or self.render_config.height,
                                           float(self.model.cam_fovy[cam]), pose)

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()

    def __enter__(self) -> "World":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
