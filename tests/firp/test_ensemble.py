"""EnsembleScorer: equals the members scored one by one, runs the backbone once, checks plans."""

import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch

from firp.bundle import BundleMember, load_bundle
from firp.core.contract import PlanValidationError
from firp.ensemble import AUTO_VMAP_MAX_N, EnsembleResult, EnsembleScorer, _GRUCellOps
from firp.model import build_model
from firp.model.encoder import ImageEncoder

from .bundle_helpers import T_RANGE, export_tiny, random_image, tiny_backbone, tiny_members, valid_plans
from .model.helpers import TINY


@pytest.fixture
def exported(tmp_path):
    """(members, backbone, bundle) of a 3-member FIRP ensemble, before and after the round trip."""
    members, backbone = tiny_members(), tiny_backbone()
    return members, backbone, load_bundle(export_tiny(tmp_path / "b", members, backbone))


def _direct(members, backbone, image, plans):
    """Reference: the original (never exported) models, one by one, with the original backbone."""
    encoder = ImageEncoder(TINY.encoder, backbone=backbone)
    with torch.no_grad():
        feats = encoder.backbone_features(image[None]).expand(len(plans), -1)
        actions = torch.from_numpy(plans).float()
        scores = [m.model.score(feats, actions) for m in members]
    probs = torch.stack([torch.sigmoid(s.logits) for s in scores]).double().numpy()
    weights = torch.stack([s.weights for s in scores]).double().mean(0).numpy()
    return probs, weights


@pytest.mark.parametrize("strategy", ["auto", "loop", "vmap"])
def test_scores_equal_the_original_members_after_the_round_trip(exported, strategy):
    members, backbone, bundle = exported
    image, plans = random_image(), valid_plans(4, 12)
    result = EnsembleScorer(bundle, strategy=strategy).score(image, plans)
    probs, weights = _direct(members, backbone, image, plans)
    assert isinstance(result, EnsembleResult)
    assert result.member_probabilities.shape == (3, 4)
    np.testing.assert_allclose(result.member_probabilities, probs, atol=1e-6)
    np.testing.assert_allclose(result.probabilities, probs.mean(0), atol=1e-6)
    np.testing.assert_allclose(result.spread, probs.std(0), atol=1e-6)
    np.testing.assert_allclose(result.weights, weights, atol=1e-6)
    np.testing.assert_allclose(result.weights.sum(1), 1.0, atol=1e-6)
    assert result.success.dtype == bool
    np.testing.assert_array_equal(result.success, result.probabilities >= bundle.threshold)


def test_threshold_decides_success(exported):
    _, _, bundle = exported
    image, plans = random_image(), valid_plans(6, 10)
    probs = EnsembleScorer(bundle).score(image, plans).probabilities
    middle = float(np.sort(probs)[3])  # exactly at the threshold counts as success
    result = EnsembleScorer(dataclasses.replace(bundle, threshold=middle)).score(image, plans)
    assert result.threshold == middle
    np.testing.assert_array_equal(result.success, probs >= middle)
    assert result.success.sum() == 3


