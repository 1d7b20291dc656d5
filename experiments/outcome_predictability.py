"""How learnable is a task's outcome from scene geometry, with this many episodes -- and in which frame?

A yardstick for the learned models. Two standard classifiers (logistic regression, gradient
boosting; scikit-learn) predict success under 5-fold stratified cross-validation from three
descriptions of each episode's scene:

* ``raw`` -- the recorded *ground truth* in world coordinates: true initial block poses in pick
  order, pairwise distances, yaw (as cos/sin of 4*yaw: a cube's symmetry), the perception error the
  planner worked with, and the place targets;
* ``grasp_frame_true`` -- the same scene seen from each grasp: for every moved block, the other
  blocks' offsets and relative yaw in the frame of the planned grasp (its yaw), whether each is
  still on the table, the grasp's offset from the block's true centre, and (stacking) how far the
  tower's target is from its base, (replacement) how far box A's walls are along and across the
  fingers;
* ``grasp_frame_plan`` -- the grasp-frame description built from the planner's *estimates* only,
  i.e. from what the plan itself carries (it grasps and places where the estimates say): no
  privileged information at all;
* ``plan_fk`` -- what the learned models can be given: :func:`firp.model.plan_geometry.plan_geometry`
  on the plan's joint targets (forward kinematics of each grasp and release; the recorded plan of a
  dataset, the re-made plan of a simulated episode -- the planner is deterministic).

The contrast between ``raw`` and ``grasp_frame_*`` tells whether the outcome is hard because it is
chaotic or because it is a simple function in a frame the raw coordinates hide.

Episodes come from recorded datasets or are simulated here without frames (``--simulate TASK:N``:
``planner_client.collect``'s episodes 0..N-1, the same seeds and block orders; labels are cached in a
JSONL file as they finish, so an interrupted run resumes):

    .venv/bin/python -m experiments.outcome_predictability data/stacking.h5 data/replacement.h5
    MUJOCO_GL=egl .venv/bin/python -m experiments.outcome_predictability --simulate stacking:640
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
from sklearn.ensemble import GradientBoostingClassifier
from sklearn.linear_model import LogisticRegression
from sklearn.metrics import balanced_accuracy_score
from sklearn.model_selection import StratifiedKFold, cross_val_predict
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from experiments.resumable import append_as_done

Episode = tuple[dict, bool]  # (record attrs as planner_client.collect writes them, success)
FEATURE_SETS = ("raw", "grasp_frame_true", "grasp_frame_plan", "plan_fk")
PLAN_KEY = "_plan"  # a dataset episode's recorded plan, kept beside its attrs


def dataset_episodes(path: Path) -> tuple[list[Episode], list[str]]:
    """The episodes of a recorded dataset and its block names."""
    from firp.core.episodes import EpisodeDataset

    with EpisodeDataset(path) as ds:
        return [({**ds.demo_attrs(d), PLAN_KEY: ds.actions(d)}, ds.success(d)) for d in ds.demo_names], \
            list(ds.attrs["block_names"])


_worker: dict = {}


def _init_worker(task: str) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from planner_client.tamp import PlannerConfig, TampPlanner
    from sim_worker.scene import RenderConfig, SceneLayout
    from sim_worker.world import World

    _worker.update(task=task, planner=TampPlanner(PlannerConfig()),
                   world=World(SceneLayout(), RenderConfig.for_task(task, 16, 16)))


def _simulate_one(seed: int) -> dict:
    from planner_client.collect import episode_order, simulate_episode
    from sim_worker.perception import PoseErrorConfig

    record = simulate_episode(_worker["world"], _worker["planner"], _worker["task"], seed, episode_order(seed),
                              PoseErrorConfig(), record_frames=False)
    return {"attrs": record.attrs, "success": record.success}


def simulated_episodes(task: str, episodes: int, cache: Path, workers: int) -> tuple[list[Episode], list[str]]:
    """``collect``'s episodes 0..episodes-1 of ``task``, executed without frames; cached in ``cache``."""
    from planner_client.loop import read_records
    from sim_worker.scene import BLOCK_NAMES

    done = {int(r["attrs"]["seed"]): r for r in read_records(cache)}
    pending = [s for s in range(episodes) if s not in done]
    append_as_done(cache, _simulate_one, pending, done=done, key=lambda record: int(record["attrs"]["seed"]),
                   workers=workers, initializer=_init_worker, initargs=(task,), desc=f"simulate {task}", unit="ep")
    return [(done[s]["attrs"], bool(done[s]["success"])) for s in range(episodes)], list(BLOCK_NAMES)


