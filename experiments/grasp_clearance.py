"""How near the open hand comes to the other blocks, and how much of a stacking outcome that decides.

robosuite's three-cube stacking fails mostly one way: a finger or the hand's body comes down on a
neighbouring cube or on the tower and pushes it (the failure modes: the middle or the top cube left on
the table). :func:`firp.model.plan_geometry.hand_clearance` measures that from the plan alone -- the
signed floor-plane distance of the fingertip pads, the fingers and the hand's lowest slab to the nearest
square block among the other grasp points and the tower, with the fingers opened as the plan opens them
(``--plan-description clearance``).
This experiment reads a dataset's plans and reports, on ``firp evaluate``'s splits:

* success rate by the smallest finger clearance of the plan's grasps (a table and a plot);
* a rule with no learning: success iff every grasp's fingers clear the other blocks by at least a
  threshold (chosen on each repeat's training and validation episodes);
* gradient boosting (trained on the training and validation episodes) and a 64-unit MLP (trained as the
  models are: seed and threshold chosen on the validation episodes) on the grasp-frame description, on
  the clearance, and on both -- what each kind of learner takes from each, the yardstick for the
  models that read them (``--plan-description``);
* the learning curve of gradient boosting on both and of the MLP on the clearance (``--fractions``).

    python -m experiments.grasp_clearance --data data/robosuite_stack_three.h5 \\
        --out docs/results/robosuite_stack_three_grasp_clearance.json \\
        --plot docs/results/robosuite_stack_three_grasp_clearance.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from firp.core.episodes import EpisodeDataset
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy, choose_threshold

#: bin edges (metres) of the smallest finger clearance
BINS = (-np.inf, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02, np.inf)


def describe(actions: np.ndarray, max_picks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(N, T, 16)`` plans -> the grasp-frame description ``(N, G)``, the clearance ``(N, 6 P)`` and each
    plan's smallest fingertip-pad or finger clearance over its grasps ``(N,)``."""
    import torch

    from firp.model.plan_geometry import geometry_dim, plan_geometry

    full = plan_geometry(torch.as_tensor(actions, dtype=torch.float64), None, max_picks, description="both").numpy()
    G = geometry_dim(max_picks)
    description, clearance = full[:, :G], full[:, G:]
    present = description[:, ::G // max_picks][:, :max_picks] > 0  # each pick's presence flag
    at_grasps = clearance.reshape(len(full), max_picks, 6)[:, :, :2].min(axis=2)  # (N, P): pads and fingers
    return description, clearance, np.where(present, at_grasps, np.inf).min(axis=1)


def by_bins(finger: np.ndarray, labels: np.ndarray) -> list[dict]:
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        inside = (finger >= lo) & (finger < hi)
        rows.append({"from_m": None if np.isinf(lo) else lo, "to_m": None if np.isinf(hi) else hi,
                     "plans": int(inside.sum()),
                     "success_rate": float(labels[inside].mean()) if inside.any() else None})
    return rows


def plot(bins: list[dict], finger: np.ndarray, labels: np.ndarray, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    edges = np.linspace(-0.03, 0.06, 37)
    clipped = np.clip(finger, edges[0], edges[-1])
    left.hist([clipped[labels], clipped[~labels]], bins=edges, stacked=True, color=["tab:green", "tab:red"],
              label=["success", "failure"])
    left.axvline(0.0, color="k", lw=0.8)
    left.set_xlabel("smallest finger clearance over the plan's grasps (m; < 0: overlap)")
    left.set_ylabel("plans")
    left.legend()
    names = [("< " if b["from_m"] is None else f"{100 * b['from_m']:g}") + ("" if b["to_m"] is None or b["from_m"] is None
             else "..") + ("+" if b["to_m"] is None else f"{100 * b['to_m']:g}") for b in bins]
    rates = [np.nan if b["success_rate"] is None else b["success_rate"] for b in bins]
    right.bar(range(len(bins)), rates, color="tab:blue")
    for i, b in enumerate(bins):
        right.text(i, (rates[i] if np.isfinite(rates[i]) else 0) + 0.02, str(b["plans"]), ha="center", fontsize=8)
    right.set_xticks(range(len(bins)), names, fontsize=8)
    right.set_xlabel("smallest finger clearance (cm)")
    right.set_ylabel("success rate (plans above each bar)")
    right.set_ylim(0, 1.1)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def mlp_score(X: np.ndarray, labels: np.ndarray, train: np.ndarray, valid: np.ndarray, test: np.ndarray,
              seeds: int = 3) -> float:
    """Test balanced accuracy of a 64-unit MLP on standardised ``X``, as the models train: on the training
    episodes, the seed and the threshold chosen on the validation episodes."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    best = None
    for seed in range(seeds):
        model = make_pipeline(StandardScaler(), MLPClassifier((64,), alpha=1e-2, max_iter=400, random_state=seed))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            model.fit(X[train], labels[train])
        threshold, valid_score = choose_threshold(labels[valid], model.predict_proba(X[valid])[:, 1])
        if best is None or valid_score > best[0]:
            best = (valid_score, balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= threshold))
    return float(best[1])


def main(argv: list[str] | None = None) -> int:
    from sklearn.ensemble import GradientBoostingClassifier

    from firp.data import stratified_split

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-picks", type=int, default=3)
    parser.add_argument("--fractions", nargs="*", type=float, default=[0.25, 0.5, 0.75],
                        help="also train on these shares of each repeat's training episodes: do they still gain?")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--plot", type=Path, default=None)
    args = parser.parse_args(argv)
    if not args.data.exists():
        parser.error(f"--data: {args.data} does not exist")
    with EpisodeDataset(args.data) as ds:
        labels = ds.success_labels().astype(bool)
        actions = np.stack([ds.actions(name) for name in ds.demo_names])  # (N, T, 16)
    description, clearance, finger = describe(actions, args.max_picks)
    features = {"description": description, "clearance": clearance,
                "description_and_clearance": np.hstack([description, clearance])}
    rows = []
    for repeat in range(args.repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        seen = np.concatenate([train, valid])
        threshold, _ = choose_threshold(labels[seen], finger[seen])
        row = {"repeat": repeat, "finger_clearance_rule": balanced_accuracy(labels[test], finger[test] >= threshold),
               "finger_clearance_threshold_m": float(threshold)}
        for name, X in features.items():
            model = GradientBoostingClassifier(random_state=repeat).fit(X[seen], labels[seen])
            row[f"{name}_gradient_boosting"] = balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)
            row[f"{name}_mlp"] = mlp_score(X, labels, train, valid, test)
        for fraction in args.fractions:  # the learning curve of the two best learners
            share, _ = stratified_split(labels[train].astype(int), 1.0 - fraction, seed=repeat)
            part = np.concatenate([train[share], valid])
            X = features["description_and_clearance"]
            model = GradientBoostingClassifier(random_state=repeat).fit(X[part], labels[part])
            row[f"description_and_clearance_gradient_boosting@{fraction:g}"] = balanced_accuracy(
                labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)
            row[f"clearance_mlp@{fraction:g}"] = mlp_score(clearance, labels, train[share], valid, test)
        rows.append(row)
        print(f"repeat {repeat}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "repeat"))
    summary = {k: [float(np.mean([r[k] for r in rows])), float(np.std([r[k] for r in rows], ddof=1))]
               for k in rows[0] if k != "repeat"}
    bins = by_bins(finger, labels)
    print("smallest finger clearance -> success rate:")
    for b in bins:
        print(f"  [{b['from_m']}, {b['to_m']}): {b['plans']} plans, "
              f"{'-' if b['success_rate'] is None else format(b['success_rate'], '.3f')}")
    command = f"python -m experiments.grasp_clearance --data {args.data} --out {args.out}" + (
        f" --plot {args.plot}" if args.plot else "")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "episodes": len(labels), "training_episodes": len(train),
                                    "validation_episodes": len(valid), "rows": rows, "mean_std": summary,
                                    "bins": bins, "command": command}, indent=1))
    if args.plot:
        plot(bins, finger, labels, args.plot, f"{args.data.stem}: the open fingers' clearance to the other blocks")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
