"""robosuite's Panda, as the plan's grasp-frame description reads it: the fixture both environments check.

``firp.model.plan_geometry`` reads a plan with the Franka Panda's DH kinematics (torch, main environment);
robosuite's Panda lives in ``.venv-robosuite`` (no torch). ``tests/golden/robosuite_panda_grip_site.json``
holds robosuite's grip-site poses for fixed joint angles: this test checks it against robosuite's model,
``tests/firp/model/test_plan_geometry.py`` checks the DH model against it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from robosuite_worker.robot import grip_site_poses, panda_kinematics

FIXTURE = Path(__file__).resolve().parents[1] / "golden" / "robosuite_panda_grip_site.json"


def fixture_joints(home: np.ndarray) -> np.ndarray:
    """Twelve postures around robosuite's initial one (seeded)."""
    return home + np.random.default_rng(0).normal(0.0, 0.4, size=(12, 7))


def test_the_grip_site_fixture_is_robosuites_own_model():
    kinematics = panda_kinematics()
    recorded = json.loads(FIXTURE.read_text())
    joints = fixture_joints(kinematics.home)
    np.testing.assert_allclose(np.array(recorded["joints"]), joints, atol=1e-12)
    positions, rotations = grip_site_poses(kinematics, joints)
    np.testing.assert_allclose(np.array(recorded["position"]), positions, atol=1e-9)
    np.testing.assert_allclose(np.array(recorded["rotation"]), rotations, atol=1e-9)


if __name__ == "__main__":  # regenerate: .venv-robosuite/bin/python -m tests.robosuite_worker.test_kinematics
    kinematics = panda_kinematics()
    joints = fixture_joints(kinematics.home)
    positions, rotations = grip_site_poses(kinematics, joints)
    FIXTURE.write_text(json.dumps({"what": "robosuite 1.5.2 Panda + PandaGripper, gripper0_right_grip_site in the "
                                           "base frame (robosuite_worker.robot.grip_site_poses)",
                                   "joints": joints.tolist(), "position": positions.tolist(),
                                   "rotation": rotations.tolist()}, indent=1) + "\n")
