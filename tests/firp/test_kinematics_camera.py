"""The arm's kinematics and the camera's calibration as data: round trips, errors that name the field, the maths."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from firp.core.camera import CalibrationError, CameraCalibration
from firp.core.kinematics import CHAIN_FORMAT, ChainJoint, KinematicChain, KinematicsError, Pose

PANDA = Path(__file__).resolve().parents[1] / "golden" / "panda_chain.json"


def planar_arm(l1: float = 0.5, l2: float = 0.3) -> KinematicChain:
    """Two joints about z, links along x: the tool at (l1 cos a + l2 cos(a + b), l1 sin a + l2 sin(a + b), 0)."""
    return KinematicChain((ChainJoint("a", Pose(), (0.0, 0.0, 1.0)), ChainJoint("b", Pose((l1, 0.0, 0.0)), (0.0, 0.0, 1.0))),
                          tool=Pose((l2, 0.0, 0.0)))


def test_a_planar_arm_s_tool_lands_where_trigonometry_says():
    q = np.array([[0.3, -0.7], [1.2, 0.4]])
    pose = planar_arm().tool_pose(q)
    expected = np.stack([0.5 * np.cos(q[:, 0]) + 0.3 * np.cos(q.sum(1)), 0.5 * np.sin(q[:, 0]) + 0.3 * np.sin(q.sum(1))], 1)
    np.testing.assert_allclose(pose[:, :2, 3], expected, atol=1e-12)
    np.testing.assert_allclose(np.arctan2(pose[:, 1, 0], pose[:, 0, 0]), q.sum(1), atol=1e-12)


def test_a_prismatic_joint_slides_along_its_axis():
    chain = KinematicChain((ChainJoint("slide", Pose(), (0.0, 1.0, 0.0), "prismatic"),), tool=Pose((0.0, 0.0, 0.1)))
    np.testing.assert_allclose(chain.tool_pose(np.array([0.25]))[:3, 3], [0.0, 0.25, 0.1])


def test_the_chain_survives_json_and_a_pose_survives_its_matrix():
    chain = KinematicChain.from_dict(json.loads(PANDA.read_text()))
    again = KinematicChain.from_dict(json.loads(json.dumps(chain.to_dict())))
    assert again == chain and again.joint_names == tuple(f"joint{i}" for i in range(1, 8))
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        pose = Pose(tuple(rng.normal(size=3)), tuple(q / np.linalg.norm(q)))
        np.testing.assert_allclose(Pose.from_matrix(pose.matrix()).matrix(), pose.matrix(), atol=1e-12)


@pytest.mark.parametrize("edit, field", [
    (lambda d: d.update(format="urdf"), "kinematics.format"),
    (lambda d: d["joints"][2]["axis"].__setitem__(0, 3.0), "kinematics.joints[2].axis"),
    (lambda d: d["joints"][0]["origin"].__setitem__("quat", [2, 0, 0, 0]), "kinematics.joints[0].origin.quat"),
    (lambda d: d["joints"][1].update(type="ball"), "kinematics.joints[1].type"),
    (lambda d: d["joints"][1].pop("axis"), "kinematics.joints[1]"),
    (lambda d: d["joints"][3].update(name="joint1"), "kinematics.joints"),
    (lambda d: d.update(joints=[]), "kinematics.joints"),
    (lambda d: d["tool"].update(pos=[0, 0]), "kinematics.tool.pos"),
])
def test_a_bad_chain_is_refused_naming_the_field(edit, field):
    data = json.loads(PANDA.read_text())
    edit(data)
    with pytest.raises(KinematicsError, match=field.replace("[", r"\[").replace("]", r"\]")):
        KinematicChain.from_dict(data)
    assert data.get("format", CHAIN_FORMAT) in (CHAIN_FORMAT, "urdf")


def looking_down(height: float = 1.0) -> CameraCalibration:
    """A camera ``height`` above the origin looking straight down (image x along world x, image y along -y)."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[2, 3] = height
    return CameraCalibration.from_fovy(200, 100, 60.0, pose)


def test_a_point_on_the_optical_axis_lands_on_the_principal_point_and_offsets_scale_with_focal_length():
    cam = looking_down()
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.5]]))
    f = 50 / math.tan(math.radians(30))
    np.testing.assert_allclose(uv[0], [100, 50])
    np.testing.assert_allclose(uv[1], [100 + f * 0.1, 50])
    np.testing.assert_allclose(uv[2], [100, 50 - f * 0.1 / 0.5])  # world +y is up the image, twice as near
    np.testing.assert_allclose(depth, [1.0, 1.0, 0.5])
    homogeneous = cam.projection() @ np.array([0.1, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(homogeneous[:2] / homogeneous[2], uv[1])
    half = cam.resized(100, 50)
    np.testing.assert_allclose(half.project(np.array([0.1, 0.0, 0.0]))[0], uv[1] / 2)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(width=3), "calibration.width"),
    (lambda d: d.update(fx=-1.0), "calibration.fx/fy"),
    (lambda d: d.update(cy=float("nan")), "calibration.cy"),
    (lambda d: d["world_from_camera"][0].__setitem__(0, 2.0), "calibration.world_from_camera"),
    (lambda d: d.pop("fy"), "missing \\['fy'\\]"),
])
def test_a_bad_calibration_is_refused_naming_the_field(edit, message):
    data = looking_down().to_dict()
    assert CameraCalibration.from_dict(data) == looking_down()
    edit(data)
    with pytest.raises(CalibrationError, match=message):
        CameraCalibration.from_dict(data)