@pytest.mark.parametrize("n", [1, 5])
def test_vmap_equals_the_loop(tmp_path, n):
    # two vmapped groups (firp x2, a_mlp_image x2) and a GRU baseline that always runs in the loop
    members = tiny_members(("firp", "a_mlp_image", "firp", "gru", "a_mlp_image"))
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    image, plans = random_image(), valid_plans(n, 16)
    loop = EnsembleScorer(bundle, strategy="loop").score(image, plans)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "performance drop ... batching rule" fallback warning
        batched = EnsembleScorer(bundle, strategy="vmap").score(image, plans)
    np.testing.assert_allclose(batched.member_probabilities, loop.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(batched.probabilities, loop.probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(batched.weights, loop.weights, atol=1e-5, rtol=0)


def test_auto_strategy_switches_on_the_number_of_plans(exported):
    scorer = EnsembleScorer(exported[2])
    assert scorer.strategy == "auto"
    assert scorer.uses_vmap(1) and scorer.uses_vmap(AUTO_VMAP_MAX_N) and not scorer.uses_vmap(AUTO_VMAP_MAX_N + 1)
    assert not EnsembleScorer(exported[2], strategy="loop").uses_vmap(1)
    assert EnsembleScorer(exported[2], strategy="vmap").uses_vmap(100)


def test_members_without_attention_are_left_out_of_the_weights(tmp_path):
    bundle = load_bundle(export_tiny(tmp_path / "a", tiny_members(("a_mlp", "a_mlp_image"))))
    assert EnsembleScorer(bundle).score(random_image(), valid_plans(2, 9)).weights is None
    bundle = load_bundle(export_tiny(tmp_path / "b", tiny_members(("a_mlp", "firp"))))
    result = EnsembleScorer(bundle).score(random_image(), valid_plans(2, 9))
    assert result.weights.shape == (2, 9)
    np.testing.assert_allclose(result.weights.sum(1), 1.0, atol=1e-6)


def test_gru_cell_decomposition_equals_gru_cell():
    cell = torch.nn.GRUCell(5, 7)
    x, h = torch.randn(3, 5), torch.randn(3, 7)
    torch.testing.assert_close(_GRUCellOps(cell)(x, h), cell(x, h), atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("strategy", ["auto", "loop", "vmap"])
def test_the_image_goes_through_the_backbone_once(exported, strategy):
    _, _, bundle = exported
    scorer = EnsembleScorer(bundle, strategy=strategy)
    batches: list[int] = []
    handle = scorer.encoder.backbone.register_forward_hook(lambda mod, inp, out: batches.append(inp[0].shape[0]))
    try:
        scorer.score(random_image(), valid_plans(7, 10))
        assert batches == [1]  # one call, one image: not per plan (7), not per member (3)
        scorer.score(random_image(seed=1), valid_plans(2, 8))
        assert batches == [1, 1]
    finally:
        handle.remove()



def test_cached_features_score_like_the_image(exported):
    """score = score_features(image_features(image)): a caller may keep the features of a scene."""
    scorer = EnsembleScorer(exported[2])
    image, plans = random_image(seed=3), valid_plans(3, 9, seed=4)
    feats = scorer.image_features(image)
    assert feats.shape == (1, TINY.encoder.backbone_dim)
    direct, cached = scorer.score(image, plans), scorer.score_features(feats, plans)
    np.testing.assert_array_equal(direct.probabilities, cached.probabilities)
    np.testing.assert_array_equal(direct.weights, cached.weights)
    with pytest.raises(ValueError, match="features must be a"):
        scorer.score_features(feats.expand(2, -1), plans)
    with pytest.raises(PlanValidationError):
        scorer.score_features(feats, plans[:, :, :15])

def test_plans_of_different_lengths_in_separate_calls(exported):
    scorer = EnsembleScorer(exported[2])
    for t in T_RANGE:
        assert scorer.score(random_image(), valid_plans(2, t)).weights.shape == (2, t)


def test_plan_validation_errors_surface_unchanged(exported):
    scorer = EnsembleScorer(exported[2])
    image = random_image()
    plans = valid_plans(3, 10)
    bad = plans.copy()
    bad[2, 4, 9] = np.nan
    with pytest.raises(PlanValidationError) as info:
        scorer.score(image, bad)
    assert info.value.rule == "finite" and info.value.field == "plans[2][4][9]"
    bad = plans.copy()
    bad[1, 0, :7] = 0.0
    with pytest.raises(PlanValidationError) as info:
        scorer.score(image, bad)
    assert info.value.rule == "one_hot" and info.value.field == "plans[1][0]"
    with pytest.raises(PlanValidationError) as info:
        scorer.score(image, valid_plans(1, T_RANGE[1] + 1))  # longer than the bundle was trained on
    assert info.value.rule == "length" and info.value.field == "plans[0]"
    with pytest.raises(PlanValidationError) as info:
        scorer.score(image, plans[:, :, :15])
    assert info.value.rule == "width"
    with pytest.raises(PlanValidationError) as info:
        scorer.score(image, plans[0])  # one plan without the N axis
    assert info.value.rule == "shape"
    with pytest.raises(PlanValidationError):
        scorer.score(image, plans[:0])


def test_image_must_be_one_uint8_rgb_frame(exported):
    scorer = EnsembleScorer(exported[2])
    plans = valid_plans(1, 8)
    for image in (random_image().astype(np.float32), random_image()[None], random_image()[..., :2], [[1, 2, 3]]):
        with pytest.raises(ValueError, match="uint8"):
            scorer.score(image, plans)


def test_unknown_strategy(exported):
    with pytest.raises(ValueError, match="strategy"):
        EnsembleScorer(exported[2], strategy="threads")


def test_efficientnet_bundle_scores_like_its_members(tmp_path):
    from firp.bundle import BundleMember, export_bundle
    from firp.model import EncoderConfig, build_model

    cfg = dataclasses.replace(TINY, encoder=EncoderConfig(backbone="efficientnet_lite0", image_size=32, feature_dim=6,
                                                          projection_hidden=0))
    members = [BundleMember("firp", cfg, build_model("firp", cfg).eval()) for _ in range(2)]
    bundle = load_bundle(export_bundle(tmp_path / "b", members, name="e", task="stacking", threshold=0.5,
                                       calibration={"ece": 0.0, "n_val": 1}, metrics={}, training_data_hash="0",
                                       training_data_path="x", t_range=T_RANGE))
    image, plans = random_image(), valid_plans(2, 8)
    result = EnsembleScorer(bundle).score(image, plans)
    encoder = ImageEncoder(cfg.encoder)  # a fresh backbone from the pinned weights
    with torch.no_grad():
        feats = encoder.backbone_features(image[None]).expand(2, -1)
        probs = [torch.sigmoid(m.model.score(feats, torch.from_numpy(plans).float()).logits) for m in members]
    np.testing.assert_allclose(result.member_probabilities, torch.stack(probs).numpy(), atol=1e-5)


def test_chunked_members_score_the_same_batched_and_one_by_one(tmp_path):
    """Members with ``action_chunk`` > 1 (the shipped architecture) go through vmap unchanged."""
    cfg = dataclasses.replace(TINY, action_chunk=4)
    members = [BundleMember("firp", cfg, build_model("firp", cfg).eval(), {"balanced_accuracy": 0.6}) for _ in range(3)]
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    plans = valid_plans(3, 10)
    batched, looped = EnsembleScorer(bundle), EnsembleScorer(bundle, strategy="loop")
    assert batched.uses_vmap(3) and not looped.uses_vmap(3)
    a, b = batched.score(random_image(), plans), looped.score(random_image(), plans)
    np.testing.assert_allclose(a.probabilities, b.probabilities, atol=1e-6)
    assert a.weights.shape == (3, 10)
    np.testing.assert_allclose(a.weights.sum(axis=1), 1.0, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# the fused FIRP rollout
# ------------------------------------------------------------------------------------------------


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
    assert [type(runner).__name__ for _, runner in fused._small] == ["_FusedFIRP"]
    image, plans = random_image(seed=n), valid_plans(n, t, seed=t)
    a, b = fused.score(image, plans), loop.score(image, plans)
    np.testing.assert_allclose(a.member_probabilities, b.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.probabilities, b.probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.spread, b.spread, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-5, rtol=0)
    assert a.weights.shape == (n, t)
    np.testing.assert_array_equal(a.success, b.success)


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
    assert [idx for idx, _ in EnsembleScorer(bundle)._small] == [[0, 1, 2]]
    vmapped = EnsembleScorer(bundle, strategy="vmap")
    assert [(idx, type(g).__name__) for idx, g in vmapped._small] == [([0, 1, 2], "_VmappedGroup")]


@pytest.mark.parametrize("strategy", ["auto", "fused"])
@pytest.mark.parametrize("n", [1, 5, AUTO_VMAP_MAX_N + 1])
def test_every_member_kind_has_a_correct_path_next_to_fused_members(tmp_path, strategy, n):
    members = tiny_members(("firp", "a_mlp_image", "firp", "gru", "a_mlp_image", "a_mlp"))
    bundle = load_bundle(export_tiny(tmp_path / "b", members))
    image, plans = random_image(), valid_plans(n, 13)
    got = EnsembleScorer(bundle, strategy=strategy).score(image, plans)
    want = EnsembleScorer(bundle, strategy="loop").score(image, plans)
    np.testing.assert_allclose(got.member_probabilities, want.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.weights, want.weights, atol=1e-5, rtol=0)


@pytest.mark.parametrize("strategy", ["auto", "loop", "vmap"])
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


@pytest.mark.parametrize("strategy", ["auto", "fused", "vmap"])
@pytest.mark.parametrize("n", [1, 6, AUTO_VMAP_MAX_N + 1])
def test_plan_geometry_members_score_like_the_loop_on_every_path(tmp_path, strategy, n):
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
    scorer = EnsembleScorer(bundle, strategy=strategy)
    runners = {type(runner).__name__ for _, runner in scorer._small + scorer._large}
    assert ("_FusedFIRP" in runners) == (strategy != "vmap")
    image, plans = random_image(), valid_plans(n, 16, seed=3 + n)
    got, want = scorer.score(image, plans), EnsembleScorer(bundle, strategy="loop").score(image, plans)
    np.testing.assert_allclose(got.member_probabilities, want.member_probabilities, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.weights, want.weights, atol=1e-5, rtol=0)
    with torch.no_grad():
        enc = ImageEncoder(TINY.encoder, backbone=bundle.backbone)
        feats = enc.backbone_features(image[None]).expand(len(plans), -1)
        ref = torch.sigmoid(members[0].model.score(feats, torch.from_numpy(plans).float()).logits).numpy()
    np.testing.assert_allclose(got.member_probabilities[0], ref, atol=1e-5, rtol=0)
