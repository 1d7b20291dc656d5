"""What would the replanning loop gain from a scorer that reads the plan in each grasp's frame?

``experiments/outcome_predictability.py`` found that gradient boosting on the plan's geometry in each
grasp's frame (``grasp_frame_plan``: no privileged information) predicts stacking outcomes far
better than any learned model here. This script puts that classifier in the loop's place, with no
information the main job does not have:

1. train it on ``collect``'s episodes 0..N-1 (the cached, re-simulated labels of
   ``outcome_predictability.py --simulate TASK:N``);
2. score every candidate plan of the calibration seeds (200000+) and the main job's seeds (100000+)
   recorded by ``experiments/replan_threshold.py`` (whose records hold each candidate's real outcome);
3. replay the loop's rule (first candidate scoring at least the threshold, else the last) with the
   threshold that maximises success on the calibration seeds, and report it on the main job's seeds
   beside the shipped FIRP bundle's results on the same candidates.

    MUJOCO_GL=egl .venv/bin/python -m experiments.grasp_frame_scorer --task stacking --train-episodes 640
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from sklearn.ensemble import GradientBoostingClassifier

from experiments import outcome_predictability, replan_threshold


def candidate_attrs(task: str, seed: int, orders: list[list[str]]) -> list[dict]:
    """The attrs ``collect`` would record for each candidate plan of ``seed`` (no execution)."""
    from planner_client.tamp import PlannerConfig, TampPlanner
    from planner_client.collect import plan_episode
    from sim_worker.perception import PoseErrorConfig

    planner = TampPlanner(PlannerConfig())
    return [plan_episode(planner, task, seed, tuple(order), PoseErrorConfig()).attrs() for order in orders]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="stacking", choices=["stacking", "replacement"])
    parser.add_argument("--train-episodes", type=int, default=640)
    parser.add_argument("--records", type=Path, default=Path("docs/results/replan_threshold"),
                        help="folder with <task>-calibration.jsonl and <task>-test.jsonl from replan_threshold.py")
    parser.add_argument("--out", type=Path, default=None, help="default: docs/results/grasp_frame_scorer_<task>.json")
    args = parser.parse_args()
    predictability, replay = outcome_predictability, replan_threshold
    from planner_client.loop import read_records
    from sim_worker.scene import BLOCK_NAMES

    names = list(BLOCK_NAMES)
    train, _ = predictability.simulated_episodes(args.task, args.train_episodes,
                                                 Path(f"runs/predictability-{args.task}.jsonl"), workers=2)
    X = predictability.features(train, names, "grasp_frame_plan")
    y = np.array([ok for _, ok in train])
    model = GradientBoostingClassifier(random_state=0).fit(X, y)

    splits = {}
    for split in ("calibration", "test"):
        path = args.records / f"{args.task}-{split}.jsonl"
        records = read_records(path)
        firp_scores, success, bundle = replay.arrays(records, path)
        episodes = [(a, False) for r in records for a in candidate_attrs(args.task, int(r["seed"]), r["orders"])]
        scores = model.predict_proba(predictability.features(episodes, names, "grasp_frame_plan"))[:, 1]
        splits[split] = (scores.reshape(success.shape), success, firp_scores, bundle)

    grid = np.round(np.arange(0.02, 0.981, 0.02), 2)
    cal_scores, cal_success, _, _ = splits["calibration"]
    threshold = float(max(grid, key=lambda t: (round(replay.replan_success(cal_scores, cal_success, t)[0], 9), -t)))
    result: dict = {"command": f"MUJOCO_GL=egl .venv/bin/python -m experiments.grasp_frame_scorer --task {args.task} "
                               f"--train-episodes {args.train_episodes}",
                    "train_episodes": int(len(y)), "threshold_chosen_on_calibration": threshold, "splits": {}}
    for split, (scores, success, firp_scores, bundle) in splits.items():
        lines = replay.policies(scores, success)
        result["splits"][split] = {
            "trials": int(len(success)),
            "tamp_alone": lines["tamp_alone"], "oracle": lines["oracle"],
            "grasp_frame_loop_at_threshold": replay.replan_success(scores, success, threshold)[0],
            "grasp_frame_best_of_candidates": lines["best_score"],
            "grasp_frame_candidate_auc": replay.candidate_metrics(scores, success, threshold)["roc_auc"],
            "firp_loop_at_bundle_threshold": replay.replan_success(firp_scores, success, bundle["threshold"])[0],
            "firp_candidate_auc": replay.candidate_metrics(firp_scores, success, bundle["threshold"])["roc_auc"],
        }
    print("| split | trials | TAMP alone | grasp-frame GB loop | GB best of 6 | GB AUC | FIRP loop | FIRP AUC | oracle |")
    print("|---|---|---|---|---|---|---|---|---|")
    for split, r in result["splits"].items():
        print(f"| {split} | {r['trials']} | {r['tamp_alone']:.0%} | {r['grasp_frame_loop_at_threshold']:.0%} | "
              f"{r['grasp_frame_best_of_candidates']:.0%} | {r['grasp_frame_candidate_auc']:.3f} | "
              f"{r['firp_loop_at_bundle_threshold']:.0%} | {r['firp_candidate_auc']:.3f} | {r['oracle']:.0%} |")
    print(f"threshold chosen on the calibration seeds: {threshold}")
    out = args.out or Path(f"docs/results/grasp_frame_scorer_{args.task}.json")
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
