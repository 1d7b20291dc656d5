"""EnsembleScorer: equals the members scored one by one, runs the backbone once, checks plans."""

import dataclasses

import numpy as np
import pytest
import torch

from firp.bundle import BundleMember, load_bundle
from firp.core.contract import PlanValidationError
from firp.serving import EnsembleResult, EnsembleScorer
from firp.model import build_model
from firp.model.encoder import ImageEncoder

from ..bundle_helpers import T_RANGE, export_tiny, random_image, tiny_members, valid_plans
from ..model.helpers import TINY


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


@pytest.mark.parametrize("strategy", ["fused", "loop"])
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


def test_members_without_attention_are_left_out_of_the_weights(tmp_path):
    bundle = load_bundle(export_tiny(tmp_path / "a", tiny_members(("a_mlp", "a_mlp_image"))))
    assert EnsembleScorer(bundle).score(random_image(), valid_plans(2, 9)).weights is None
    bundle = load_bundle(export_tiny(tmp_path / "b", tiny_members(("a_mlp", "firp"))))
    result = EnsembleScorer(bundle).score(random_image(), valid_plans(2, 9))
    assert result.weights.shape == (2, 9)
    np.testing.assert_allclose(result.weights.sum(1), 1.0, atol=1e-6)


@pytest.mark.parametrize("strategy", ["fused", "loop"])
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
    for wrong in ("threads", "vmap", "auto"):
        with pytest.raises(ValueError, match="strategy must be 'fused' or 'loop'"):
            EnsembleScorer(exported[2], strategy=wrong)


def test_efficientnet_bundle_scores_like_its_members(tmp_path):
    from firp.bundle import export_bundle
    from firp.model import EncoderConfig

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
