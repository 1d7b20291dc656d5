"""The fused FIRP rollout (firp.serving.fused) equals the members' own forward pass, FIRP.score."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from firp.bundle import BundleMember, load_bundle
from firp.serving import EnsembleScorer
from firp.serving.fused import FusedFIRP
from firp.model import build_model
from firp.model.encoder import ImageEncoder

from ..bundle_helpers import export_tiny, random_image, tiny_members, valid_plans
from ..model.helpers import TINY


#: the shipped bundle's configuration on TINY's sizes: a sharp attention head (L = 0.05) and the plan's
#: grasp-frame description. Random members attend almost uniformly whatever L; the check with trained,
#: peaked attention that differs between plans runs on the shipped bundle (tests/golden).
SHIPPED_LIKE = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, temperature=0.05),
                                   geometry=dataclasses.replace(TINY.geometry, enabled=True))


def _firp_bundle(tmp_path, chunk: int, n_members: int = 3, losses: bool = False, base=TINY, fit_plans=None):
    """FIRP members of one architecture; ``losses``: each with other loss weights (as the shipped bundle)."""
    members = []
    for k in range(n_members):
        cfg = dataclasses.replace(base, action_chunk=chunk)
        if losses:
            cfg = dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, alpha=0.001 * (k + 1), overshooting=0.0))
        model = build_model("firp", cfg).eval()
        with torch.no_grad():  # non-trivial plan statistics, as a trained member has
            model.action_norm.mean[7:] = torch.randn(9) * 0.3
            model.action_norm.std[7:] = torch.rand(9) + 0.5
        if cfg.geometry.enabled:
            model.geometry.fit(torch.from_numpy(fit_plans).float())
        members.append(BundleMember("firp", cfg, model, {"balanced_accuracy": 0.6}))
    return load_bundle(export_tiny(tmp_path / f"b{chunk}-{losses}-{base.head.temperature}", members))


@pytest.mark.parametrize("chunk", [1, 4, 8])
@pytest.mark.parametrize("n", [1, 3])
@pytest.mark.parametrize("t", [8, 11, 16])  # 11: not a multiple of 4, the last chunk is padded
@pytest.mark.parametrize("base", [TINY, SHIPPED_LIKE], ids=["paper-head", "shipped-head"])
def test_fused_equals_the_loop(tmp_path, chunk, n, t, base):
    bundle = _firp_bundle(tmp_path, chunk, base=base, fit_plans=valid_plans(8, 16, seed=99))
    fused, loop = EnsembleScorer(bundle, strategy="fused"), EnsembleScorer(bundle, strategy="loop")
    assert fused.uses_fused and not loop.uses_fused
    assert [type(runner).__name__ for _, runner in fused.units] == ["FusedFIRP"]
    image, plans = random_image(seed=n), valid_plans(n, t, seed=t)
    a, b = fused.score(image, plans), loop.score(image, plans)
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.probabilities, b.probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.spread, b.spread, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-5, rtol=0)
    assert a.weights.shape == (n, t)
    np.testing.assert_array_equal(a.success, b.success)


def test_fused_members_reading_the_hands_clearance_equal_the_loop(tmp_path):
    """Members whose description is the hand's clearance (--plan-description clearance) fuse like the others."""
    base = dataclasses.replace(SHIPPED_LIKE, geometry=dataclasses.replace(SHIPPED_LIKE.geometry, description="clearance"))
    bundle = _firp_bundle(tmp_path, 4, base=base, fit_plans=valid_plans(8, 16, seed=99))
    fused, loop = EnsembleScorer(bundle, strategy="fused"), EnsembleScorer(bundle, strategy="loop")
    assert fused.uses_fused
    image, plans = random_image(seed=3), valid_plans(3, 16, seed=5)
    a, b = fused.score(image, plans), loop.score(image, plans)
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    from firp.serving.fused import FusedFIRP

    other = dataclasses.replace(SHIPPED_LIKE, action_chunk=4)
    models = [*bundle.models, build_model("firp", other).eval()]
    with pytest.raises(TypeError, match="describe the plan alike"):
        FusedFIRP(models)


