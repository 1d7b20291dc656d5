"""Would more episodes teach a scorer the layout? A learning curve for a robosuite task, told the scene.

On ``pick_place`` the learned scorers stay at 0.5-0.6 balanced accuracy while a scorer that read the
scene as well as the planner's perception could reach about 0.92 (``experiments.robosuite_sensitivity``).
Between the two lies learning: what decides an episode is where the hand meets the other objects and the
bin's walls, which is in the scene, but a few hundred episodes may be too few to learn it from.

This measures it without images, so that the curve can run far past the rendered dataset's size. Each
episode is the one ``firp collect --world robosuite`` records for its scene seed (the same choice, plan and
label; nothing is rendered), kept with the planner's pose estimates. Then two learners -- gradient boosting
(thresholds and interactions of the raw numbers) and the small MLP of the other analyses (smooth functions
of them) -- are trained on growing shares of the episodes, each time tested on the same held-out episodes,
on three inputs:

* ``choice``: the planner's choice alone (the order, each grasp's faces and height) -- what a learned
  scorer could at best read from the plan's joint targets;
* ``choice_and_poses``: the choice plus every object's estimated position and yaw -- the layout given as
  numbers, perfectly perceived to the planner's own precision, instead of 84 px of image;
* ``choice_and_clutter``: that plus the relations a person would compute: per pick, how near the picked
  object's nearest neighbour still in the bin is and how tall it is, and how near the picked object stands
  to the bin's walls.

If even these curves stay far below the ceiling at the dataset's size, the dataset's size -- not the
image pipeline or the model -- is what stops the learned scorers, and the curve says how many episodes
the target would need. Episodes are appended to a JSONL file as they end; a rerun resumes. The episodes
run in the robosuite environment, the curve in the main one (scikit-learn); with every episode done, a run
simulates nothing and needs no robosuite:

    .venv-robosuite/bin/python -m experiments.robosuite_layout_learning --task pick_place --episodes 1600 \\
        --workers 2 --simulate-only --out runs/robosuite_layout_pick_place.jsonl
    .venv/bin/python -m experiments.robosuite_layout_learning --task pick_place --episodes 1600 \\
        --out runs/robosuite_layout_pick_place.jsonl --report docs/results/robosuite_pick_place_layout_learning.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from experiments.resumable import run_seeds

INPUTS = ("choice", "choice_and_poses", "choice_and_clutter")
LEARNERS = ("gradient_boosting", "mlp")
DEFAULT_SIZES = (100, 200, 400, 800, 1200)

_state: dict = {}


# -- simulation (the robosuite environment) ----------------------------------------------------------------

def _init(task: str, mm: float, deg: float) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from planner_client.robosuite_tamp import RobosuiteTampPlanner
    from robosuite_worker.world import RobosuiteWorld

    _state.update(world=RobosuiteWorld(image_size=32), planner=RobosuiteTampPlanner(), task=task, mm=mm, deg=deg)


def run_episode(seed: int) -> dict:
    """The dataset's episode for ``seed`` without its frames: choice, pose estimates, scene and label."""
    from planner_client.collect_robosuite import simulate_episode
    from planner_client.ik import IKFailure

    try:
        record = simulate_episode(_state["world"], _state["planner"], _state["task"], seed, _state["mm"],
                                  _state["deg"], record_frames=False)
    except IKFailure as exc:
        return {"seed": seed, "unplannable": str(exc)}
    keep = ("choice", "block_order", "pose_estimates", "scene", "reason", "kind", "is_default_choice")
    return {"seed": seed, "success": bool(record.success), **{k: record.attrs[k] for k in keep}}


# -- features (pure functions of a record) -----------------------------------------------------------------

def choice_features(record: dict, objects: list[str]) -> list[float]:
    """Each object's place in the order, then its face pair and grasp height (-1 for an object not moved):
    ``experiments.choice_predictability``'s, imported here because that module needs torch, which the
    robosuite environment that runs the episodes does not have."""
    from experiments.choice_predictability import choice_features as from_attrs

    return from_attrs(record, objects)


def pose_features(record: dict, objects: list[str]) -> list[float]:
    """Each object's estimated position (x, y, z) and yaw as cos/sin of yaw and of twice yaw (a box looks
    the same turned half a turn)."""
    out = []
    for name in objects:
        pose = record["pose_estimates"][name]
        yaw = float(pose["yaw"])
        out += [*map(float, pose["position"]), np.cos(yaw), np.sin(yaw), np.cos(2 * yaw), np.sin(2 * yaw)]
    return out


