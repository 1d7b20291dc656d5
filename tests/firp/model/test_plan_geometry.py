"""The plan's grasp-frame description: forward kinematics, pick events, the description, its use in models."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from firp.core.contract import CATEGORY_INDEX, JOINT_LOWER, JOINT_UPPER, N_CATEGORIES
from firp.model.config import EncoderConfig, FIRPConfig, GeometryConfig, RSSMConfig
from firp.model.baselines import build_model
from firp.model.plan_geometry import PlanGeometry, geometry_dim, panda_tcp_pose, pick_events, plan_geometry, tcp_yaw
from planner_client.ik import PandaIK, rotation_yaw
from planner_client.tamp import PlannerConfig, TampPlanner
from planner_client.collect import plan_episode
from sim_worker.perception import PoseErrorConfig

ORDER = ("red", "green", "blue")


@pytest.fixture(scope="module")
def planned():
    planner = TampPlanner(PlannerConfig())
    return {task: [plan_episode(planner, task, seed, ORDER, PoseErrorConfig()) for seed in range(3)]
            for task in ("stacking", "replacement")}


def _actions(episodes) -> torch.Tensor:
    return torch.tensor(np.stack([np.asarray(e.plan.actions) for e in episodes]), dtype=torch.float64)


def test_forward_kinematics_matches_the_sims_panda():
    ik, rng = PandaIK(), np.random.default_rng(0)
    for _ in range(50):
        q = rng.uniform(JOINT_LOWER[:7], JOINT_UPPER[:7])
        pos, rot = ik.forward(q)
        pos_t, rot_t = panda_tcp_pose(torch.tensor(q, dtype=torch.float64))
        np.testing.assert_allclose(pos_t.numpy(), pos, atol=1e-9)
        np.testing.assert_allclose(rot_t.numpy(), rot, atol=1e-6)
        assert float(tcp_yaw(rot_t)) == pytest.approx(rotation_yaw(rot), abs=1e-6)


def test_forward_kinematics_reads_robosuites_panda_up_to_a_shift_along_the_tool():
    """robosuite's Panda (``tests/golden/robosuite_panda_grip_site.json``, checked against robosuite by
    ``tests/robosuite_worker/test_kinematics.py``): its grip site lies 6.9 mm short of the DH tool point,
    along the tool's axis, and its fingers close along the same line -- so the description, made of
    relative positions and yaws, reads robosuite's plans as it reads ours."""
    recorded = json.loads((Path(__file__).resolve().parents[2] / "golden" / "robosuite_panda_grip_site.json").read_text())
    pos, rot = panda_tcp_pose(torch.tensor(recorded["joints"], dtype=torch.float64))
    site_pos, site_rot = np.array(recorded["position"]), np.array(recorded["rotation"])
    offset, tool_axis = site_pos - pos.numpy(), rot.numpy()[..., 2]
    along = (offset * tool_axis).sum(-1)
    np.testing.assert_allclose(along, -0.0069, atol=2e-4)
    np.testing.assert_allclose(offset - along[:, None] * tool_axis, 0.0, atol=1e-6)
    closing = np.abs((site_rot[..., 0] * rot.numpy()[..., 1]).sum(-1))  # robosuite: site x; DH: tool y
    assert closing.min() > 0.9999
    site_yaw = np.arctan2(site_rot[:, 1, 0], site_rot[:, 0, 0])
    turn = (site_yaw - tcp_yaw(rot).numpy() + math.pi / 2) % math.pi - math.pi / 2  # the same axis, either sense
    np.testing.assert_allclose(turn, 0.0, atol=1e-3)


def test_forward_kinematics_batches_and_rejects_a_wrong_width():
    q = torch.zeros(2, 5, 7)
    pos, rot = panda_tcp_pose(q)
    assert pos.shape == (2, 5, 3) and rot.shape == (2, 5, 3, 3)
    with pytest.raises(ValueError, match="7 arm joints"):
        panda_tcp_pose(torch.zeros(3, 9))


