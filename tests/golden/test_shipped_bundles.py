"""The shipped bundles (``models/<task>``) against the figures committed for them.

* Scores: the threshold-replay records (``docs/results/replan_threshold_geometry``: every candidate
  of a scene planned, scored by the shipped stacking bundle and executed) are scored again for the
  first trials of both splits; each score must come back, so the candidates' ROC AUC does too, and
  the committed AUC must be the one its records give.
* Outcomes: those records' success flags are physics, not copies: the first trials' candidates are
  executed again.
* The fused serving path on the shipped configuration (EfficientNet-Lite0 at 84 px, eight plan steps
  per transition, the plan's grasp-frame description, attention temperature 0.05): equal to the
  members' own forward pass -- scores *and* attention -- with trained, peaked attention, so a path
  that attaches one plan's attention to another plan cannot pass.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from firp.bundle import load_bundle
from experiments import replan_threshold as replan
from firp.core.bundle_format import shipped_bundle_dir
from planner_client.loop import read_records
from planner_client.tamp import TampPlanner, block_orders
from sim_worker.worlds import TaskWorlds

from .conftest import RESULTS, read_json, read_jsonl

RESCORED_TRIALS = {"calibration": 20, "test": 50}  # every trial of the main job's seeds
EXECUTED_TRIALS = 3  # per split, every candidate
REPORT = "replan_threshold_stacking_geometry.json"



def _records(split: str) -> list[dict]:
    return read_jsonl(f"replan_threshold_geometry/stacking-{split}.jsonl")


def _auc(records: list[dict]) -> float:
    scores, success, model = replan.arrays(records, RESULTS)
    return replan.candidate_metrics(scores, success, model["threshold"])["roc_auc"]


#: the flags each shipped bundle was made with, on top of the product preset (see firp.presets)
SHIPPED_RECIPES = {"stacking": {}, "replacement": {"action_chunk": 4, "plan_geometry": False}, "stack_three": {}}


@pytest.mark.parametrize("task", sorted(SHIPPED_RECIPES))
def test_the_shipped_bundles_are_the_product_preset(task):
    """What ships is a named recipe, not a list of flags: every member's architecture is the product preset's
    (the loss weights are what the study tuned)."""
    import dataclasses

    from firp.model.config import FIRPConfig
    from firp.presets import PRESETS

    want = PRESETS["product"].with_overrides(**SHIPPED_RECIPES[task]).model
    manifest = json.loads((shipped_bundle_dir(task) / "manifest.json").read_text())
    for member in manifest["members"]:
        got = FIRPConfig.from_dict(member["config"])
        assert dataclasses.replace(got, loss=want.loss) == want


@pytest.mark.parametrize("split", ["calibration", "test"])
def test_the_committed_candidate_auc_is_the_one_its_records_give(split):
    committed = read_json(REPORT)["splits"][split]
    records = _records(split)
    assert len(records) == committed["trials"]
    assert _auc(records) == pytest.approx(committed["roc_auc"], abs=1e-12)


@pytest.mark.parametrize("split", ["calibration", "test"])
def test_the_shipped_bundle_scores_the_recorded_candidates_again(tmp_path, split):
    records = _records(split)
    first = records[:RESCORED_TRIALS[split]]
    source = tmp_path / f"stacking-{split}.jsonl"
    source.write_text("".join(json.dumps(r) + "\n" for r in first))
    out = tmp_path / "rescored" / source.name
    replan.rescore("stacking", split, source, shipped_bundle_dir("stacking"), out, progress=False)
    again = read_records(out)
    np.testing.assert_allclose([r["scores"] for r in again], [r["scores"] for r in first], atol=2e-6, rtol=0)
    np.testing.assert_allclose([r["spread"] for r in again], [r["spread"] for r in first], atol=2e-6, rtol=0)
    assert _auc(again) == pytest.approx(_auc(first), abs=1e-9)
    if len(first) == len(records):
        assert _auc(again) == pytest.approx(read_json(REPORT)["splits"][split]["roc_auc"], abs=1e-9)
    assert 0.8 < _auc(again) < 1.0  # the ranking the loop's gain rests on, not a degenerate one


@pytest.fixture(scope="module")
def worlds():
    w = TaskWorlds()
    yield w
    w.close()


@pytest.mark.parametrize("split", ["calibration", "test"])
def test_the_recorded_outcomes_are_what_the_simulator_gives(worlds, split):
    planner = TampPlanner()
    for record in _records(split)[:EXECUTED_TRIALS]:
        episode = worlds.begin("stacking", record["seed"])
        got = [bool(worlds.execute("stacking", episode.true_blocks,
                                   planner.plan("stacking", episode.observation, tuple(order)).actions).success)
               for order in record["orders"]]
        assert got == record["success"], record["trial"]


@pytest.fixture(scope="module")
def shipped_stacking():
    torch.set_num_threads(1)
    return load_bundle(shipped_bundle_dir("stacking"))


def _scene_and_candidates(worlds, seed: int) -> tuple[np.ndarray, np.ndarray]:
    episode = worlds.begin("stacking", seed)
    planner = TampPlanner()
    plans = np.stack([planner.plan("stacking", episode.observation, order).actions for order in block_orders()])
    return episode.image, plans


@pytest.mark.parametrize("seed", [100_000, 100_003])
def test_the_fused_path_on_the_shipped_configuration_equals_the_members_forward_pass(worlds, shipped_stacking, seed):
    from firp.serving import EnsembleScorer

    bundle = shipped_stacking
    cfg = bundle.configs[0]
    assert (cfg.encoder.backbone, cfg.encoder.image_size, cfg.action_chunk, cfg.head.temperature,
            cfg.geometry.enabled) == ("efficientnet_lite0", 84, 8, 0.05, True)
    image, plans = _scene_and_candidates(worlds, seed)
    fused = EnsembleScorer(bundle, strategy="fused")
    assert {type(runner).__name__ for _, runner in fused.units} == {"FusedFIRP"}
    got = fused.score(image, plans)
    with torch.inference_mode():  # the reference: each member's own forward pass, one by one
        feats = fused.encoder.backbone_features(image[None]).expand(len(plans), -1)
        scores = [m.score(feats, torch.from_numpy(plans).float()) for m in bundle.models]
    probs = torch.stack([torch.sigmoid(s.logits) for s in scores]).double().numpy()
    weights = torch.stack([s.weights for s in scores]).double().mean(0).numpy()
    np.testing.assert_allclose(got.member_probabilities, probs, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.weights, weights, atol=1e-5, rtol=0)
    # trained attention is peaked (uniform would be 1/120 per step) and differs between the plans
    assert weights.max(axis=1).min() > 10 / plans.shape[1]
    assert np.abs(weights - weights[[1, 2, 3, 4, 5, 0]]).max() > 0.05
    assert np.ptp(probs.mean(0)) > 0.3  # and the candidates' scores differ: a ranking, not a constant


def test_the_generic_bundle_is_the_generic_preset_on_the_world_s_own_chain():
    """``models/stacking_generic``: every member is the generic preset (the loss weights are the study's), reads the
    plan's events and no hand-built description, through the chain the world reads off its robot model."""
    import dataclasses
    from pathlib import Path

    from firp.model.config import FIRPConfig
    from firp.presets import PRESETS

    chain = json.loads((Path(__file__).parent / "panda_chain.json").read_text())
    want = PRESETS["generic"].train.model
    manifest = json.loads((Path(shipped_bundle_dir("stacking")).parent / "stacking_generic" / "manifest.json").read_text())
    for member in manifest["members"]:
        got = FIRPConfig.from_dict(member["config"])
        assert got.events.kinematics == chain and not got.geometry.enabled
        assert dataclasses.replace(got, loss=want.loss, events=dataclasses.replace(got.events, kinematics=None)) == want


@pytest.mark.parametrize("seed", [100_000, 100_003])
def test_the_generic_bundle_scores_the_main_job_s_candidates_as_recorded(worlds, seed):
    """Its fused path equals each member's own forward pass, and the scores of the main job's recorded candidates
    come back."""
    from pathlib import Path

    from firp.serving import EnsembleScorer

    bundle = load_bundle(Path(shipped_bundle_dir("stacking")).parent / "stacking_generic")
    image, plans = _scene_and_candidates(worlds, seed)
    fused = EnsembleScorer(bundle, strategy="fused")
    got = fused.score(image, plans)
    loop = EnsembleScorer(bundle, strategy="loop").score(image, plans)
    np.testing.assert_allclose(got.member_probabilities, loop.member_probabilities, atol=1e-5, rtol=0)
    record = next(r for r in read_jsonl("main_job/stacking-50-generic.jsonl") if r["seed"] == seed)
    recorded = {tuple(json.loads(k)): v for k, v in record["candidate_scores"].items()}
    for order, p in zip(block_orders(), got.probabilities):
        assert p == pytest.approx(recorded[tuple(order)], abs=2e-5), order
