"""The workspace: table, three coloured blocks, two open boxes and the cameras, built with MjSpec.

One scene serves both tasks, so a camera image always shows the same world; the boxes sit at the
sides of the table, clear of the stacking area. Everything the planner needs to know about the
fixed furniture (box placement and size) is published through :class:`SceneLayout` and reported
to clients with the object poses, so the planner never imports these constants.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sim_worker.robot import panda_spec

BLOCK_NAMES: tuple[str, ...] = ("red", "green", "blue")
BLOCK_COLOURS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.15, 0.12, 1.0),
    "green": (0.15, 0.7, 0.2, 1.0),
    "blue": (0.15, 0.3, 0.85, 1.0),
}
CAMERA = "agentview"
WRIST_CAMERA = "wrist"


@dataclass(frozen=True)
class BoxLayout:
    """An open box fixed to the table: centre (x, y), interior half extents, wall and floor size."""

    name: str
    centre: tuple[float, float]
    inner_half: tuple[float, float] = (0.10, 0.10)
    wall_height: float = 0.05  # above the box floor's top
    wall_thickness: float = 0.01
    floor_thickness: float = 0.01

    @property
    def floor_top(self) -> float:
        return self.floor_thickness

    @property
    def rim_height(self) -> float:
        return self.floor_thickness + self.wall_height

    def as_dict(self) -> dict:
        return {
            "name": self.name, "centre": list(self.centre), "inner_half": list(self.inner_half),
            "wall_height": self.wall_height, "wall_thickness": self.wall_thickness,
            "floor_top": self.floor_top, "rim_height": self.rim_height,
        }


@dataclass(frozen=True)
class SceneLayout:
    """Geometry of the fixed parts of the world (metres, world frame; the table top is z = 0)."""

    timestep: float = 0.005  # implicitfast is stable at 5 ms; 50 physics steps per 4 FPS plan step
    block_half: float = 0.02
    block_mass: float = 0.05
    block_friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)
    boxes: tuple[BoxLayout, ...] = (
        BoxLayout("box_a", (0.5, -0.22)),
        BoxLayout("box_b", (0.5, 0.22)),
    )
    stack_area_centre: tuple[float, float] = (0.5, 0.0)

    def box(self, name: str) -> BoxLayout:
        for box in self.boxes:
            if box.name == name:
                return box
        raise KeyError(name)

    def as_dict(self) -> dict:
        return {
            "block_half": self.block_half, "block_size": 2 * self.block_half,
            "boxes": {b.name: b.as_dict() for b in self.boxes},
            "stack_area_centre": list(self.stack_area_centre),
        }


@dataclass(frozen=True)
class CameraPose:
    """Where the fixed ``agentview`` camera stands and looks (world frame, metres, degrees)."""

    pos: tuple[float, float, float]
    target: tuple[float, float, float]
    fovy: float


#: Each task frames its workspace: stacking is seen low and from the side, so a tower's levels
#: show and the retreating gripper does not hide them; replacement is seen from high up, so the
#: blocks inside the boxes are not hidden by the walls.
CAMERA_POSES: dict[str, CameraPose] = {
    "stacking": CameraPose(pos=(0.95, 0.25, 0.35), target=(0.5, 0.0, 0.06), fovy=40.0),
    "replacement": CameraPose(pos=(0.8, 0.0, 0.95), target=(0.40, 0.0, 0.0), fovy=42.0),
}


@dataclass(frozen=True)
class RenderConfig:
    """Camera image settings. 84x84 as robomimic's default; shadows off (they cost 5-30x)."""

    height: int = 84
    width: int = 84
    shadows: bool = False
    visual_meshes: bool = False
    camera: CameraPose = CAMERA_POSES["replacement"]

    @classmethod
    def for_task(cls, task: str, height: int = 84, width: int = 84) -> "RenderConfig":
        """The task's camera framing at the given image size."""
        if task not in CAMERA_POSES:
            raise ValueError(f"task: unknown task {task!r}; expected one of {sorted(CAMERA_POSES)}")
        return cls(height=height, width=width, camera=CAMERA_POSES[task])


