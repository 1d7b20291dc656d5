import mujoco
import numpy as np
import pytest

from firp.core.contract import FINGER_OPEN, JOINT_LOWER, JOINT_NAMES, JOINT_UPPER
from sim_worker.robot import GRIPPER_CTRL_MAX, PandaIndices, finger_ctrl, panda_spec


def test_contract_joint_limits_match_the_menagerie_model():
    model = panda_spec().compile()
    for i, name in enumerate(JOINT_NAMES):
        low, high = model.jnt_range[model.joint(name).id]
        assert low == pytest.approx(JOINT_LOWER[i], abs=1e-4), name
        assert high == pytest.approx(JOINT_UPPER[i], abs=1e-4), name


def test_gravity_compensation_holds_the_home_posture():
    model = panda_spec().compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    ix = PandaIndices.of(model)
    start = data.qpos[ix.qpos].copy()
    mujoco.mj_step(model, data, nstep=500)
    assert np.abs(data.qpos[ix.qpos][:7] - start[:7]).max() < 1e-4


def test_finger_ctrl_maps_metres_onto_the_gripper_range():
    assert finger_ctrl(np.array([FINGER_OPEN, FINGER_OPEN])) == pytest.approx(GRIPPER_CTRL_MAX)
    assert finger_ctrl(np.array([0.0, 0.0])) == pytest.approx(0.0)
    assert finger_ctrl(np.array([0.01, 0.03])) == pytest.approx(GRIPPER_CTRL_MAX / 2)


def test_tcp_sits_between_the_fingertips():
    model = panda_spec().compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    ix = PandaIndices.of(model)
    pads = [g for g in range(model.ngeom) if model.geom_bodyid[g] in
            (model.body("left_finger").id, model.body("right_finger").id) and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
    centre = data.geom_xpos[pads].mean(axis=0)
    assert np.linalg.norm(centre - data.site_xpos[ix.tcp_site]) < 0.006


def test_the_kinematic_chain_read_off_the_model_puts_the_tool_where_mujoco_does():
    import json
    from pathlib import Path

    import mujoco

    from firp.core.contract import JOINT_LOWER, JOINT_UPPER
    from firp.core.kinematics import KinematicChain
    from sim_worker.robot import PandaIndices, kinematic_chain
    from sim_worker.scene import build_spec

    model = build_spec().compile()
    data = mujoco.MjData(model)
    chain = kinematic_chain(model)
    golden = Path(__file__).resolve().parents[1] / "golden" / "panda_chain.json"
    assert KinematicChain.from_dict(json.loads(golden.read_text())) == chain, "tests/golden/panda_chain.json is stale"
    panda = PandaIndices.of(model)
    rng = np.random.default_rng(1)
    for _ in range(25):
        q = rng.uniform(JOINT_LOWER[:7], JOINT_UPPER[:7])
        data.qpos[panda.qpos[:7]] = q
        mujoco.mj_kinematics(model, data)
        pose = chain.base.matrix() @ chain.tool_pose(q)
        np.testing.assert_allclose(pose[:3, 3], data.site_xpos[panda.tcp_site], atol=1e-9)
        np.testing.assert_allclose(pose[:3, :3], data.site_xmat[panda.tcp_site].reshape(3, 3), atol=1e-9)


def test_the_camera_calibration_projects_each_block_onto_its_colour():
    from sim_worker.scene import BLOCK_COLOURS, BLOCK_NAMES, RenderConfig, SceneLayout
    from sim_worker.tasks import sample_initial_blocks
    from sim_worker.world import World

    with World(SceneLayout(), RenderConfig.for_task("stacking", 128, 128)) as world:
        blocks = sample_initial_blocks("stacking", 7)
        world.reset(blocks)
        image = world.render().astype(int)
        uv, depth = world.camera_calibration().project(blocks[:, :3])
    assert (depth > 0).all()
    for name, (u, v) in zip(BLOCK_NAMES, uv):
        colour = np.array(BLOCK_COLOURS[name][:3])
        assert int(np.argmax(image[int(v), int(u)])) == int(np.argmax(colour)), f"{name} block not at {u:.1f}, {v:.1f}"
