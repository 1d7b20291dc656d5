"""How much of a plan's outcome is fixed by what a camera can see? The pre-execution ceiling.

The simulator is deterministic: an outcome is a function of the true initial state and the plan.
But a predictor sees the state only through an 84x84 image (about 5 mm per pixel on the stacking
camera) and cannot know it better than that. This script executes each episode's plan (the one
``planner_client.collect`` would record for that seed: same scene, perception error, block order and
planner) once from the true initial state and ``K`` more times from initial states that differ by
a small random shift of every block (``--xy-mm`` in-plane std, ``--yaw-deg`` yaw std; a fifth of a
pixel by default). The plan is fixed; only contact physics sees the difference.

From the ``K`` perturbed outcomes, ``p_i`` estimates each episode's success probability for a
predictor that knows the state to that resolution. The ceiling is how well thresholding ``p_i``
predicts the *unperturbed* outcome (an independent draw): balanced accuracy at the best threshold
(success when ``p_i >=`` it, chosen by ``firp.metrics.choose_threshold`` as for the bundles; optimistic:
the threshold is chosen on the same episodes) and with a threshold chosen by 5-fold
cross-validation. A model that sees only the image cannot beat it by more than this estimate's
noise, whatever its architecture.

Each episode's record is appended to a JSONL file as soon as it is done, so an interrupted run
resumes (``--resume`` is implicit: finished seeds are skipped).

    MUJOCO_GL=egl .venv/bin/python -m experiments.outcome_sensitivity --task stacking --episodes 160
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments.resumable import append_as_done
from firp.metrics import balanced_accuracy, choose_threshold

PERTURB_STREAM = 23  # separates the perturbation draws from the scene, perception and order streams


@dataclass(frozen=True)
class SensitivityConfig:
    task: str
    perturbations: int
    xy_std_m: float
    yaw_std_deg: float
    image_size: int = 84


_worker: dict = {}


def _init_worker(config: SensitivityConfig) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from planner_client.tamp import PlannerConfig, TampPlanner
    from sim_worker.scene import RenderConfig, SceneLayout
    from sim_worker.world import World

    _worker["config"] = config
    _worker["world"] = World(SceneLayout(), RenderConfig.for_task(config.task, config.image_size, config.image_size))
    _worker["planner"] = TampPlanner(PlannerConfig())


def perturbed_blocks(true_blocks: np.ndarray, seed: int, k: int, xy_std_m: float, yaw_std_deg: float) -> np.ndarray:
    """``true_blocks`` (n, 4: x, y, z, yaw) with every block shifted in-plane and turned, draw ``k``."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, PERTURB_STREAM, k]))
    out = true_blocks.copy()
    n = len(out)
    out[:, :2] += rng.normal(0.0, xy_std_m, (n, 2))
    out[:, 3] += np.radians(rng.normal(0.0, yaw_std_deg, n))
    return out


def run_episode(unit: tuple[int, tuple[str, ...]]) -> dict:
    """The plan of (seed, block order) executed from its true state and from ``K`` perturbed ones."""
    from planner_client.collect import plan_episode
    from sim_worker.executor import ExecutorConfig, execute_plan
    from sim_worker.perception import PoseErrorConfig

    seed, order = unit
    config: SensitivityConfig = _worker["config"]
    world = _worker["world"]
    planned = plan_episode(_worker["planner"], config.task, seed, order, PoseErrorConfig(), world.layout)
    true_blocks, plan = planned.true_blocks, planned.plan.actions
    no_frames = ExecutorConfig(record_frames=False)
    base = execute_plan(world, config.task, true_blocks, plan, no_frames)
    outcomes, reasons = [], []
    for k in range(config.perturbations):
        start = perturbed_blocks(true_blocks, seed, k, config.xy_std_m, config.yaw_std_deg)
        result = execute_plan(world, config.task, start, plan, no_frames)
        outcomes.append(bool(result.success))
        reasons.append(result.reason)
    return {"seed": int(seed), "order": list(order), "success": bool(base.success), "reason": base.reason,
            "perturbed_success": outcomes, "perturbed_reasons": reasons}


Unit = tuple[int, tuple[str, ...]]  # (scene seed, block order)


def unit_of(record: dict) -> Unit:
    return int(record["seed"]), tuple(record["order"])


def read_done(path: Path) -> dict[Unit, dict]:
    """Finished units of an earlier (possibly interrupted) run; a torn last line is ignored."""
    from planner_client.loop import read_records

    return {unit_of(record): record for record in read_records(path)}