def clutter_features(record: dict, objects: list[str]) -> list[float]:
    """Per pick in the plan's order: the distance from the picked object to its nearest neighbour still in
    the first bin, that neighbour's height, the number of neighbours within 8 cm, and the picked object's
    distance to the first bin's nearest wall (all in the plane, from the pose estimates)."""
    scene = record["scene"]
    centre = np.asarray(scene["bin1"][:2], float)
    half = np.asarray(scene["bin_size"], float) / 2.0
    position = {n: np.asarray(record["pose_estimates"][n]["position"][:2], float) for n in objects}
    height = {n: 2.0 * float(scene["objects"][n]["half"][2]) for n in objects}
    order = list(record["block_order"])
    out = []
    for k, name in enumerate(order):
        remaining = order[k + 1:]
        if remaining:
            gaps = [float(np.linalg.norm(position[name] - position[other])) for other in remaining]
            nearest = remaining[int(np.argmin(gaps))]
            out += [min(gaps), height[nearest], float(sum(g < 0.08 for g in gaps))]
        else:
            out += [1.0, 0.0, 0.0]
        offset = np.abs(position[name] - centre)
        out.append(float(np.min(half - offset)))
    return out


def feature_table(records: list[dict], name: str) -> np.ndarray:
    """``(N, D)`` features of input ``name`` (one of :data:`INPUTS`)."""
    objects = sorted(records[0]["pose_estimates"])
    rows = []
    for record in records:
        row = choice_features(record, objects)
        if name in ("choice_and_poses", "choice_and_clutter"):
            row += pose_features(record, objects)
        if name == "choice_and_clutter":
            row += clutter_features(record, objects)
        rows.append(row)
    return np.asarray(rows, float)


# -- the learning curve ------------------------------------------------------------------------------------

def fit(learner: str, X: np.ndarray, labels: np.ndarray, seed: int):
    """A fitted classifier: ``gradient_boosting`` (trees: thresholds and interactions of raw numbers) or
    ``mlp`` (the small MLP every analysis of the plan's numbers uses: smooth functions of them)."""
    if learner == "gradient_boosting":
        from sklearn.ensemble import HistGradientBoostingClassifier

        return HistGradientBoostingClassifier(max_iter=200, learning_rate=0.05, early_stopping=False,
                                              class_weight="balanced", random_state=seed).fit(X, labels)
    if learner == "mlp":
        from experiments.grasp_clearance import fit_mlp

        return fit_mlp(X, labels, seed)
    raise ValueError(f"learner: one of {LEARNERS}, got {learner!r}")


def learning_curve(records: list[dict], sizes: list[int], repeats: int, learners: tuple[str, ...] = LEARNERS,
                   test_share: float = 0.25) -> dict:
    """Per repeat, a stratified held-out test share; per size, each learner trained on that many of the
    remaining episodes (a stratified, seeded subset; the smaller subsets lie inside the larger ones), tested
    on the held-out ones at 0.5. Returns ``{learner: {input: {training episodes: cell}}}``, each cell the
    repeats' balanced accuracies and their mean and standard deviation."""
    from firp.data import stratified_split
    from firp.metrics import balanced_accuracy

    labels = np.array([bool(r["success"]) for r in records])
    tables = {name: feature_table(records, name) for name in INPUTS}
    curves: dict = {learner: {name: {} for name in INPUTS} for learner in learners}
    for repeat in range(repeats):
        pool, test = stratified_split(labels.astype(int), test_share, seed=1000 + repeat)
        for size in sizes:
            if size > len(pool):
                continue
            keep = stratified_split(labels[pool].astype(int), 1.0 - size / len(pool), seed=repeat)[0] \
                if size < len(pool) else np.arange(len(pool))
            train = pool[keep]
            for learner in learners:
                for name, X in tables.items():
                    model = fit(learner, X[train], labels[train], repeat)
                    score = balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)
                    curves[learner][name].setdefault(str(len(train)), {"repeats": []})["repeats"].append(float(score))
    for by_input in curves.values():
        for by_size in by_input.values():
            for cell in by_size.values():
                cell["mean"] = float(np.mean(cell["repeats"]))
                cell["std"] = float(np.std(cell["repeats"], ddof=1)) if len(cell["repeats"]) > 1 else 0.0
    return curves


def gain_per_doubling(curve: dict[str, dict]) -> float:
    """Least-squares slope of mean balanced accuracy against log2(training episodes)."""
    sizes = np.array([int(s) for s in curve], float)
    means = np.array([cell["mean"] for cell in curve.values()])
    return float(np.polyfit(np.log2(sizes), means, 1)[0]) if len(sizes) > 1 else float("nan")


