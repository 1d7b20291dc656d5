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
