"""The generic reading of the plan: forward kinematics from data, the plan's events, the relation network and the
plan-conditioned view's hand-aligned crops."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from firp.core.camera import CameraCalibration
from firp.core.kinematics import KinematicChain
from firp.model import FIRPConfig
from firp.model.baselines import build_model
from firp.model.config import PlanEventsConfig
from firp.model.kinematics import ChainFK
from firp.model.plan_events import PlanEvents, event_steps
from firp.model.plan_geometry import panda_tcp_pose
from firp.model.plan_view import crop_grid

from .helpers import TINY, assert_finite_grads, random_plan

PANDA = json.loads((Path(__file__).resolve().parents[2] / "golden" / "panda_chain.json").read_text())
EVENTS = PlanEventsConfig(enabled=True, hidden=8, kinematics=PANDA)


def panda_plans(B: int, T: int, seed: int = 0) -> torch.Tensor:
    """Contract plans with joint targets inside the Panda's limits around its home posture."""
    torch.manual_seed(seed)
    plan = random_plan(B, T)
    home = torch.tensor([0.0, -0.35, 0.0, -2.3, 0.0, 1.95, -0.7853])
    plan[..., 7:14] = home + 0.3 * torch.randn(B, T, 7)
    plan[..., 14:] = torch.rand(B, T, 1).expand(B, T, 2) * 0.04
    from firp.core.contract import JOINT_LOWER, JOINT_UPPER

    return plan.clamp(torch.cat([torch.zeros(7), torch.tensor(JOINT_LOWER, dtype=torch.float32)]),
                      torch.cat([torch.ones(7), torch.tensor(JOINT_UPPER, dtype=torch.float32)]))


def test_chain_fk_equals_the_numpy_reference_and_the_panda_s_published_dh_parameters():
    chain = KinematicChain.from_dict(PANDA)
    q = panda_plans(3, 10)[..., 7:14].double()
    pos, rot = ChainFK(chain)(q)
    ref = chain.tool_pose(q.numpy())
    np.testing.assert_allclose(pos.numpy(), ref[..., :3, 3], atol=1e-6)
    np.testing.assert_allclose(rot.numpy(), ref[..., :3, :3], atol=1e-6)
    dh_pos, dh_rot = panda_tcp_pose(q)  # Franka's documented DH parameters: an independent derivation
    np.testing.assert_allclose(pos.numpy(), dh_pos.numpy(), atol=1e-6)
    np.testing.assert_allclose(rot.numpy(), dh_rot.numpy(), atol=1e-6)


def test_events_are_the_first_steps_of_category_runs_up_to_the_limit():
    plan = torch.zeros(2, 9, 16)
    for b, cats in enumerate([[4, 4, 1, 1, 1, 3, 0, 0, 5], [2, 2, 2, 2, 2, 2, 2, 2, 2]]):
        plan[b, torch.arange(9), torch.tensor(cats)] = 1.0
    index, present = event_steps(plan, None, max_events=24)
    assert index[0].tolist() == [0, 2, 5, 6, 8] and present[0].tolist() == [True] * 5
    assert index[1, :1].tolist() == [0] and present[1].tolist() == [True, False, False, False, False]
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[0, 6:] = False
    index, present = event_steps(plan, mask, max_events=2)
    assert index[0].tolist() == [0, 2] and present[1].tolist() == [True, False]


def test_the_relation_network_reads_raw_plans_learns_and_ignores_padding():
    events = PlanEvents(EVENTS, KinematicChain.from_dict(PANDA), action_dim=16)
    plans = panda_plans(6, 12)
    events.fit(plans)
    tokens, pairs, present = events.raw_features(plans)
    t = (tokens[present] - events.token_mean) / events.token_std
    assert t.mean(0).abs().max() < 1e-4 and ((t.std(0, unbiased=False) - 1).abs() < 1e-3).sum() >= 6
    out = events(plans)
    assert out.shape == (6, events.dim) and torch.isfinite(out).all()
    out.sum().backward()
    assert_finite_grads(events)
    padded = torch.cat([plans, plans[:, -1:].expand(6, 5, 16)], dim=1)
    mask = torch.ones(6, 17, dtype=torch.bool)
    mask[:, 12:] = False
    torch.testing.assert_close(events(padded, mask), events(plans), atol=1e-5, rtol=0)


def test_events_see_relations_in_the_hand_s_frame_not_where_the_arm_stands():
    """Turning the base joint turns the whole arm about the base's z: every relation between events stays."""
    events = PlanEvents(EVENTS, KinematicChain.from_dict(PANDA), action_dim=16)
    plans = panda_plans(2, 12).double()
    turned = plans.clone()
    turned[..., 7] += 0.4
    _, pairs, _ = events.raw_features(plans)
    _, pairs_turned, _ = events.raw_features(turned)
    torch.testing.assert_close(pairs, pairs_turned, atol=1e-9, rtol=0)