def test_fused_members_reading_the_description_through_one_layer_equal_the_loop(tmp_path):
    """--description-layers 1 (the sized clearance read through one ReLU layer) fuses like two layers."""
    geometry = dataclasses.replace(SHIPPED_LIKE.geometry, description="sized_clearance_and_heights", layers=1)
    base = dataclasses.replace(SHIPPED_LIKE, geometry=geometry)
    bundle = _firp_bundle(tmp_path, 4, base=base, fit_plans=valid_plans(8, 16, seed=99))
    assert all(isinstance(m.head.context, torch.nn.Linear) for m in bundle.models)
    fused, loop = EnsembleScorer(bundle, strategy="fused"), EnsembleScorer(bundle, strategy="loop")
    assert fused.uses_fused
    image, plans = random_image(seed=4), valid_plans(3, 16, seed=6)
    a, b = fused.score(image, plans), loop.score(image, plans)
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-5, rtol=0)
    from firp.serving.fused import FusedFIRP

    two = dataclasses.replace(base, geometry=dataclasses.replace(geometry, layers=2))
    with pytest.raises(TypeError, match="as many layers"):
        FusedFIRP([*bundle.models, build_model("firp", dataclasses.replace(two, action_chunk=4)).eval()])


def test_fused_plans_shorter_than_one_chunk(tmp_path):
    """T <= k: one transition, no prior steps; the head reads e_1 alone (weights all on step 0)."""
    cfg = dataclasses.replace(TINY, action_chunk=8)
    members = [BundleMember("firp", cfg, build_model("firp", cfg).eval()) for _ in range(2)]
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    a = EnsembleScorer(bundle, strategy="fused").score(random_image(), valid_plans(2, 8))
    b = EnsembleScorer(bundle, strategy="loop").score(random_image(), valid_plans(2, 8))
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-6)


def test_members_differing_only_in_loss_weights_are_batched(tmp_path):
    """The loss weights shape training, not the computation: such members form one group."""
    bundle = _firp_bundle(tmp_path, 4, losses=True)
    assert len({json.dumps(c.loss.__dict__, sort_keys=True) for c in bundle.configs}) == 3
    assert [idx for idx, _ in EnsembleScorer(bundle).units] == [[0, 1, 2]]
    assert [idx for idx, _ in EnsembleScorer(bundle, strategy="loop").units] == [[0], [1], [2]]


@pytest.mark.parametrize("n", [1, 5, 9])
def test_every_member_kind_has_a_correct_path_next_to_fused_members(tmp_path, n):
    members = tiny_members(("firp", "a_mlp_image", "firp", "gru", "a_mlp_image", "a_mlp"))
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    image, plans = random_image(), valid_plans(n, 13)
    got = EnsembleScorer(bundle).score(image, plans)
    want = EnsembleScorer(bundle, strategy="loop").score(image, plans)
    np.testing.assert_allclose(got.member_probabilities, want.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.weights, want.weights, atol=1e-5, rtol=0)


@pytest.mark.parametrize("strategy", ["fused", "loop"])
def test_one_scene_per_plan(exported, strategy):
    """features (N, Db), row i the scene of plan i: each plan scores as with its own image."""
    scorer = EnsembleScorer(exported[2], strategy=strategy)
    images, plans = [random_image(seed=s) for s in range(3)], valid_plans(3, 10, seed=7)
    feats = torch.cat([scorer.image_features(im) for im in images])
    together = scorer.score_features(feats, plans)
    for i, image in enumerate(images):
        alone = scorer.score(image, plans[i: i + 1])
        np.testing.assert_allclose(together.member_probabilities[:, i], alone.member_probabilities[:, 0], atol=1e-6)
        np.testing.assert_allclose(together.weights[i], alone.weights[0], atol=1e-6)


def test_fused_scoring_is_safe_from_several_threads(tmp_path):
    """The fused runner holds plain tensors only (no parameters swapped in and out)."""
    from concurrent.futures import ThreadPoolExecutor

    bundle = _firp_bundle(tmp_path, 4)
    scorer = EnsembleScorer(bundle)
    image, plans = random_image(), [valid_plans(2, 12, seed=s) for s in range(8)]
    alone = [scorer.score(image, p).probabilities for p in plans]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda p: scorer.score(image, p).probabilities, plans))
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a, b)