def _look_at_xyaxes(pos: np.ndarray, target: np.ndarray) -> list[float]:
    """MuJoCo camera ``xyaxes`` for a camera at ``pos`` looking at ``target`` with world z up."""
    forward = target - pos
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return [*right, *up]


def _add_box(world: mujoco.MjsBody, box: BoxLayout) -> None:
    """An open box as five static geoms (floor + four walls) so that fingers can hit the walls."""
    body = world.add_body(name=box.name, pos=[box.centre[0], box.centre[1], 0.0])
    colour = [0.62, 0.47, 0.3, 1.0]
    hx, hy = box.inner_half
    t = box.wall_thickness
    body.add_geom(name=f"{box.name}_floor", type=mujoco.mjtGeom.mjGEOM_BOX,
                  size=[hx + 2 * t / 2 + t / 2, hy + t, box.floor_thickness / 2],
                  pos=[0, 0, box.floor_thickness / 2], rgba=colour)
    zc = box.floor_thickness + box.wall_height / 2
    hz = box.wall_height / 2
    for name, pos, size in (
        ("xneg", [-(hx + t / 2), 0, zc], [t / 2, hy + t, hz]),
        ("xpos", [hx + t / 2, 0, zc], [t / 2, hy + t, hz]),
        ("yneg", [0, -(hy + t / 2), zc], [hx, t / 2, hz]),
        ("ypos", [0, hy + t / 2, zc], [hx, t / 2, hz]),
    ):
        body.add_geom(name=f"{box.name}_{name}", type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=pos,
                      rgba=colour)


def build_spec(layout: SceneLayout = SceneLayout(), render: RenderConfig = RenderConfig()) -> mujoco.MjSpec:
    """The full scene: Panda on a table, three free blocks, two fixed boxes, lights and cameras."""
    spec = panda_spec(visual_meshes=render.visual_meshes)
    spec.option.timestep = layout.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.visual.quality.shadowsize = 1024 if render.shadows else 0
    spec.visual.global_.offwidth = max(640, render.width)
    spec.visual.global_.offheight = max(480, render.height)
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.45, 0.45, 0.45]
    world = spec.worldbody

    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], pos=[0, 0, -0.75],
                   rgba=[0.35, 0.37, 0.4, 1])
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.55, 0.6, 0.375],
                   pos=[0.4, 0.0, -0.375], rgba=[0.78, 0.74, 0.66, 1])
    world.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=[-0.3, 0.2, -1.0],
                    diffuse=[0.6, 0.6, 0.6], castshadow=render.shadows)

    for box in layout.boxes:
        _add_box(world, box)

    h = layout.block_half
    for i, name in enumerate(BLOCK_NAMES):
        body = world.add_body(name=f"block_{name}", pos=[0.3, -0.1 + 0.1 * i, h])
        body.add_freejoint(name=f"block_{name}_joint")
        body.add_geom(name=f"block_{name}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[h, h, h],
                      mass=layout.block_mass, rgba=BLOCK_COLOURS[name], friction=list(layout.block_friction),
                      condim=4)

    pos = np.asarray(render.camera.pos, dtype=float)
    world.add_camera(name=CAMERA, pos=list(pos), xyaxes=_look_at_xyaxes(pos, np.asarray(render.camera.target, dtype=float)),
                     fovy=render.camera.fovy)
    spec.body("hand").add_camera(name=WRIST_CAMERA, pos=[0.05, 0.0, 0.0], xyaxes=[0, -1, 0, 1, 0, 0],
                                 fovy=70.0)
    # the Menagerie keyframe only covers the arm; extend it with the blocks' free joints
    key = spec.key("home")
    block_qpos = []
    for i in range(len(BLOCK_NAMES)):
        block_qpos += [0.3, -0.1 + 0.1 * i, h, 1.0, 0.0, 0.0, 0.0]
    key.qpos = list(key.qpos) + block_qpos
    return spec
