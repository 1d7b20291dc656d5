"""The service's model layer: failure step, feature cache, warm-up, bundle version."""

from __future__ import annotations

import numpy as np
import pytest

from firp.core.contract import validate_plan
from service.scorer import FeatureCache, ServiceModel, failure_steps, neutral_plan
from tests.firp.bundle_helpers import export_tiny


def test_failure_step_is_the_argmax_of_attention_for_predicted_failures_only():
    att = [np.array([0.1, 0.6, 0.3]), np.array([0.5, 0.2, 0.3]), np.array([0.2, 0.4, 0.4]), None]
    assert failure_steps(att, [False, True, False, False]) == [1, None, 1, None]  # ties: the earliest step


def test_feature_cache_is_a_bounded_lru():
    cache = FeatureCache(2)
    cache.put(b"a", "A")
    cache.put(b"b", "B")
    assert cache.get(b"a") == "A"  # a is now the most recent
    cache.put(b"c", "C")  # evicts b
    assert cache.get(b"b") is None and cache.get(b"a") == "A" and cache.get(b"c") == "C" and len(cache) == 2
    off = FeatureCache(0)
    off.put(b"a", "A")
    assert off.get(b"a") is None and len(off) == 0


@pytest.mark.parametrize("t", [8, 120, 400])
def test_the_warm_up_plan_is_contract_valid(t):
    assert validate_plan(neutral_plan(t)).shape == (t, 16)


def test_warm_up_refuses_a_bundle_that_scores_nan(tiny_bundle, monkeypatch):
    model = ServiceModel.load(tiny_bundle)
    assert model.warm_up() > 0
    real = model.scorer.score_features

    def nan_scores(features, plans):
        result = real(features, plans)
        result.probabilities[:] = np.nan
        return result

    monkeypatch.setattr(model.scorer, "score_features", nan_scores)
    with pytest.raises(RuntimeError, match="non-finite"):
        model.warm_up()


def test_version_is_the_manifest_digest_unless_the_bundle_names_one(tmp_path, tiny_bundle):
    model = ServiceModel.load(tiny_bundle)
    assert model.version == model.digest[:12] and len(model.digest) == 64
    named = ServiceModel.load(export_tiny(tmp_path / "named", extra={"version": "2026.11.1"}))
    assert named.version == "2026.11.1"


def test_mixed_lengths_keep_request_order(tiny_bundle):
    from tests.firp.bundle_helpers import random_image, valid_plans

    model = ServiceModel.load(tiny_bundle)
    plans = [valid_plans(1, 8, seed=1)[0], valid_plans(1, 12, seed=2)[0], valid_plans(1, 8, seed=3)[0]]
    image = random_image()
    mixed = model.score(b"k", lambda: image, plans)
    for i, p in enumerate(plans):
        alone = model.scorer.score(image, p[None])
        assert mixed.probabilities[i] == pytest.approx(alone.probabilities[0], abs=1e-6)  # float32 members: batch composition moves the last bits
        assert mixed.attention[i].shape == (len(p),)
    assert mixed.member_probabilities.shape == (3, 3)


def test_a_dropped_model_leaves_no_cyclic_garbage(tiny_bundle):
    """The service freezes every object alive after start-up out of the garbage collector's sight
    (service.app.freeze_startup_objects), so a bundle swapped out must be freed by reference counting
    alone: anything it left for the cyclic collector would stay, frozen, for the process's life."""
    import gc
    import weakref

    model = ServiceModel.load(tiny_bundle)
    model.warm_up()
    model.score(b"k", lambda: np.zeros((40, 40, 3), np.uint8), [neutral_plan(10)])
    gone = weakref.ref(model)
    gc.collect()  # what loading and scoring left behind, before the drop
    del model
    assert gone() is None  # freed at once, by reference counting
    assert gc.collect() == 0  # and nothing of it waits for the cyclic collector