def test_the_fused_scene_cache_matches_by_value(tmp_path):
    """A scene's projections are reused only for features of equal value, never for stale ones."""
    bundle = _firp_bundle(tmp_path, 4)
    fused, loop = EnsembleScorer(bundle), EnsembleScorer(bundle, strategy="loop")
    plans = valid_plans(2, 12)
    feats = fused.image_features(random_image(seed=1))
    first = fused.score_features(feats, plans)
    again = fused.score_features(feats.clone(), plans)  # another tensor, same values: the cached projection
    np.testing.assert_array_equal(first.member_probabilities, again.member_probabilities)
    with torch.inference_mode():
        feats.add_(0.5)  # changed in place: must not be served from the cache
    changed = fused.score_features(feats, plans)
    np.testing.assert_allclose(changed.member_probabilities, loop.score_features(feats, plans).member_probabilities,
                               atol=1e-5, rtol=0)
    assert np.abs(changed.member_probabilities - first.member_probabilities).max() > 1e-4
    for seed in range(2, 8):  # more scenes than the cache holds: still right
        f = fused.image_features(random_image(seed=seed))
        np.testing.assert_allclose(fused.score_features(f, plans).probabilities,
                                   loop.score_features(f, plans).probabilities, atol=1e-5, rtol=0)


@pytest.mark.parametrize("n", [1, 6, 9])
def test_plan_geometry_members_score_like_the_loop_on_every_path(tmp_path, n):
    """Members reading the plan's grasp-frame description keep their fitted statistics through the
    bundle and score the same on every path, the fused one included (it adds the head's context)."""
    cfg = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, enabled=True))
    plans = valid_plans(6, 16, seed=3)
    members = []
    for kind in ("firp", "firp", "a_mlp_image"):
        model = build_model(kind, cfg).eval()
        model.geometry.fit(torch.from_numpy(plans).float())
        members.append(BundleMember(kind, cfg, model, {"balanced_accuracy": 0.6}))
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    assert torch.equal(bundle.models[0].geometry.std, members[0].model.geometry.std)
    scorer = EnsembleScorer(bundle)
    assert {type(runner).__name__ for _, runner in scorer.units} == {"FusedFIRP", "NoneType"}
    image, plans = random_image(), valid_plans(n, 16, seed=3 + n)
    got, want = scorer.score(image, plans), EnsembleScorer(bundle, strategy="loop").score(image, plans)
    np.testing.assert_allclose(got.member_probabilities, want.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.weights, want.weights, atol=1e-5, rtol=0)
    with torch.no_grad():
        enc = ImageEncoder(TINY.encoder, backbone=bundle.backbone)
        feats = enc.backbone_features(image[None]).expand(len(plans), -1)
        ref = torch.sigmoid(members[0].model.score(feats, torch.from_numpy(plans).float()).logits).numpy()
    np.testing.assert_allclose(got.member_probabilities[0], ref, atol=1e-5, rtol=0)


def test_fused_members_reading_the_plan_s_events_equal_the_loop(tmp_path):
    """The generic preset's members: each reads the plan's events through its own relation network."""
    from ..model.test_plan_events import EVENTS

    base = dataclasses.replace(SHIPPED_LIKE, geometry=TINY.geometry, events=EVENTS)
    members = []
    for k in range(3):
        model = build_model("firp", dataclasses.replace(base, action_chunk=4)).eval()
        model.geometry.fit(torch.from_numpy(valid_plans(8, 16, seed=99)).float())
        members.append(BundleMember("firp", model.cfg, model, {"balanced_accuracy": 0.6}))
    bundle = load_bundle(export_tiny(tmp_path / "events", members))
    assert bundle.configs[0].events.kinematics == EVENTS.kinematics  # the chain travels in the manifest
    fused, loop = EnsembleScorer(bundle, strategy="fused"), EnsembleScorer(bundle, strategy="loop")
    image, plans = random_image(seed=4), valid_plans(5, 16, seed=3)
    a, b = fused.score(image, plans), loop.score(image, plans)
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-5, rtol=0)
    assert [type(u) for _, u in fused.units] == [FusedFIRP]  # one chain and event count: fused, poses computed once
    longer = dataclasses.replace(base, action_chunk=4, events=dataclasses.replace(EVENTS, max_events=EVENTS.max_events + 1))
    other = build_model("firp", longer).eval()
    assert not members[0].model.geometry.reads_like(other.geometry)
    with pytest.raises(TypeError, match="events alike"):
        FusedFIRP([members[0].model, other])
