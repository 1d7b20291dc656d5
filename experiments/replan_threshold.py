"""Which acceptance threshold should the replanning loop use? Every candidate scored *and* executed.

The main job (``python -m planner_client run``) walks the block orders, scores each plan and stops at
the first whose score reaches the threshold (default: the bundle's, chosen on validation data to
maximise balanced accuracy -- a classification criterion, not the loop's success rate). Here, for
each trial, *all* ``--max-iterations`` candidate plans are planned, scored by the shipped ensemble
(in process, the same scorer the service runs) and executed in the simulator, so the loop's success
rate can be replayed exactly for any threshold afterwards:

* ``replan(thr)``: the loop's rule -- the first candidate with score >= thr, else the last one;
* ``TAMP alone``: the first candidate; ``oracle``: the first candidate that succeeds;
* ``best score``: the candidate with the highest score (a ranking planner, for reference).

Thresholds are chosen on *calibration* seeds (``--split calibration``: 200000 + i, neither dataset
seeds 0.. nor the main job's 100000 + i) and only then read off the *test* seeds (``--split test``:
the main job's own trials), so the test numbers are not tuned on. Records are written per trial to
a JSONL file (resumable: ``--resume``); the analysis prints a table, writes JSON and a PNG curve.

    MUJOCO_GL=egl .venv/bin/python -m experiments.replan_threshold --task stacking --split calibration --trials 100
    MUJOCO_GL=egl .venv/bin/python -m experiments.replan_threshold --task stacking --split test --trials 50
    .venv/bin/python -m experiments.replan_threshold --task stacking --analyse-only

Another bundle on the *same* candidates, without executing them again (``--rescore DIR``: each
trial's scene is set up from its seed, its recorded orders planned again -- planner and scene are
deterministic -- and scored by ``--bundle``; the recorded outcomes are kept; records go to
``--records-dir``):

    MUJOCO_GL=egl .venv/bin/python -m experiments.replan_threshold --task stacking --rescore docs/results/replan_threshold \
        --bundle runs/bundle-geometry --records-dir runs/replan_threshold_geometry --out docs/results/replan_threshold_stacking_geometry.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from planner_client.loop import chosen_candidate, read_records

ROOT = Path(__file__).resolve().parents[1]
SPLIT_SEEDS = {"calibration": 200_000, "test": 100_000}
GRID = np.round(np.arange(0.02, 0.981, 0.02), 2)


def _scoring_setup(bundle_dir: Path) -> tuple:
    """The in-process ensemble scorer (the one the service runs), the model as records name it, the
    task worlds and the planner."""
    import torch

    from firp.bundle import load_bundle
    from firp.serving import EnsembleScorer
    from planner_client.tamp import TampPlanner
    from sim_worker.worlds import TaskWorlds

    torch.set_num_threads(1)
    scorer = EnsembleScorer(load_bundle(bundle_dir))
    model = {"name": scorer.bundle.manifest.get("name"), "version": scorer.bundle.manifest.get("version"),
             "threshold": scorer.threshold}
    return scorer, model, TaskWorlds(), TampPlanner()


def _scored_candidates(worlds, planner, scorer, task: str, seed: int, orders) -> tuple:
    """Set up scene ``seed``, plan every order, score the plans: ``(episode, plans (K, T, 16), score fields)``."""
    episode = worlds.begin(task, seed)
    plans = np.stack([planner.plan(task, episode.observation, tuple(order)).actions for order in orders])
    result = scorer.score(episode.image, plans)
    return episode, plans, {"scores": [round(float(v), 6) for v in result.probabilities],
                            "spread": [round(float(v), 6) for v in result.spread]}


def collect(task: str, split: str, trials: int, bundle_dir: Path, out: Path, max_iterations: int,
            resume: bool, progress: bool) -> None:
    """Plan, score and execute every candidate of each pending trial; one JSON line per trial."""
    from planner_client.tamp import block_orders

    if out.exists() and not resume:
        sys.exit(f"--out: {out} exists; pass --resume to continue it or choose another file")
    records = read_records(out)  # a torn last line (killed mid-write) is dropped: that trial runs again
    done = {r["trial"] for r in records}
    if out.exists():
        out.write_text("".join(json.dumps(r) + "\n" for r in records))
    scorer, model, worlds, planner = _scoring_setup(bundle_dir)
    orders = block_orders()[:max_iterations]
    out.parent.mkdir(parents=True, exist_ok=True)
    pending = [t for t in range(trials) if t not in done]
    with out.open("a") as sink:
        for trial in tqdm(pending, desc=f"{task} {split}", unit="trial", disable=not progress):
            started = time.perf_counter()
            seed = SPLIT_SEEDS[split] + trial
            episode, plans, scored = _scored_candidates(worlds, planner, scorer, task, seed, orders)
            successes = [bool(worlds.execute(task, episode.true_blocks, plan).success) for plan in plans]
            record = {"trial": trial, "seed": seed, "task": task, "split": split, "model": model,
                      "orders": [list(o) for o in orders], **scored,
                      "success": successes, "seconds": round(time.perf_counter() - started, 3)}
            sink.write(json.dumps(record) + "\n")
            sink.flush()
    worlds.close()


def rescore(task: str, split: str, source: Path, bundle_dir: Path, out: Path, progress: bool) -> None:
    """Score the candidates recorded in ``source`` with another bundle; outcomes are copied, not re-run."""
    records = read_records(source)
    if not records:
        sys.exit(f"--rescore: {source} holds no trials")
    scorer, model, worlds, planner = _scoring_setup(bundle_dir)
    model = {**model, "bundle": str(bundle_dir)}
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w") as sink:
        for record in tqdm(records, desc=f"rescore {task} {split}", unit="trial", disable=not progress):
            if record["task"] != task or record["split"] != split:
                sys.exit(f"--rescore: {source} holds a {record['task']}/{record['split']} trial, expected {task}/{split}")
            _, _, scored = _scored_candidates(worlds, planner, scorer, task, int(record["seed"]), record["orders"])
            sink.write(json.dumps({**record, "model": model, **scored, "rescored_from": str(source)}) + "\n")
    worlds.close()


def read(path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(N, K)`` scores and successes of a records file, and the model it was scored with."""
    return arrays(read_records(path), path)