def cross_validated_ba(p: np.ndarray, y: np.ndarray, folds: int = 5, seed: int = 0) -> float:
    """Balanced accuracy when each fold's threshold is chosen on the other folds."""
    order = np.random.default_rng(seed).permutation(len(y))
    pred = np.zeros(len(y), dtype=bool)
    for fold in np.array_split(order, folds):
        train = np.setdiff1d(order, fold)
        cut, _ = choose_threshold(y[train], p[train])
        pred[fold] = p[fold] >= cut
    return balanced_accuracy(y, pred)


def reason_kind(reason: str) -> str:
    """A failure reason without its block names and numbers, to count kinds of failure."""
    return re.sub(r"-?\d+(\.\d+)?", "#", re.sub(r"\b(red|green|blue)\b", "<block>", reason))


def analyse(records: list[dict]) -> dict:
    y = np.array([r["success"] for r in records])
    outcomes = np.array([r["perturbed_success"] for r in records], dtype=float)  # (N, K)
    p = outcomes.mean(axis=1)
    k = outcomes.shape[1]
    disagree = outcomes != y[:, None]  # (N, K)
    cut, ba_best = choose_threshold(y, p)
    return {
        "plans": int(len(y)), "perturbations_per_plan": int(k),
        "success_rate": round(float(y.mean()), 3),
        "perturbed_success_rate": round(float(outcomes.mean()), 3),
        "plans_whose_outcome_flips_under_some_perturbation": round(float(disagree.any(axis=1).mean()), 3),
        "perturbed_runs_disagreeing_with_unperturbed": round(float(disagree.mean()), 3),
        "plans_with_p_strictly_between_0_and_1": round(float(((p > 0) & (p < 1)).mean()), 3),
        "p_histogram": {f"{j}/{k}": int((outcomes.sum(axis=1) == j).sum()) for j in range(k + 1)},
        "ceiling_balanced_accuracy_best_threshold": round(ba_best, 3),
        "ceiling_threshold": round(cut, 3),
        "ceiling_balanced_accuracy_5fold_threshold": round(cross_validated_ba(p, y), 3),
        "failure_kinds_unperturbed": dict(Counter(reason_kind(r["reason"]) for r in records if not r["success"])
                                          .most_common()),
        "failure_kinds_of_flipped_runs": dict(Counter(
            reason_kind(why) for r in records for ok, why in zip(r["perturbed_success"], r["perturbed_reasons"])
            if not ok and r["success"]).most_common()),
    }


def analyse_loop(records: list[dict], orders: list[tuple[str, ...]], scores_path: Path | None) -> dict:
    """The replanning loop's ceiling: every candidate judged by its perturbed success rate ``p``.

    ``scores_path`` (``experiments/replan_threshold.py`` records of the same seeds, in trial order)
    adds the FIRP bundle's own choices and ranking on the same candidates, for comparison.
    """
    from experiments import replan_threshold as replay
    by_seed: dict[int, dict[tuple[str, ...], dict]] = {}
    for r in records:
        by_seed.setdefault(int(r["seed"]), {})[tuple(r["order"])] = r
    seeds = sorted(by_seed)
    y = np.array([[by_seed[s][o]["success"] for o in orders] for s in seeds])  # (N, C)
    p = np.array([[np.mean(by_seed[s][o]["perturbed_success"]) for o in orders] for s in seeds])  # (N, C)
    curve = {float(t): replay.replan_success(p, y, t)[0] for t in np.unique(p)}  # accept when p >= t
    best = max(curve, key=curve.get)
    lines = replay.policies(p, y)
    result = {
        "trials": len(seeds), "candidates_per_trial": len(orders),
        "tamp_alone_success": round(lines["tamp_alone"], 3),
        "oracle_success": round(lines["oracle"], 3),
        "ceiling_pick_highest_p_success": round(lines["best_score"], 3),
        "ceiling_paper_rule_best_threshold_success": round(curve[best], 3),
        "ceiling_paper_rule_best_threshold": round(best, 3),
        "ceiling_candidate_auc": round(replay.candidate_metrics(p, y, best)["roc_auc"], 3),
    }
    if scores_path is not None:
        f, recorded, model = replay.read(scores_path)
        if f.shape != y.shape or not np.array_equal(recorded, y):
            raise SystemExit(f"{scores_path}: its candidates' outcomes differ from this run's unperturbed ones "
                             "(other seeds, orders or simulator)")
        result.update({
            "recorded_outcomes_reproduced": True,
            "firp_paper_rule_bundle_threshold_success": round(replay.replan_success(f, y, model["threshold"])[0], 3),
            "firp_pick_highest_score_success": round(replay.policies(f, y)["best_score"], 3),
            "firp_candidate_auc": round(replay.candidate_metrics(f, y, model["threshold"])["roc_auc"], 3),
        })
        # where FIRP's mistakes are: plans whose outcome no perturbation changes vs the others
        stable = (p == 0) | (p == 1)
        for name, mask in (("stable", stable), ("unstable", ~stable)):
            part = replay.candidate_metrics(f[mask][:, None], y[mask][:, None], model["threshold"]) \
                if 0 < y[mask].mean() < 1 else None
            result[f"firp_on_{name}_candidates"] = {
                "candidates": int(mask.sum()),
                "roc_auc": round(part["roc_auc"], 3) if part else None,
                "balanced_accuracy_at_bundle_threshold":
                    round(part["balanced_accuracy_at_bundle_threshold"], 3) if part else None,
            }
    return result