def plot(curves: dict, ceiling: float | None, target: float | None, dataset_train: int | None, path: Path,
         title: str) -> None:
    """One panel per learner: each input's mean ± std over the repeats against the training episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(5.2 * len(curves), 4.4), sharey=True, squeeze=False)
    for ax, (learner, by_input) in zip(axes[0], curves.items()):
        for name, curve in by_input.items():
            ax.errorbar([int(s) for s in curve], [c["mean"] for c in curve.values()],
                        yerr=[c["std"] for c in curve.values()], marker="o", capsize=3, label=name.replace("_", " "))
        if ceiling is not None:
            ax.axhline(ceiling, color="k", linestyle="--", linewidth=1, label=f"perception-level ceiling {ceiling:.3f}")
        if target is not None:
            ax.axhline(target, color="tab:red", linestyle=":", linewidth=1, label=f"target {target:.3f}")
        if dataset_train is not None:
            ax.axvline(dataset_train, color="grey", linewidth=1, label=f"the rendered dataset's training ({dataset_train})")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("training episodes")
        ax.set_title(learner.replace("_", " "))
        ax.legend(fontsize=7, loc="center left")
    axes[0][0].set_ylabel("test balanced accuracy")
    axes[0][0].set_ylim(0.45, 1.0)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, choices=["stack_three", "nut_assembly", "pick_place"])
    parser.add_argument("--episodes", type=int, required=True)
    parser.add_argument("--seed-offset", type=int, default=0, help="first scene seed (a dataset's are 0..)")
    parser.add_argument("--pose-error-mm", type=float, default=3.0, help="the planner's perception error")
    parser.add_argument("--pose-error-deg", type=float, default=3.0)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES),
                        help="training episodes per point of the curve (sizes above the pool are skipped)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=max(1, os.cpu_count() or 1))
    parser.add_argument("--ceiling", type=float, default=None, help="the perception-level ceiling, drawn on the plot")
    parser.add_argument("--target", type=float, default=None, help="the task's target, drawn on the plot")
    parser.add_argument("--dataset-train", type=int, default=None,
                        help="training episodes of the rendered dataset's protocol, drawn on the plot")
    parser.add_argument("--simulate-only", action="store_true", help="run the episodes, skip the curve")
    parser.add_argument("--out", type=Path, required=True, help="JSONL of the episodes (a rerun resumes)")
    parser.add_argument("--report", type=Path, help="JSON report; its plot goes beside it (.png); needed "
                                                     "unless --simulate-only")
    args = parser.parse_args(argv)
    if args.report is None and not args.simulate_only:
        parser.error("--report: required unless --simulate-only")
    for flag, value in (("--episodes", args.episodes), ("--repeats", args.repeats), ("--workers", args.workers),
                        *(("--sizes", s) for s in args.sizes)):
        if value < 1:
            parser.error(f"{flag}: must be at least 1, got {value}")
    started = time.perf_counter()
    wanted = [args.seed_offset + i for i in range(args.episodes)]
    done = run_seeds(args.out, run_episode, wanted, workers=args.workers, initializer=_init,
                     initargs=(args.task, args.pose_error_mm, args.pose_error_deg), desc=f"episodes {args.task}")
    if args.simulate_only:
        return 0
    records = [done[s] for s in wanted if "unplannable" not in done[s]]
    labels = np.array([r["success"] for r in records])
    if labels.all() or not labels.any():
        parser.error(f"the {len(records)} episodes' outcomes are of one class; ask for more --episodes")
    curves = learning_curve(records, sorted(set(args.sizes)), args.repeats)
    result = {"task": args.task, "episodes": len(wanted), "unplannable": len(wanted) - len(records),
              "successes": int(labels.sum()), "failures": int((~labels).sum()),
              "seeds": [wanted[0], wanted[-1]], "pose_error": {"mm": args.pose_error_mm, "deg": args.pose_error_deg},
              "test_episodes": int(round(0.25 * len(records))), "repeats": args.repeats,
              "curves": curves, "gain_per_doubling": {learner: {name: gain_per_doubling(c) for name, c in by_input.items()}
                                                      for learner, by_input in curves.items()},
              "ceiling": args.ceiling, "target": args.target, "dataset_train": args.dataset_train,
              "seconds_this_call": round(time.perf_counter() - started, 1),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "command": "python -m experiments.robosuite_layout_learning " + " ".join(argv or sys.argv[1:])}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(json.dumps(result, indent=1) + "\n")
    plot(curves, args.ceiling, args.target, args.dataset_train, args.report.with_suffix(".png"),
         f"robosuite {args.task}: would more episodes teach the layout?")
    for learner, by_input in curves.items():
        for name, curve in by_input.items():
            print(f"{learner:>17} {name:>18}: "
                  + "  ".join(f"{s}: {c['mean']:.3f}±{c['std']:.3f}" for s, c in curve.items())
                  + f"  ({result['gain_per_doubling'][learner][name]:+.3f} per doubling)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