def test_pick_events_recover_the_planners_grasps_and_places(planned):
    for task, episodes in planned.items():
        ev = pick_events(_actions(episodes))
        for b, ep in enumerate(episodes):
            moved = ep.order[1:] if task == "stacking" else ep.order
            assert ev["present"][b].tolist() == [True] * len(moved) + [False] * (3 - len(moved))
            for k, name in enumerate(moved):
                estimate = np.asarray(ep.observation["blocks"][name]["position"])
                np.testing.assert_allclose(ev["grasp_pos"][b, k, :2].numpy(), estimate[:2], atol=1e-3)
                assert float(ev["grasp_yaw"][b, k]) == pytest.approx(ep.plan.grasp_yaws[k], abs=2e-3)
                target = np.asarray(ep.plan.place_targets[k])
                np.testing.assert_allclose(ev["release_pos"][b, k].numpy(), target[:3], atol=1e-3)
            # absent picks are zeros
            assert torch.all(ev["grasp_pos"][b, len(moved):] == 0)


def _one_hot_plan(categories: list[str]) -> torch.Tensor:
    a = torch.zeros(1, len(categories), N_CATEGORIES + 9)
    for t, c in enumerate(categories):
        a[0, t, CATEGORY_INDEX[c]] = 1.0
    return a


def test_pick_events_pair_each_grasp_with_the_next_release_and_respect_the_mask():
    cats = ["move_before_grasp", "grasp", "grasp", "hold", "release", "release", "move_after_release",
            "grasp", "hold", "release", "move"]
    a = _one_hot_plan(cats)
    ev = pick_events(a, max_picks=3)
    assert ev["present"].tolist() == [[True, True, False]]
    # a mask that hides the second release leaves the second grasp without a release: not a pick
    mask = torch.ones(1, len(cats), dtype=torch.bool)
    mask[0, 9:] = False
    assert pick_events(a, mask, max_picks=3)["present"].tolist() == [[True, False, False]]


def test_description_is_invariant_to_turning_and_shifting_the_whole_scene_in_its_grasp_frame_parts():
    """Offsets in the grasp frame do not change when the robot turns about its base axis (joint 1)."""
    planner = TampPlanner(PlannerConfig())
    ep = plan_episode(planner, "stacking", 0, ORDER, PoseErrorConfig())
    a = _actions([ep])
    turned = a.clone()
    turned[..., N_CATEGORIES] += 0.3  # joint 1: the whole plan turned about the world z axis
    g, g_turned = plan_geometry(a), plan_geometry(turned)
    P = 3
    per_pick = geometry_dim(P) // P
    for k in range(2):  # the two picks of stacking
        row, row_t = g[0, k * per_pick:(k + 1) * per_pick], g_turned[0, k * per_pick:(k + 1) * per_pick]
        rel, rel_t = row[8:], row_t[8:]  # everything after presence, grasp xyz, release xyz, rise
        torch.testing.assert_close(rel, rel_t, atol=1e-9, rtol=0)
        # while the world positions do change
        assert not torch.allclose(row[1:4], row_t[1:4])