def main() -> None:
    from planner_client.tamp import block_orders
    from planner_client.collect import episode_order

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="stacking", choices=["stacking", "replacement"])
    parser.add_argument("--candidates", default="dataset", choices=["dataset", "loop"],
                        help="dataset: each seed's plan with the block order collect draws for it; loop: all of "
                             "the replanning loop's candidates (the first --max-iterations block orders)")
    parser.add_argument("--max-iterations", type=int, default=6, help="loop candidates per seed (--candidates loop)")
    parser.add_argument("--episodes", type=int, default=160, help="scene seeds")
    parser.add_argument("--seed-offset", type=int, default=None,
                        help="first scene seed (default: 0 = collect's, or 100000 = the main job's with --candidates loop)")
    parser.add_argument("--perturbations", type=int, default=8, help="perturbed executions per plan (K)")
    parser.add_argument("--xy-mm", type=float, default=1.0, help="in-plane std of the block shift, mm")
    parser.add_argument("--yaw-deg", type=float, default=1.0, help="std of the block turn, degrees")
    parser.add_argument("--scores", type=Path, default=None,
                        help="experiments/replan_threshold.py records of the same seeds: compare FIRP's choices")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--records", type=Path, default=None,
                        help="JSONL of finished plans (default: runs/sensitivity-<task>[-loop]_<xy>mm.jsonl)")
    parser.add_argument("--out", type=Path, default=None,
                        help="summary JSON (default: docs/results/outcome_sensitivity_<task>[_loop]_<xy>mm.json)")
    args = parser.parse_args()
    if args.perturbations < 1 or args.episodes < 5:
        parser.error("--perturbations must be >= 1 and --episodes >= 5")
    if not 1 <= args.max_iterations <= 6:
        parser.error("--max-iterations must be between 1 and 6 (the block orders of three blocks)")
    loop = args.candidates == "loop"
    seed_offset = args.seed_offset if args.seed_offset is not None else (100000 if loop else 0)
    tag = f"{args.task}{'_loop' if loop else ''}_{args.xy_mm:g}mm"
    records_path = args.records or Path(f"runs/sensitivity-{tag}.jsonl")
    out = args.out or Path(f"docs/results/outcome_sensitivity_{tag}.json")
    config = SensitivityConfig(args.task, args.perturbations, args.xy_mm / 1000.0, args.yaw_deg)

    seeds = list(range(seed_offset, seed_offset + args.episodes))
    orders = block_orders()[: args.max_iterations]
    units = [(s, o) for s in seeds for o in orders] if loop else [(s, episode_order(s)) for s in seeds]
    done = read_done(records_path)
    pending = [u for u in units if u not in done]
    append_as_done(records_path, run_episode, pending, done=done, key=unit_of, workers=args.workers,
                   initializer=_init_worker, initargs=(config,), desc=f"sensitivity {tag}", unit="plan",
                   already=len(units) - len(pending))
    records = [done[u] for u in units]
    if any(len(r["perturbed_success"]) != args.perturbations for r in records):
        raise SystemExit(f"{records_path} holds records with another --perturbations; use a new --records file")
    summary = analyse(records)
    if loop:
        summary["loop"] = analyse_loop(records, orders, args.scores)
    result = {
        "command": f"MUJOCO_GL=egl .venv/bin/python -m experiments.outcome_sensitivity --task {args.task} "
                   f"--candidates {args.candidates} --episodes {args.episodes} --seed-offset {seed_offset} "
                   f"--perturbations {args.perturbations} --xy-mm {args.xy_mm:g} --yaw-deg {args.yaw_deg:g}"
                   + (f" --max-iterations {args.max_iterations}" if loop else "")
                   + (f" --scores {args.scores}" if args.scores else ""),
        "perturbation": {"xy_std_mm": args.xy_mm, "yaw_std_deg": args.yaw_deg},
        **summary,
    }
    print("| measure | value |\n|---|---|")
    for key, value in summary.items():
        if key == "loop":
            for k2, v2 in value.items():
                print(f"| loop: {k2} | {v2} |")
        else:
            print(f"| {key} | {value} |")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
