"""Three cubes stacked into one tower: robosuite's ``Stack`` (two cubes) with a third, in its style.

MimicGen's stacking column has three cubes; robosuite ships two. Same table, materials, sampler and
observables as ``Stack``; the success check is written like ``Stack.staged_rewards``'s stacking
stage, extended to a tower of three: the middle cube is lifted off the table and touches the bottom
one, the top cube is above the middle one and touches it, and the gripper holds none of them. Which
cube goes where is the planner's choice (any order is a tower).

Beside the arena's cameras it has ``workspaceview``: a close front view at table height of the square
the cubes are placed in. In robosuite's ``agentview`` a 4-5 cm cube is 5-8 pixels of an 84 px image,
and a finished tower differs from two stacked cubes with the third beside them by a few of them; from
``workspaceview`` a cube is some 15 pixels and the tower's side is in view.
"""


import numpy as np
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
from robosuite.models.arenas import TableArena
from robosuite.models.objects import BoxObject
from robosuite.models.tasks import ManipulationTask
from robosuite.utils.mjcf_utils import CustomMaterial
from robosuite.utils.observables import Observable, sensor
from robosuite.utils.placement_samplers import UniformRandomSampler
from robosuite.utils.transform_utils import convert_quat, mat2quat

#: (name, half size, rgba, robosuite texture) of the three cubes
CUBES = (("cubeA", 0.02, (1, 0, 0, 1), "WoodRed"), ("cubeB", 0.025, (0, 1, 0, 1), "WoodGreen"),
         ("cubeC", 0.02, (0, 0, 1, 1), "WoodBlue"))
#: a cube counts as off the table (lifted) this far above the table top, as in robosuite's Stack
LIFT_MARGIN = 0.04
#: the top cube's centre must be at least this far above the middle one's (the smallest cube is 4 cm high)
LEVEL_MARGIN = 0.03
#: ``workspaceview``: where it is, the point it looks at (both in the world frame, m) and its vertical field of
#: view (degrees) -- 49 cm from the table's centre, 25 cm above its top, so a tower's three cubes and the
#: +-7 cm square they start in fill the middle of the image
WORKSPACE_CAMERA = ((0.45, 0.0, 1.05), (0.0, 0.0, 0.86), 40.0)