def test_description_by_hand_for_two_picks(monkeypatch):
    """Hand-made events: check one grasp-frame relation against numbers worked out on paper."""
    from firp.model import plan_geometry as pg

    grasp_pos = torch.tensor([[[0.5, 0.0, 0.02], [0.5, 0.1, 0.02], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    release_pos = torch.tensor([[[0.4, 0.0, 0.06], [0.4, 0.0, 0.10], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    events = {"grasp_pos": grasp_pos, "release_pos": release_pos,
              "grasp_yaw": torch.tensor([[math.pi / 2, 0.0, 0.0]], dtype=torch.float64),
              "release_yaw": torch.tensor([[0.1, 0.1, 0.0]], dtype=torch.float64),
              "present": torch.tensor([[True, True, False]])}
    monkeypatch.setattr(pg, "pick_events", lambda *args, **kw: events)
    g = pg.plan_geometry(torch.zeros(1, 8, 16, dtype=torch.float64))
    row = g[0, : geometry_dim() // 3]
    assert row[0] == 1.0  # present
    torch.testing.assert_close(row[1:4], grasp_pos[0, 0])
    assert float(row[7]) == pytest.approx(0.0)  # the first release rises 0 over itself
    # pick 1's grasp seen from pick 0's grasp, turned by 90 deg: world +y 0.1 -> frame x +0.1, y 0
    rel = row[8:16]
    assert rel[:2].tolist() == pytest.approx([0.1, 0.0], abs=1e-12)
    assert float(rel[4]) == pytest.approx(0.1)
    # relative yaw -90 deg: cos(4 * -pi/2) = 1, sin = 0; pick 1 is picked later: still there
    assert rel[5:].tolist() == pytest.approx([1.0, 0.0, 1.0], abs=1e-12)
    # the absent third pick contributes zeros
    assert torch.all(g[0, 2 * geometry_dim() // 3:] == 0)


def test_standardised_geometry_and_models_reading_it(planned):
    a = _actions(planned["stacking"] + planned["replacement"]).float()
    enc = PlanGeometry()
    enc.fit(a)
    z = enc(a)
    assert z.shape == (6, geometry_dim()) and torch.isfinite(z).all()
    varying = plan_geometry(a.double()).std(dim=0) > 1e-6
    assert torch.allclose(z[:, varying].mean(0), torch.zeros(int(varying.sum())), atol=1e-4)
    cfg = FIRPConfig(encoder=EncoderConfig(feature_dim=8, projection_hidden=0),
                     rssm=RSSMConfig(deter_dim=8, stoch_dim=4, hidden=8), geometry=GeometryConfig(enabled=True),
                     action_chunk=8)
    feats = torch.randn(6, a.shape[1], cfg.encoder.backbone_dim)
    for kind in ("firp", "a_mlp", "a_mlp_image", "gru"):
        model = build_model(kind, cfg)
        assert model.geometry is not None
        model.geometry.fit(a)
        model.forward_train(feats, a)["logits"].sum().backward()
        head_inputs = [p for n, p in model.named_parameters() if "context" in n or n.startswith("mlp.0")]
        assert head_inputs and all(p.grad is not None and p.grad.abs().sum() > 0 for p in head_inputs), kind
        # the description changes the score: move one block's grasp (joint 1 of the first grasp run)
        moved = a.clone()
        t = int((a[0, :, CATEGORY_INDEX["grasp"]] > 0).nonzero()[0])
        moved[0, t, N_CATEGORIES] += 0.05
        with torch.no_grad():
            s0 = model.score(feats[:, 0], a).logits
            s1 = model.score(feats[:, 0], moved).logits
        assert s0[0] != s1[0] and torch.equal(s0[1:], s1[1:]), kind


def test_geometry_is_off_by_default_and_old_configs_load():
    cfg = FIRPConfig()
    assert cfg.geometry.enabled is False
    assert build_model("firp", cfg).geometry is None
    d = cfg.to_dict()
    d.pop("geometry")  # a manifest written before the option existed
    assert FIRPConfig.from_dict(d) == cfg
    with pytest.raises(ValueError, match="max_picks"):
        GeometryConfig(max_picks=0)


def test_a_geometry_only_mlp_reads_the_description_and_nothing_else(planned):
    from firp.model.config import BaselineConfig

    with pytest.raises(ValueError, match="enable geometry"):
        build_model("a_mlp", FIRPConfig(baseline=BaselineConfig(plan_pooling="none")))
    cfg = FIRPConfig(baseline=BaselineConfig(plan_pooling="none"), geometry=GeometryConfig(enabled=True))
    model = build_model("a_mlp", cfg)
    assert model.mlp[0].in_features == geometry_dim()
    a = _actions(planned["stacking"]).float()
    model.geometry.fit(a)
    changed = a.clone()
    changed[:, :, -2:] = 0.01  # finger targets are not part of the description
    with torch.no_grad():
        assert torch.equal(model.score(None, a).logits, model.score(None, changed).logits)


def test_columns_constant_in_training_stay_unscaled_and_unseen_plans_stay_bounded(planned):
    """Fitted on stacking (two picks), scoring a replacement plan (three picks): the third pick's columns
    were constant (zero) in training -- they are not divided by a tiny std, and nothing exceeds the clip."""
    from firp.model.plan_geometry import STANDARD_CLIP

    enc = PlanGeometry()
    enc.fit(_actions(planned["stacking"]).float())
    per_pick = geometry_dim() // 3
    assert torch.all(enc.std[2 * per_pick:] == 1.0) and torch.all(enc.mean[2 * per_pick:] == 0.0)
    z = enc(_actions(planned["replacement"]).float())
    assert torch.all(z[:, 2 * per_pick] == 1.0)  # the third pick's presence flag: 1 - 0, unscaled
    assert z.abs().max() <= STANDARD_CLIP


# -- the hand's clearance ---------------------------------------------------------------------------------


def _clearance_of(x: float, y: float = 0.0, yaw: float = 0.0, opening: float = 0.04, half: float = 0.02):
    from firp.model.plan_geometry import hand_clearance

    block = torch.tensor([[[x, y]]], dtype=torch.float64)
    return hand_clearance(block, torch.tensor([[yaw]], dtype=torch.float64), torch.tensor([opening], dtype=torch.float64),
                          half)[0, 0].tolist()  # pad, finger, hand


def test_hand_clearance_by_hand():
    """Fingers open 4 cm: a pad covers x in [0.04, 0.0544], a finger [0.04, 0.0665], the hand's slab reaches 0.104."""
    from firp.model.plan_geometry import CLEARANCE_FAR, FINGER_BODY, FINGER_PAD, HAND_SLAB_HALF

    pad, finger, hand = _clearance_of(0.1)  # a 4 cm block whose near face is at 8 cm
    assert pad == pytest.approx(0.08 - (0.04 + FINGER_PAD[0]), abs=1e-9)
    assert finger == pytest.approx(0.08 - (0.04 + FINGER_BODY[0]), abs=1e-9)
    assert hand == pytest.approx(0.08 - HAND_SLAB_HALF[0], abs=1e-9)  # under the hand by 2.4 cm: negative
    assert _clearance_of(-0.1) == pytest.approx([pad, finger, hand], abs=1e-9)  # the other finger alike
    # turned by 45 degrees, its corner comes 2 * (sqrt(2) - 1) cm nearer
    corner = _clearance_of(0.1, yaw=math.pi / 4)
    assert corner[0] == pytest.approx(pad - 0.02 * (math.sqrt(2) - 1), abs=1e-9)
    assert _clearance_of(0.1, yaw=math.pi / 2) == pytest.approx([pad, finger, hand], abs=1e-9)  # a quarter turn: same
    # overlapping the pad, negative by the depth of the overlap: block x in [0.04, 0.08], pad x in [0.04, 0.0544]
    assert _clearance_of(0.06)[0] == pytest.approx(-FINGER_PAD[0], abs=1e-9)
    # beside the finger, across the closing axis: the gap in y
    assert _clearance_of(0.047, y=0.05)[1] == pytest.approx(0.05 - 0.02 - FINGER_BODY[1], abs=1e-9)
    # a wider opening clears more; far blocks are clipped
    assert _clearance_of(0.1, opening=0.03)[0] == pytest.approx(pad + 0.01, abs=1e-9)
    assert _clearance_of(1.0) == [CLEARANCE_FAR] * 3


def _inside(point: np.ndarray, polygon: np.ndarray) -> bool:
    """A point inside a convex counter-clockwise polygon (4, 2): left of every edge."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    to_point = point - polygon
    return bool(np.all(edges[:, 0] * to_point[:, 1] - edges[:, 1] * to_point[:, 0] >= 0))


@pytest.mark.slow
def test_signed_distance_agrees_with_dense_sampling():
    """Random turned rectangles: apart, the distance is the nearest pair of boundary points; overlapping,
    it is negative."""
    from firp.model.plan_geometry import _corners, _signed_distance

    rng = np.random.default_rng(0)
    n = 200
    centre = torch.tensor(rng.uniform(-0.05, 0.05, (n, 2, 2)))
    half = torch.tensor(rng.uniform(0.005, 0.03, (n, 2, 2)))
    yaw = torch.tensor(rng.uniform(-math.pi, math.pi, (n, 2)))
    rect = _corners(centre, half, yaw)  # (n, 2, 4, 2)
    d = _signed_distance(rect[:, 0], rect[:, 1]).numpy()
    s = np.linspace(0.0, 1.0, 400)[:, None]
    for i in range(n):
        pts = []
        for r in range(2):
            c = rect[i, r].numpy()
            pts.append(np.concatenate([c[j] + s * (c[(j + 1) % 4] - c[j]) for j in range(4)]))
        dense = np.sqrt(((pts[0][:, None, :] - pts[1][None, :, :]) ** 2).sum(-1)).min()
        if d[i] > 0:
            assert d[i] == pytest.approx(dense, abs=2e-4), i
        else:  # touching or overlapping: the boundaries meet, or one holds the other
            a, b = rect[i, 0].numpy(), rect[i, 1].numpy()
            assert dense < 2e-4 or _inside(a.mean(0), b) or _inside(b.mean(0), a), i
    assert (d < 0).sum() > 20 and (d > 0).sum() > 20  # both cases were drawn


def test_clearance_columns_read_the_plan(planned):
    from firp.model.plan_geometry import CLEARANCE_FAR, clearance_dim, hand_clearance

    a = _actions(planned["stacking"])
    plain = plan_geometry(a)
    both, only = plan_geometry(a, description="both"), plan_geometry(a, description="clearance")
    assert both.shape == (3, geometry_dim(description="both")) == (3, geometry_dim() + clearance_dim())
    assert only.shape == (3, geometry_dim(description="clearance")) == (3, 6 * 3)
    assert torch.equal(both[:, :geometry_dim()], plain) and torch.equal(both[:, geometry_dim():], only)
    assert torch.all(only <= CLEARANCE_FAR) and torch.isfinite(only).all()
    # pick 0's grasp, by hand: the nearer of the tower (the block under the first release point) and the
    # block picked second, still on the table
    ev = pick_events(a)
    c, s = torch.cos(ev["grasp_yaw"][:, 0]), torch.sin(ev["grasp_yaw"][:, 0])

    def in_grasp_frame(p):  # world xy (B, 2) -> pick 0's grasp frame, x along the closing axis
        d = p[:, :2] - ev["grasp_pos"][:, 0, :2]
        return torch.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], dim=-1)

    spots = torch.stack([in_grasp_frame(ev["release_pos"][:, 0]), in_grasp_frame(ev["grasp_pos"][:, 1])], dim=1)
    turns = torch.stack([ev["release_yaw"][:, 0], ev["grasp_yaw"][:, 1]], dim=1) - ev["grasp_yaw"][:, :1]
    nearest = hand_clearance(spots, turns, ev["grasp_open"][:, 0], 0.02).min(dim=1).values  # (B, 3)
    torch.testing.assert_close(only[:, :3], nearest)
    assert torch.all(ev["grasp_open"][:, :2] > 0.03)  # the fingers stand open before each grasp
    # pick 1 (the last of stacking) releases with no block left on the table: far; the absent pick 2: zeros
    assert torch.all(only[:, 9:12] == CLEARANCE_FAR) and torch.all(only[:, 12:] == 0)


def test_clearance_and_heights_columns(planned):
    from firp.model.plan_geometry import PICK_HEIGHTS, clearance_dim

    a = _actions(planned["stacking"])
    only = plan_geometry(a, description="clearance")
    with_heights = plan_geometry(a, description="clearance_and_heights")
    P = 3
    assert with_heights.shape == (3, geometry_dim(description="clearance_and_heights")) == (3, clearance_dim() + 3 * P)
    assert torch.equal(with_heights[:, :clearance_dim()], only)
    heights = with_heights[:, clearance_dim():].reshape(3, P, len(PICK_HEIGHTS))
    ev = pick_events(a)
    torch.testing.assert_close(heights[:, :2, 0], ev["grasp_pos"][:, :2, 2])  # where each grasp closes
    torch.testing.assert_close(heights[:, :2, 1], ev["release_pos"][:, :2, 2])  # where each release opens
    assert torch.all(heights[:, 0, 2] == 0)  # the first release rises over itself by nothing
    # stacking's second release goes on top of the first block: it rises by about a block
    assert torch.all((heights[:, 1, 2] > 0.02) & (heights[:, 1, 2] < 0.1))
    assert torch.all(heights[:, 2] == 0)  # the absent third pick: zeros, as its clearance


def test_plan_description_config_flags_and_models(capsys):
    import argparse

    from firp.flags import add_model_flags, add_training_flags, recipe_flags, recipe_from

    with pytest.raises(ValueError, match="--plan-description: 'nearest' is none of"):
        GeometryConfig(enabled=True, description="nearest")
    with pytest.raises(ValueError, match="object_half"):
        GeometryConfig(enabled=True, object_half=0.0)
    parser = argparse.ArgumentParser()
    add_training_flags(parser)
    add_model_flags(parser)
    config, overrides = recipe_from(parser.parse_args(["--data", "x", "--plan-description", "clearance"]))
    assert config.model.geometry.enabled and config.model.geometry.description == "clearance"
    assert recipe_flags("product", overrides) == "--preset product --plan-description clearance"
    contradicting = parser.parse_args(["--data", "x", "--plan-description", "both", "--no-plan-geometry"])
    with pytest.raises(ValueError, match="drop one of the two"):
        recipe_from(contradicting)
    with pytest.raises(SystemExit):  # with the parser: its CLI error
        recipe_from(contradicting, parser)
    assert "--plan-description: the recipe leaves the plan's description out" in capsys.readouterr().err
    cfg = FIRPConfig(encoder=EncoderConfig(feature_dim=8, projection_hidden=0),
                     rssm=RSSMConfig(deter_dim=8, stoch_dim=4, hidden=8),
                     geometry=GeometryConfig(enabled=True, description="clearance"), action_chunk=8)
    assert FIRPConfig.from_dict(cfg.to_dict()) == cfg
    for kind in ("firp", "a_mlp"):
        assert build_model(kind, cfg).geometry.dim == geometry_dim(description="clearance")
    config, overrides = recipe_from(parser.parse_args(["--data", "x", "--plan-description", "clearance_and_heights"]))
    assert config.model.geometry.description == "clearance_and_heights"
    assert build_model("gru", config.model).geometry.dim == geometry_dim(description="clearance_and_heights") == 27


def test_block_halves_read_the_tower_under_each_release(planned):
    from firp.model.plan_geometry import block_halves

    a = _actions(planned["stacking"])
    ev = pick_events(a)
    halves = block_halves(ev, 0.02)  # (B, 1 + P): the base, then each pick's block
    assert halves.shape == (3, 4)
    tower = ev["release_pos"][:, :2, 2] - ev["grasp_pos"][:, :2, 2]  # the tower's height under each release
    torch.testing.assert_close(halves[:, 0], tower[:, 0] / 2)
    torch.testing.assert_close(halves[:, 1], (tower[:, 1] - tower[:, 0]) / 2)
    # the sim's blocks: 4 cm cubes (the release gap adds its half to the base; the next step cancels it)
    assert torch.all((halves[:, 0] > 0.019) & (halves[:, 0] < 0.03))
    torch.testing.assert_close(halves[:, 1], torch.full((3,), 0.02, dtype=torch.float64), atol=3e-3, rtol=0)
    # the last block stacked (nothing goes on it) and the absent third pick: the assumed size
    assert torch.all(halves[:, 2:] == 0.02)


def test_sized_clearance_is_the_clearance_to_blocks_of_those_sizes(planned):
    a = _actions(planned["stacking"])
    one_size = plan_geometry(a, description="clearance_and_heights")
    sized = plan_geometry(a, description="sized_clearance_and_heights")
    assert sized.shape == one_size.shape == (3, geometry_dim(description="sized_clearance_and_heights")) == (3, 27)
    assert torch.equal(sized[:, 18:], one_size[:, 18:])  # the heights are the same numbers
    # given every block the assumed size, the sized clearance is the one-size clearance exactly
    same = torch.full((3, 4), 0.02, dtype=torch.float64)
    assert torch.equal(plan_geometry(a, description="sized_clearance_and_heights", halves=same), one_size)
    # a wider tower base and a wider block left on the table come nearer the hand: no clearance grows, and the
    # second pick's grasp (beside the tower) comes 5 mm nearer wherever the tower is the nearest block in reach
    wider = same.clone()
    wider[:, 0] = 0.025
    wider[:, 2] = 0.025
    near = plan_geometry(a, description="sized_clearance_and_heights", halves=wider)
    assert torch.all(near[:, :18] <= one_size[:, :18] + 1e-12)
    assert torch.any(near[:, 6:9] < one_size[:, 6:9] - 1e-3)
    with pytest.raises(ValueError, match="halves: only with sized_clearance_and_heights"):
        plan_geometry(a, description="clearance_and_heights", halves=same)
    with pytest.raises(ValueError, match=r"halves: .*\(3, 4\)"):
        plan_geometry(a, description="sized_clearance_and_heights", halves=same[:, :3])


def test_sized_clearance_flag_builds_models_of_its_width():
    import argparse

    from firp.flags import add_model_flags, add_training_flags, recipe_from

    parser = argparse.ArgumentParser()
    add_training_flags(parser)
    add_model_flags(parser)
    config, _ = recipe_from(parser.parse_args(["--data", "x", "--plan-description", "sized_clearance_and_heights"]))
    assert config.model.geometry.enabled and config.model.geometry.description == "sized_clearance_and_heights"
    model = build_model("firp", config.model)
    assert model.geometry.dim == 27
    plans = torch.zeros(2, 16, 16)
    assert model.geometry(plans).shape == (2, 27)
    assert type(model.head.context).__name__ == "Sequential"  # two layers, as shipped
    config, overrides = recipe_from(parser.parse_args(["--data", "x", "--plan-description", "sized_clearance_and_heights",
                                                       "--description-layers", "1"]))
    assert overrides == {"plan_description": "sized_clearance_and_heights", "description_layers": 1}
    for kind in ("firp", "gru"):  # both read it through their success head: one ReLU layer
        head = build_model(kind, config.model).head
        assert isinstance(head.context, torch.nn.Linear) and head.context.in_features == 27
    assert FIRPConfig.from_dict(config.model.to_dict()) == config.model
    with pytest.raises(ValueError, match="--description-layers: the heads read the description through 1 or 2"):
        GeometryConfig(enabled=True, layers=3)
    with pytest.raises(SystemExit):
        parser.parse_args(["--data", "x", "--description-layers", "3"])


def test_description_weight_flag_sets_the_loss_and_needs_the_description():
    import argparse

    from firp.flags import add_loss_flags, add_model_flags, add_training_flags, recipe_flags, recipe_from

    parser = argparse.ArgumentParser()
    add_training_flags(parser)
    add_model_flags(parser)
    add_loss_flags(parser)
    config, overrides = recipe_from(parser.parse_args(["--data", "x", "--description-weight", "1"]))
    assert config.model.loss.description == 1.0 and overrides == {"description_weight": 1.0}
    assert recipe_flags("product", overrides) == "--preset product --description-weight 1.0"
    assert build_model("firp", config.model).cfg.loss.description == 1.0
    assert FIRPConfig.from_dict(config.model.to_dict()) == config.model
    config, _ = recipe_from(parser.parse_args(["--data", "x"]))
    assert config.model.loss.description == 0.0  # off as shipped
    with pytest.raises(ValueError, match="--description-weight: the recipe leaves the plan's description out"):
        recipe_from(parser.parse_args(["--data", "x", "--no-plan-geometry", "--description-weight", "1"]))
    with pytest.raises(SystemExit):
        parser.parse_args(["--data", "x", "--description-weight", "-1"])


def _events(grasp_z: list[list[float]], tower: list[list[float]], present: list[list[bool]]) -> dict:
    """Pick events with only the heights set: grasps at ``grasp_z``, releases ``tower`` above them."""
    g = torch.zeros(len(grasp_z), len(grasp_z[0]), 3, dtype=torch.float64)
    g[..., 2] = torch.tensor(grasp_z, dtype=torch.float64)
    r = g.clone()
    r[..., 2] += torch.tensor(tower, dtype=torch.float64)
    return {"grasp_pos": g, "release_pos": r, "present": torch.tensor(present)}


def test_grasp_halves_read_each_picked_block_from_its_grasp_over_the_table():
    from firp.model.plan_geometry import HIGH_GRASP_BELOW_TOP, TABLE_Z, block_halves, grasp_halves

    # a centre grasp on a 2.5 cm cube, a high grasp on a 2 cm one, a high grasp on a 2.5 cm one; then a centre
    # grasp on a 2 cm cube and an absent pick
    z = [[TABLE_Z + 0.025, TABLE_Z + 2 * 0.02 - HIGH_GRASP_BELOW_TOP, TABLE_Z + 2 * 0.025 - HIGH_GRASP_BELOW_TOP],
         [TABLE_Z + 0.0205, TABLE_Z + 0.03, 0.0]]
    ev = _events(z, [[0.045, 0.09, 0.13], [0.05, 0.09, 0.0]], [[True, True, True], [True, True, False]])
    halves = grasp_halves(ev, 0.02)
    shown = block_halves(ev, 0.02)
    assert halves.shape == (2, 4)
    torch.testing.assert_close(halves[:, 0], shown[:, 0])  # the base is never grasped: its release shows it
    torch.testing.assert_close(halves[0, 1:], torch.tensor([0.025, 0.02, 0.025], dtype=torch.float64))
    torch.testing.assert_close(halves[1, 1:3], torch.tensor([0.0205, 0.019], dtype=torch.float64))
    assert halves[1, 3] == shown[1, 3] == 0.02  # an absent pick: the assumed size


def test_the_table_sized_clearance_reads_robosuites_stacking_plans_to_their_cubes_sizes():
    """Four plans of robosuite's three-cube stacking (``tests/golden/robosuite_stack_three_plans.json``, from the
    collected set: the 5 cm cube last, grasped at its centre and high; first; as the base): every picked cube's
    size decoded from the plan alone within the planner's 1 mm height estimate error, where the tower's steps
    (``block_halves``) leave the last one at the assumed 4 cm."""
    from firp.model.plan_geometry import block_halves, grasp_halves

    recorded = json.loads((Path(__file__).resolve().parents[2] / "golden" / "robosuite_stack_three_plans.json").read_text())
    a = torch.tensor(recorded["actions"], dtype=torch.float64)
    true = torch.tensor(recorded["halves"], dtype=torch.float64)  # (4, 3): base, first pick, second pick
    ev = pick_events(a)
    decoded, shown = grasp_halves(ev, 0.02), block_halves(ev, 0.02)
    torch.testing.assert_close(decoded[:, 1:3], true[:, 1:3], atol=2.5e-3, rtol=0)
    assert torch.all((shown[:2, 2] - true[:2, 2]).abs() > 4e-3)  # the 5 cm cube stacked last: not in the steps
    table = plan_geometry(a, description="table_sized_clearance_and_heights")
    sized = plan_geometry(a, description="sized_clearance_and_heights")
    assert table.shape == sized.shape == (4, geometry_dim(description="table_sized_clearance_and_heights")) == (4, 27)
    assert torch.equal(table[:, 18:], sized[:, 18:])  # the heights are the same numbers; the clearance is not
    assert not torch.equal(table[:, :18], sized[:, :18])
    # within millimetres of the clearance to the true sizes (the base reads 2.5 mm wide: half the release gap)
    truly = torch.cat([true, torch.full((4, 1), 0.02, dtype=torch.float64)], dim=1)
    torch.testing.assert_close(table, plan_geometry(a, description="table_sized_clearance_and_heights",
                                                    halves=truly), atol=5e-3, rtol=0)