@pytest.mark.parametrize("kind", ["firp", "gru", "a_mlp", "a_mlp_image"])
def test_every_plan_reading_model_takes_the_events(kind):
    cfg = replace(TINY, events=EVENTS)
    model = build_model(kind, cfg)
    model.geometry.fit(panda_plans(4, 12))
    feats, plans = torch.randn(3, 12, TINY.encoder.backbone_dim), panda_plans(3, 12, seed=1)
    logits = model.score(feats[:, 0] if kind != "oracle" else feats, plans).logits
    assert logits.shape == (3,) and torch.isfinite(logits).all()
    out = model.forward_train(feats, plans)
    out["logits"].sum().backward()
    assert all(p.grad is not None for p in model.geometry.parameters())


def test_a_model_reads_the_hand_built_description_or_the_events_not_both():
    with pytest.raises(ValueError, match="not both"):
        FIRPConfig(geometry=replace(FIRPConfig().geometry, enabled=True), events=EVENTS)
    with pytest.raises(ValueError, match="events.kinematics"):
        build_model("firp", replace(TINY, events=replace(EVENTS, kinematics=None)))


def test_forward_initial_is_the_open_loop_that_inference_classifies():
    """Episodes without later frames train the same open loop FIRP.score computes (means: no sampling)."""
    model = build_model("firp", replace(TINY, events=EVENTS, action_chunk=4)).eval()
    model.geometry.fit(panda_plans(4, 12))
    feats, plans = torch.randn(3, TINY.encoder.backbone_dim), panda_plans(3, 12, seed=2)
    torch.testing.assert_close(model.forward_initial(feats, plans, sample=False), model.score(feats, plans).logits)


def overhead_camera(size: int = 64) -> tuple[CameraCalibration, torch.Tensor]:
    """A camera 1 m above the base looking down, and its base-frame projection (1, 3, 4)."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = [0.5, 0.0, 1.0]
    cam = CameraCalibration.from_fovy(size, size, 40.0, pose)
    return cam, torch.tensor(cam.projection(), dtype=torch.float32)[None]


def test_a_crop_is_centred_on_the_hand_and_turns_with_it():
    """A red square at the tool point with a green one beside it along the hand's closing axis: the crop shows red
    at its centre and green on the same side of it whatever the hand's yaw."""
    cam, projection = overhead_camera(128)
    cfg = replace(EVENTS, view=True, view_crop=32, view_window=0.08)
    from firp.model.plan_view import PlanView

    view = PlanView(cfg)
    for yaw in (0.0, 0.6, -1.1):
        rot = torch.tensor([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0, 0, 1.0]])
        rot = rot @ torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # pointing down, as a top grasp
        closing = rot[:, 1].numpy()  # the hand's y axis
        tool = np.array([0.5, 0.05, 0.0])
        image = np.zeros((128, 128, 3), np.uint8)
        for point, colour in ((tool, 0), (tool + 0.03 * closing, 1)):
            (u, v), _ = cam.project(point)
            image[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3, colour] = 255
        crops = view.crops(torch.from_numpy(image)[None], projection, torch.tensor(tool, dtype=torch.float32)[None, None],
                           rot[None, None])[0, 0]  # (3, C, C)
        assert crops[0, 14:18, 14:18].mean() > 0.5, f"yaw {yaw}: the tool point is not at the crop's centre"
        green = crops[1].nonzero().float().mean(0)  # (row, column) of the green square
        assert abs(green[0] - 15.5) < 2 and green[1] - 15.5 > 8, f"yaw {yaw}: the closing axis is not the columns"


def test_the_view_feeds_each_event_and_its_gradient_reaches_the_cnn():
    _, projection = overhead_camera(64)
    events = PlanEvents(replace(EVENTS, view=True, view_crop=16, view_window=0.1), KinematicChain.from_dict(PANDA), 16)
    plans = panda_plans(2, 12)
    events.fit(plans)
    views = torch.randint(0, 255, (2, 64, 64, 3), dtype=torch.uint8)
    out = events(plans, view=views, projection=projection.expand(2, 3, 4), augment=True)
    out.sum().backward()
    assert all(p.grad is not None for p in events.view.parameters())
    with pytest.raises(ValueError, match="plan-conditioned view"):
        events(plans)
    grid = crop_grid(projection.expand(2, 3, 4), torch.zeros(2, 3, 3), torch.eye(3).expand(2, 3, 3, 3), 0.1, 16, 64, 64)
    assert grid.shape == (6, 16, 16, 2)