def look_at_quat(position, target) -> np.ndarray:
    """The (w, x, y, z) orientation of a MuJoCo camera at ``position`` looking at ``target``, its image upright
    (a camera looks along its -z axis with +y up)."""
    forward = np.asarray(target, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return convert_quat(mat2quat(np.stack([right, up, -forward], axis=1)), to="wxyz")


class StackThree(ManipulationEnv):
    """Stack three cubes into one tower on the table, with a single-arm robot.

    Arguments are those of robosuite's ``Stack`` (see its docstring); the sampler places the three
    cubes apart within ``placement_range`` of the table's centre, each with a random yaw.
    """

    def __init__(self, robots, env_configuration="default", controller_configs=None, gripper_types="default",
                 base_types="default", initialization_noise="default", table_full_size=(0.8, 0.8, 0.05),
                 table_friction=(1.0, 5e-3, 1e-4), use_camera_obs=True, use_object_obs=True, reward_scale=1.0,
                 reward_shaping=False, placement_initializer=None, placement_range=0.1, has_renderer=False,
                 has_offscreen_renderer=True, render_camera="frontview", render_collision_mesh=False,
                 render_visual_mesh=True, render_gpu_device_id=-1, control_freq=20, lite_physics=True, horizon=1000,
                 ignore_done=False, hard_reset=True, camera_names="agentview", camera_heights=256, camera_widths=256,
                 camera_depths=False, camera_segmentations=None, renderer="mjviewer", renderer_config=None, seed=None):
        self.table_full_size = table_full_size
        self.table_friction = table_friction
        self.table_offset = np.array((0, 0, 0.8))
        self.reward_scale = reward_scale
        self.reward_shaping = reward_shaping
        self.use_object_obs = use_object_obs
        self.placement_initializer = placement_initializer
        self.placement_range = placement_range
        super().__init__(
            robots=robots, env_configuration=env_configuration, controller_configs=controller_configs,
            base_types=base_types, gripper_types=gripper_types, initialization_noise=initialization_noise,
            use_camera_obs=use_camera_obs, has_renderer=has_renderer, has_offscreen_renderer=has_offscreen_renderer,
            render_camera=render_camera, render_collision_mesh=render_collision_mesh,
            render_visual_mesh=render_visual_mesh, render_gpu_device_id=render_gpu_device_id,
            control_freq=control_freq, lite_physics=lite_physics, horizon=horizon, ignore_done=ignore_done,
            hard_reset=hard_reset, camera_names=camera_names, camera_heights=camera_heights,
            camera_widths=camera_widths, camera_depths=camera_depths, camera_segmentations=camera_segmentations,
            renderer=renderer, renderer_config=renderer_config, seed=seed,
        )

    def reward(self, action=None):
        """Sparse: ``reward_scale`` when the tower of three stands (``_check_success``), else 0."""
        return float(self.reward_scale) if self._check_success() else 0.0

    def _load_model(self):
        super()._load_model()
        xpos = self.robots[0].robot_model.base_xpos_offset["table"](self.table_full_size[0])
        self.robots[0].robot_model.set_base_xpos(xpos)
        mujoco_arena = TableArena(table_full_size=self.table_full_size, table_friction=self.table_friction,
                                  table_offset=self.table_offset)
        mujoco_arena.set_origin([0, 0, 0])
        position, target, fovy = WORKSPACE_CAMERA
        mujoco_arena.set_camera("workspaceview", pos=list(position), quat=list(look_at_quat(position, target)),
                                camera_attribs={"fovy": str(fovy)})
        tex_attrib = {"type": "cube"}
        mat_attrib = {"texrepeat": "1 1", "specular": "0.4", "shininess": "0.1"}
        self.cubes = []
        for name, half, rgba, texture in CUBES:
            material = CustomMaterial(texture=texture, tex_name=f"{name}_tex", mat_name=f"{name}_mat",
                                      tex_attrib=tex_attrib, mat_attrib=mat_attrib)
            self.cubes.append(BoxObject(name=name, size_min=[half] * 3, size_max=[half] * 3, rgba=list(rgba),
                                        material=material))
        self.cubeA, self.cubeB, self.cubeC = self.cubes
        if self.placement_initializer is not None:
            self.placement_initializer.reset()
            self.placement_initializer.add_objects(self.cubes)
        else:
            r = self.placement_range
            self.placement_initializer = UniformRandomSampler(
                name="ObjectSampler", mujoco_objects=self.cubes, x_range=[-r, r], y_range=[-r, r], rotation=None,
                ensure_object_boundary_in_range=False, ensure_valid_placement=True,
                reference_pos=self.table_offset, z_offset=0.01, rng=self.rng)
        self.model = ManipulationTask(mujoco_arena=mujoco_arena,
                                      mujoco_robots=[robot.robot_model for robot in self.robots],
                                      mujoco_objects=self.cubes)

    def _setup_references(self):
        super()._setup_references()
        self.cube_body_ids = [self.sim.model.body_name2id(cube.root_body) for cube in self.cubes]

    def _reset_internal(self):
        super()._reset_internal()
        if not self.deterministic_reset:
            for obj_pos, obj_quat, obj in self.placement_initializer.sample().values():
                self.sim.data.set_joint_qpos(obj.joints[0], np.concatenate([np.array(obj_pos), np.array(obj_quat)]))

    def _setup_observables(self):
        observables = super()._setup_observables()
        if self.use_object_obs:
            modality = "object"
            sensors = []
            for cube, body_id in zip(self.cubes, self.cube_body_ids):
                sensors += [self._pos_sensor(cube.name, body_id, modality), self._quat_sensor(cube.name, body_id, modality)]
            arm_prefixes = self._get_arm_prefixes(self.robots[0], include_robot_name=False)
            full_prefixes = self._get_arm_prefixes(self.robots[0])
            sensors += [self._get_obj_eef_sensor(full_pf, f"{cube.name}_pos", f"{arm_pf}gripper_to_{cube.name}", modality)
                        for arm_pf, full_pf in zip(arm_prefixes, full_prefixes) for cube in self.cubes]
            for s in sensors:
                observables[s.__name__] = Observable(name=s.__name__, sensor=s, sampling_rate=self.control_freq)
        return observables

    def _pos_sensor(self, name, body_id, modality):
        @sensor(modality=modality)
        def pos(obs_cache):
            return np.array(self.sim.data.body_xpos[body_id])
        pos.__name__ = f"{name}_pos"
        return pos

    def _quat_sensor(self, name, body_id, modality):
        @sensor(modality=modality)
        def quat(obs_cache):
            return convert_quat(np.array(self.sim.data.body_xquat[body_id]), to="xyzw")
        quat.__name__ = f"{name}_quat"
        return quat

    def tower(self):
        """The cubes from the lowest to the highest, by their centres' heights."""
        heights = [self.sim.data.body_xpos[body_id][2] for body_id in self.cube_body_ids]
        return [self.cubes[i] for i in np.argsort(heights)], sorted(heights)

    def _check_success(self):
        """Whether the three cubes stand as one tower and the gripper holds none of them."""
        (bottom, middle, top), (z_bottom, z_middle, z_top) = self.tower()
        if any(self._check_grasp(gripper=self.robots[0].gripper, object_geoms=cube) for cube in self.cubes):
            return False
        middle_lifted = z_middle > self.table_offset[2] + LIFT_MARGIN
        top_above = z_top > z_middle + LEVEL_MARGIN
        return bool(middle_lifted and top_above and self.check_contact(middle, bottom)
                    and self.check_contact(top, middle))

    def visualize(self, vis_settings):
        super().visualize(vis_settings=vis_settings)
        if vis_settings["grippers"]:
            self._visualize_gripper_to_target(gripper=self.robots[0].gripper, target=self.cubeA)


__all__ = ["CUBES", "StackThree", "WORKSPACE_CAMERA", "look_at_quat"]