def arrays(records: list[dict], path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(N, K)`` scores and successes of records read from ``path``, and the model they were scored with."""
    if not records:
        sys.exit(f"{path}: no trials recorded yet")
    return (np.array([r["scores"] for r in records]), np.array([r["success"] for r in records], dtype=bool),
            records[0]["model"])


def replan_success(scores: np.ndarray, success: np.ndarray, threshold: float) -> tuple[float, float]:
    """Success rate of the loop's rule at ``threshold`` and the mean number of plans it scores."""
    chosen = np.array([chosen_candidate(row, threshold) for row in scores])  # the loop's own rule
    return float(success[np.arange(len(chosen)), chosen].mean()), float((chosen + 1).mean())


def policies(scores: np.ndarray, success: np.ndarray) -> dict[str, float]:
    """The threshold-free lines: TAMP alone, best score, oracle (first success), random candidate."""
    return {"tamp_alone": float(success[:, 0].mean()),
            "best_score": float(success[np.arange(len(scores)), scores.argmax(axis=1)].mean()),
            "any_candidate_mean": float(success.mean()),
            "oracle": float(success.any(axis=1).mean())}


def candidate_metrics(scores: np.ndarray, success: np.ndarray, threshold: float) -> dict[str, float]:
    """How well the scores separate successful from failed candidates (all candidates pooled)."""
    from sklearn.metrics import balanced_accuracy_score, roc_auc_score

    y, s = success.ravel(), scores.ravel()
    return {"candidates": int(y.size), "positive_rate": float(y.mean()),
            "roc_auc": float(roc_auc_score(y, s)) if 0 < y.mean() < 1 else float("nan"),
            "balanced_accuracy_at_bundle_threshold": float(balanced_accuracy_score(y, s >= threshold))}


def choose_threshold(curve: list[dict]) -> float:
    """The threshold with the highest success rate; ties: the fewest plans scored, then the lowest."""
    best = max(curve, key=lambda row: (round(row["success_rate"], 9), -row["plans_scored"], -row["threshold"]))
    return float(best["threshold"])


def analyse(task: str, files: dict[str, Path], out_json: Path, out_png: Path, command: str) -> dict:
    loaded = {split: read(path) for split, path in files.items() if path.exists()}  # (scores, success, model)
    made_by = [f"MUJOCO_GL=egl python -m experiments.replan_threshold --task {task} --split {split} --trials "
               f"{len(scores)}" for split, (scores, _, _) in loaded.items()]
    report: dict = {"command": command, "records_made_by": made_by, "task": task,
                    "machine": {"python": platform.python_version()}, "grid": GRID.tolist(), "splits": {}}
    for split, (scores, success, model) in loaded.items():
        path = files[split]
        curve = [dict(zip(("threshold", "success_rate", "plans_scored"), (float(t), *replan_success(scores, success, t))))
                 for t in GRID]
        bundle_rate, bundle_plans = replan_success(scores, success, model["threshold"])
        report["splits"][split] = {
            "file": str(path), "trials": int(len(scores)), "model": model, "curve": curve,
            "bundle_threshold": {"threshold": model["threshold"], "success_rate": bundle_rate,
                                 "plans_scored": bundle_plans},
            **policies(scores, success), **candidate_metrics(scores, success, model["threshold"])}
    if "calibration" in report["splits"]:
        chosen = choose_threshold(report["splits"]["calibration"]["curve"])
        report["chosen_threshold"] = chosen
        for split, part in report["splits"].items():
            scores, success, _ = loaded[split]
            rate, plans = replan_success(scores, success, chosen)
            part["chosen_threshold"] = {"threshold": chosen, "success_rate": rate, "plans_scored": plans}
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(report, indent=1))
    _plot(report, out_png)
    return report


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    colors = {"calibration": "tab:blue", "test": "tab:orange"}
    for split, part in report["splits"].items():
        c = colors.get(split, "k")
        ax.plot([r["threshold"] for r in part["curve"]], [100 * r["success_rate"] for r in part["curve"]],
                color=c, label=f"{split}: replan until score ≥ threshold ({part['trials']} trials)")
        ax.axhline(100 * part["tamp_alone"], color=c, ls=":", lw=1, label=f"{split}: TAMP alone")
        ax.axhline(100 * part["oracle"], color=c, ls="--", lw=1, label=f"{split}: oracle")
    first = next(iter(report["splits"].values()))
    ax.axvline(first["model"]["threshold"], color="grey", lw=1, label="bundle threshold (validation BA)")
    if "chosen_threshold" in report:
        ax.axvline(report["chosen_threshold"], color="tab:green", lw=1.5, label="chosen on calibration seeds")
    ax.set_xlabel("acceptance threshold")
    ax.set_ylabel("success rate (%)")
    ax.set_title(f"{report['task']}: the replanning loop's success rate vs its threshold")
    ax.legend(fontsize=7, loc="lower center")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def table(report: dict) -> str:
    rows = [("split", "trials", "TAMP alone", "replan @ bundle thr", "replan @ chosen thr", "best score", "oracle",
             "plans scored (chosen)", "candidate AUC")]
    for split, p in report["splits"].items():
        chosen = p.get("chosen_threshold", {})
        rows.append((split, str(p["trials"]), f"{100 * p['tamp_alone']:.0f}%",
                     f"{100 * p['bundle_threshold']['success_rate']:.0f}% (thr {p['bundle_threshold']['threshold']:.3f})",
                     f"{100 * chosen['success_rate']:.0f}% (thr {chosen['threshold']:.2f})" if chosen else "-",
                     f"{100 * p['best_score']:.0f}%", f"{100 * p['oracle']:.0f}%",
                     f"{chosen['plans_scored']:.2f}" if chosen else "-", f"{p['roc_auc']:.3f}"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=("stacking", "replacement"), default="stacking")
    ap.add_argument("--split", choices=tuple(SPLIT_SEEDS), default="calibration")
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--max-iterations", type=int, default=6)
    ap.add_argument("--bundle", type=Path, default=None, help="default: models/<task>")
    ap.add_argument("--records-dir", type=Path, default=ROOT / "runs" / "replan_threshold")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--analyse-only", action="store_true", help="no new trials: replay the records on disk")
    ap.add_argument("--out", type=Path, default=None, help="JSON (default docs/results/replan_threshold_<task>.json)")
    ap.add_argument("--rescore", type=Path, default=None, metavar="DIR",
                    help="score the candidates recorded in DIR/<task>-<split>.jsonl (every split found) with --bundle; "
                         "no execution: the recorded outcomes are kept")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()
    if args.trials < 1 or args.max_iterations < 1:
        ap.error("--trials and --max-iterations must be >= 1")
    bundle = args.bundle or ROOT / "models" / args.task
    files = {s: args.records_dir / f"{args.task}-{s}.jsonl" for s in SPLIT_SEEDS}
    if args.rescore is not None:
        sources = {s: args.rescore / f"{args.task}-{s}.jsonl" for s in SPLIT_SEEDS}
        if not any(p.exists() for p in sources.values()):
            ap.error(f"--rescore: no {args.task}-<split>.jsonl records in {args.rescore}")
        if args.rescore.resolve() == args.records_dir.resolve():
            ap.error("--rescore: give another --records-dir (the rescored records must not overwrite their source)")
        for split, source in sources.items():
            if source.exists():
                rescore(args.task, split, source, bundle, files[split], not args.no_progress)
    elif not args.analyse_only:
        collect(args.task, args.split, args.trials, bundle, files[args.split], args.max_iterations, args.resume,
                not args.no_progress)
    out_json = args.out or ROOT / "docs" / "results" / f"replan_threshold_{args.task}.json"
    report = analyse(args.task, files, out_json, out_json.with_suffix(".png"), "python " + " ".join(sys.argv))
    print(table(report))
    print(f"wrote {out_json} and {out_json.with_suffix('.png')}")


if __name__ == "__main__":
    main()