def _poses_in_order(attrs: dict, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 4)`` true and estimated (x, y, z, yaw) block poses in pick order."""
    order = list(attrs["block_order"])
    true = np.asarray(attrs["true_initial_blocks"], dtype=float)[[names.index(c) for c in order]]
    est = np.array([[*attrs["pose_estimates"][c]["position"], attrs["pose_estimates"][c]["yaw"]] for c in order])
    return true, est


def raw_features(attrs: dict, names: list[str]) -> np.ndarray:
    blocks, estimates = _poses_in_order(attrs, names)
    n = len(blocks)
    pairs = [np.linalg.norm(blocks[i, :2] - blocks[j, :2]) for i in range(n) for j in range(i + 1, n)]
    targets = np.asarray(attrs["place_targets"], dtype=float)
    return np.concatenate([blocks.ravel(), pairs, np.cos(4 * blocks[:, 3]), np.sin(4 * blocks[:, 3]),
                           (estimates[:, :2] - blocks[:, :2]).ravel(), targets[:, :2].ravel()])


def grasp_frame_features(attrs: dict, names: list[str], use_estimates: bool) -> np.ndarray:
    """The scene seen from each planned grasp (see the module docstring).

    Stacking moves the 2nd and 3rd blocks of the order onto the 1st; replacement moves all three.
    ``plan.grasp_yaws`` follows the moved blocks.
    """
    true, est = _poses_in_order(attrs, names)
    scene = est if use_estimates else true
    n = len(scene)
    stacking = attrs["task"] == "stacking"
    moved = list(range(1, n)) if stacking else list(range(n))
    rows: list[float] = []
    if stacking:  # the tower is built where the base is estimated to be
        rows += list(est[0, :2] - scene[0, :2])
    for k, yaw in zip(moved, attrs["grasp_yaws"]):
        c, s = np.cos(yaw), np.sin(yaw)
        to_grasp = np.array([[c, s], [-s, c]])  # world xy -> grasp frame
        rows += list(to_grasp @ (est[k, :2] - scene[k, :2]))  # grasp offset from the block's centre
        rows += [np.cos(4 * (scene[k, 3] - yaw)), np.sin(4 * (scene[k, 3] - yaw))]
        for j in range(n):
            if j == k:
                continue
            rel = to_grasp @ (scene[j, :2] - scene[k, :2])
            still_there = float(j not in moved or moved.index(j) > moved.index(k))
            rows += [rel[0], rel[1], abs(rel[0]), abs(rel[1]), float(np.hypot(*rel)),
                     np.cos(4 * (scene[j, 3] - yaw)), np.sin(4 * (scene[j, 3] - yaw)), still_there]
        if not stacking:  # replacement picks from inside box A: how far its walls are along and across the fingers
            rows += wall_clearances(scene[k, :2], yaw)
    return np.array(rows)


def wall_clearances(xy: np.ndarray, yaw: float) -> list[float]:
    """Distances from ``xy`` (inside box A) to the box's inner walls along +/- the finger axis at ``yaw``
    and +/- the axis across it."""
    from sim_worker.scene import SceneLayout

    box = SceneLayout().box("box_a")
    rel, half = xy - np.asarray(box.centre), np.asarray(box.inner_half)
    out = []
    for angle in (yaw, yaw + np.pi, yaw + np.pi / 2, yaw - np.pi / 2):
        d = np.array([np.cos(angle), np.sin(angle)])
        with np.errstate(divide="ignore"):
            t = np.where(d > 0, (half - rel) / d, np.where(d < 0, (-half - rel) / d, np.inf))
        out.append(float(t.min()))
    return out


def episode_plan(attrs: dict) -> np.ndarray:
    """The episode's plan (T, 16): recorded, or made again from its seed and order (deterministic)."""
    if PLAN_KEY in attrs:
        return np.asarray(attrs[PLAN_KEY])
    from planner_client.tamp import PlannerConfig, TampPlanner
    from planner_client.collect import plan_episode
    from sim_worker.perception import PoseErrorConfig

    if "planner" not in _worker:  # one planner (and its IK model) for every re-made plan
        _worker["planner"] = TampPlanner(PlannerConfig())
    planned = plan_episode(_worker["planner"], attrs["task"], int(attrs["seed"]), tuple(attrs["block_order"]), PoseErrorConfig())
    return np.asarray(planned.plan.actions)


def plan_fk_features(episodes: list[Episode]) -> np.ndarray:
    """:func:`firp.model.plan_geometry.plan_geometry` of each plan (constant columns dropped)."""
    import torch

    from firp.model.plan_geometry import plan_geometry

    plans = torch.from_numpy(np.stack([episode_plan(a) for a, _ in episodes]).astype(np.float64))
    X = plan_geometry(plans).numpy()
    return X[:, X.std(axis=0) > 1e-9]


def features(episodes: list[Episode], names: list[str], kind: str) -> np.ndarray:
    if kind == "plan_fk":
        return plan_fk_features(episodes)
    if kind == "raw":
        return np.array([raw_features(a, names) for a, _ in episodes])
    return np.array([grasp_frame_features(a, names, use_estimates=kind == "grasp_frame_plan") for a, _ in episodes])


def evaluate(X: np.ndarray, y: np.ndarray) -> dict[str, float]:
    cv = StratifiedKFold(5, shuffle=True, random_state=0)
    out = {}
    for name, model in [("logistic_regression", LogisticRegression(max_iter=3000)),
                        ("gradient_boosting", GradientBoostingClassifier(random_state=0))]:
        pred = cross_val_predict(make_pipeline(StandardScaler(), model), X, y, cv=cv)
        out[name] = round(balanced_accuracy_score(y, pred), 3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", nargs="*", type=Path)
    parser.add_argument("--simulate", action="append", default=[], metavar="TASK:N",
                        help="simulate collect's first N episodes of TASK without frames (repeatable)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("docs/results/outcome_predictability.json"))
    args = parser.parse_args()
    if not args.datasets and not args.simulate:
        parser.error("give dataset files and/or --simulate TASK:N")
    sources: list[tuple[str, list[Episode], list[str]]] = []
    for path in args.datasets:
        sources.append((str(path), *dataset_episodes(path)))
    for spec in args.simulate:
        task, _, count = spec.partition(":")
        if task not in ("stacking", "replacement") or not count.isdigit() or int(count) < 10:
            parser.error(f"--simulate {spec!r}: expected TASK:N with TASK stacking or replacement and N >= 10")
        cache = Path(f"runs/predictability-{task}.jsonl")
        sources.append((f"simulated {task} episodes 0-{int(count) - 1} (collect's seeds and orders)",
                        *simulated_episodes(task, int(count), cache, args.workers)))
    results = []
    for source, episodes, names in sources:
        y = np.array([ok for _, ok in episodes])
        for kind in FEATURE_SETS:
            X = features(episodes, names, kind)
            for classifier, score in evaluate(X, y).items():
                results.append({"source": source, "episodes": int(len(y)), "success_rate": round(float(y.mean()), 3),
                                "features": kind, "n_features": int(X.shape[1]), "classifier": classifier,
                                "balanced_accuracy_5fold": score})
    print("| source | episodes | features | classifier | balanced accuracy (5-fold CV) |\n|---|---|---|---|---|")
    for r in results:
        print(f"| {r['source']} | {r['episodes']} | {r['features']} | {r['classifier']} | {r['balanced_accuracy_5fold']:.3f} |")
    command = "experiments/outcome_predictability.py " + " ".join(
        [*map(str, args.datasets), *(f"--simulate {s}" for s in args.simulate)])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": command, "results": results}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
