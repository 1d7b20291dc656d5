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
  the clearance, on the clearance with each pick's grasp and release heights, and on the description
  and the clearance -- what each kind of learner takes from each, the yardstick for the models that
  read them (``--plan-description``);
* where gradient boosting on the description and the clearance draws from: its feature importance's
  shares on the clearance, on each pick's heights, and on the other grasp-frame numbers;
* learning curves (``--fractions`` of each repeat's training episodes, ``--curves`` which learners on
  which inputs; by default gradient boosting on both and the MLP on the clearance), drawn with
  ``--curve-plot``: do the learners still gain from more episodes, and which input gains most?
  ``--first N`` reads a larger set's first N episodes, so one collection gives both sizes' numbers.

    python -m experiments.grasp_clearance --data data/robosuite_stack_three.h5 \\
        --out docs/results/robosuite_stack_three_grasp_clearance.json \\
        --plot docs/results/robosuite_stack_three_grasp_clearance.png
    python -m experiments.grasp_clearance --data data/robosuite_stack_three_workspaceview_2000.h5 \\
        --curves description_and_clearance:gradient_boosting clearance:mlp description_and_clearance:mlp \\
        --out runs/curves.json --curve-plot runs/curves.png
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from firp.core.episodes import EpisodeDataset
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy, choose_threshold

#: bin edges (metres) of the smallest finger clearance
BINS = (-np.inf, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02, np.inf)
#: the inputs the learners read, and the learners
INPUTS = ("description", "clearance", "clearance_and_heights", "sized_clearance_and_heights",
          "true_sized_clearance_and_heights", "description_and_clearance")
LEARNERS = ("gradient_boosting", "mlp")
#: the learning curves drawn unless --curves says otherwise: the two best learners on 800 episodes
DEFAULT_CURVES = ("description_and_clearance:gradient_boosting", "clearance:mlp")


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


def described(actions: np.ndarray, max_picks: int, description: str, halves: np.ndarray | None = None) -> np.ndarray:
    """``(N, T, 16)`` plans -> the product's ``--plan-description description`` of them ``(N, G)`` as numpy
    (:func:`firp.model.plan_geometry.plan_geometry` in double precision); ``halves`` as it takes them."""
    import torch

    from firp.model.plan_geometry import plan_geometry

    true = None if halves is None else torch.as_tensor(halves, dtype=torch.float64)
    return plan_geometry(torch.as_tensor(actions, dtype=torch.float64), None, max_picks,
                         description=description, halves=true).numpy()


def clearance_and_heights(actions: np.ndarray, max_picks: int) -> np.ndarray:
    """``(N, T, 16)`` plans -> the clearance and each pick's grasp and release heights ``(N, 9 P)``, the
    product's ``--plan-description clearance_and_heights``."""
    return described(actions, max_picks, "clearance_and_heights")


def sized_clearance_and_heights(actions: np.ndarray, max_picks: int, halves: np.ndarray | None = None) -> np.ndarray:
    """``(N, T, 16)`` plans -> the clearance to blocks of the sizes the plan shows and the heights ``(N, 9 P)``,
    the product's ``--plan-description sized_clearance_and_heights``; with ``halves`` ``(N, 1 + P)`` (the base's
    and each pick's block's true half-size) the clearance to blocks of those sizes instead."""
    return described(actions, max_picks, "sized_clearance_and_heights", halves)


def table_sized_clearance_and_heights(actions: np.ndarray, max_picks: int) -> np.ndarray:
    """``(N, T, 16)`` plans -> the clearance to blocks sized from each grasp's height over the table, and the
    heights ``(N, 9 P)``: the product's ``--plan-description table_sized_clearance_and_heights``."""
    return described(actions, max_picks, "table_sized_clearance_and_heights")


def true_halves(ds: EpisodeDataset, names: list[str], max_picks: int) -> np.ndarray | None:
    """Each episode's blocks' half-sizes in the order the plan moves them ``(N, 1 + P)`` -- the tower's base
    first -- from the recorded block order and the scene's cube sizes (robosuite's stacking records both);
    None for a dataset that does not record them."""
    rows = []
    for name in names:
        attrs = ds.demo_attrs(name)
        if "block_order" not in attrs or "cube_half" not in attrs.get("scene", {}):
            return None
        sizes = [float(attrs["scene"]["cube_half"][block]) for block in attrs["block_order"]][:1 + max_picks]
        rows.append(sizes + [0.0] * (1 + max_picks - len(sizes)))
    return np.asarray(rows)


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


def fit_mlp(X: np.ndarray, labels: np.ndarray, seed: int):
    """A 64-unit MLP (L2 0.01, 400 iterations) on standardised ``X``, fitted with seed ``seed``: the small
    learner every analysis of the plan's numbers uses (this one and ``experiments.description_seeds``)."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = make_pipeline(StandardScaler(), MLPClassifier((64,), alpha=1e-2, max_iter=400, random_state=seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return model.fit(X, labels)


def mlp_score(X: np.ndarray, labels: np.ndarray, train: np.ndarray, valid: np.ndarray, test: np.ndarray,
              seeds: int = 3) -> float:
    """Test balanced accuracy of :func:`fit_mlp`, as the models train: on the training episodes, the seed and
    the threshold chosen on the validation episodes."""
    best = None
    for seed in range(seeds):
        model = fit_mlp(X[train], labels[train], seed)
        threshold, valid_score = choose_threshold(labels[valid], model.predict_proba(X[valid])[:, 1])
        if best is None or valid_score > best[0]:
            best = (valid_score, balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= threshold))
    return float(best[1])


def curve(text: str) -> tuple[str, str]:
    """``INPUT:LEARNER`` (argparse type of ``--curves``)."""
    name, _, learner = text.partition(":")
    if name not in INPUTS or learner not in LEARNERS:
        raise argparse.ArgumentTypeError(f"{text!r}: give INPUT:LEARNER, INPUT one of {', '.join(INPUTS)}, "
                                         f"LEARNER one of {', '.join(LEARNERS)}")
    return name, learner


def learner_score(learner: str, X: np.ndarray, labels: np.ndarray, train: np.ndarray, valid: np.ndarray,
                  test: np.ndarray, seed: int) -> float:
    """Test balanced accuracy of ``learner`` on ``X``: gradient boosting fits the training and validation
    episodes (its threshold 0.5), the MLP fits the training ones and chooses on the validation ones."""
    if learner == "mlp":
        return mlp_score(X, labels, train, valid, test)
    from sklearn.ensemble import GradientBoostingClassifier

    seen = np.concatenate([train, valid])
    model = GradientBoostingClassifier(random_state=seed).fit(X[seen], labels[seen])
    return balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)


def importance_shares(description: np.ndarray, clearance: np.ndarray, labels: np.ndarray, seen: np.ndarray,
                      seed: int, max_picks: int) -> dict[str, float]:
    """Where gradient boosting on the description and the clearance draws from: the shares of its feature
    importance on the clearance, on each pick's grasp and release heights (the grasp-frame numbers'
    grasp z, release z and rise, what ``clearance_and_heights`` adds), and on the other grasp-frame numbers."""
    from sklearn.ensemble import GradientBoostingClassifier

    model = GradientBoostingClassifier(random_state=seed).fit(np.hstack([description, clearance])[seen], labels[seen])
    importance = model.feature_importances_
    per_pick = description.shape[1] // max_picks
    heights = [k * per_pick + j for k in range(max_picks) for j in (3, 6, 7)]  # grasp z, release z, rise
    shares = {"clearance": float(importance[description.shape[1]:].sum()), "heights": float(importance[heights].sum())}
    shares["other_grasp_frame"] = float(1.0 - shares["clearance"] - shares["heights"])
    return shares


def plot_curves(curves: list[dict], path: Path, title: str) -> None:
    """Test balanced accuracy (mean and std over the repeats) against training episodes, log-2 axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for c in curves:
        x = [p["training_episodes"] for p in c["points"]]
        mean = np.array([p["mean"] for p in c["points"]])
        std = np.array([p["std"] for p in c["points"]])
        line, = ax.plot(x, mean, marker="o", label=c["name"].replace("_", " ").replace(":", ", "))
        ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.15)
    ax.set_xscale("log", base=2)
    sizes = sorted({p["training_episodes"] for c in curves for p in c["points"]})
    ax.set_xticks(sizes, [str(n) for n in sizes])
    ax.minorticks_off()
    ax.set_xlabel("training episodes per repeat (the validation episodes on top)")
    ax.set_ylabel("test balanced accuracy")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from firp.data import stratified_split

    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--first", type=int, default=None, metavar="N",
                        help="read only the dataset's first N episodes (a larger set's smaller subset: seeds 0..N-1)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-picks", type=int, default=3)
    parser.add_argument("--fractions", nargs="*", type=float, default=[0.25, 0.5, 0.75],
                        help="also train on these shares of each repeat's training episodes: do they still gain?")
    parser.add_argument("--curves", nargs="+", type=curve, default=[curve(c) for c in DEFAULT_CURVES],
                        metavar="INPUT:LEARNER",
                        help=f"the learners whose learning curves are measured (default {' '.join(DEFAULT_CURVES)}; "
                             f"INPUT one of {', '.join(INPUTS)}, LEARNER one of {', '.join(LEARNERS)})")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--curve-plot", type=Path, default=None, help="draw the learning curves here (PNG)")
    args = parser.parse_args(argv)
    if not args.data.exists():
        parser.error(f"--data: {args.data} does not exist")
    bad = [f for f in args.fractions if not 0.0 < f < 1.0]
    if bad:
        parser.error(f"--fractions: each share must lie strictly between 0 and 1 (all of them is always run), got {bad}")
    if args.first is not None and args.first < 10:
        parser.error(f"--first: read at least 10 episodes, got {args.first}")
    with EpisodeDataset(args.data) as ds:
        if args.first is not None and args.first > len(ds.demo_names):
            parser.error(f"--first: {args.data} holds {len(ds.demo_names)} episodes, fewer than {args.first}")
        names = ds.demo_names[:args.first]
        labels = ds.success_labels().astype(bool)[:len(names)]
        actions = np.stack([ds.actions(name) for name in names])  # (N, T, 16)
        halves = true_halves(ds, names, args.max_picks)
    if halves is None and any(name == "true_sized_clearance_and_heights" for name, _ in args.curves):
        parser.error(f"--curves: {args.data} records no block order and cube sizes, so it has no "
                     "true_sized_clearance_and_heights")
    description, clearance, finger = describe(actions, args.max_picks)
    features = {"description": description, "clearance": clearance,
                "clearance_and_heights": clearance_and_heights(actions, args.max_picks),
                "sized_clearance_and_heights": sized_clearance_and_heights(actions, args.max_picks),
                "description_and_clearance": np.hstack([description, clearance])}
    if halves is not None:  # the yardstick: every block's size known, the last one's too
        features["true_sized_clearance_and_heights"] = sized_clearance_and_heights(actions, args.max_picks, halves)
    rows, sizes = [], {}
    for repeat in range(args.repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        seen = np.concatenate([train, valid])
        threshold, _ = choose_threshold(labels[seen], finger[seen])
        row = {"repeat": repeat, "finger_clearance_rule": balanced_accuracy(labels[test], finger[test] >= threshold),
               "finger_clearance_threshold_m": float(threshold)}
        for name, X in features.items():
            for learner in LEARNERS:
                row[f"{name}_{learner}"] = learner_score(learner, X, labels, train, valid, test, repeat)
        for part, share in importance_shares(description, clearance, labels, seen, repeat, args.max_picks).items():
            row[f"gradient_boosting_importance_{part}"] = share
        sizes[1.0] = len(train)
        for fraction in args.fractions:  # the learning curves
            share, _ = stratified_split(labels[train].astype(int), 1.0 - fraction, seed=repeat)
            sizes[fraction] = len(share)
            for name, learner in args.curves:
                row[f"{name}_{learner}@{fraction:g}"] = learner_score(learner, features[name], labels, train[share],
                                                                      valid, test, repeat)
        rows.append(row)
        print(f"repeat {repeat}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "repeat"), flush=True)
    summary = {k: [float(np.mean([r[k] for r in rows])), float(np.std([r[k] for r in rows], ddof=1))]
               for k in rows[0] if k != "repeat"}
    curves = []
    for name, learner in args.curves:
        keys = [(sizes[f], f"{name}_{learner}@{f:g}") for f in sorted(args.fractions)] + [(sizes[1.0], f"{name}_{learner}")]
        curves.append({"name": f"{name}:{learner}", "points": [
            {"training_episodes": n, "mean": summary[k][0], "std": summary[k][1]} for n, k in keys]})
    bins = by_bins(finger, labels)
    print("smallest finger clearance -> success rate:")
    for b in bins:
        print(f"  [{b['from_m']}, {b['to_m']}): {b['plans']} plans, "
              f"{'-' if b['success_rate'] is None else format(b['success_rate'], '.3f')}")
    command = f"python -m experiments.grasp_clearance {shlex.join(argv)}"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "first": args.first, "episodes": len(labels), "training_episodes": len(train),
                                    "validation_episodes": len(valid), "rows": rows, "mean_std": summary,
                                    "curves": curves, "bins": bins, "command": command}, indent=1))
    if args.plot:
        plot(bins, finger, labels, args.plot, f"{args.data.stem}: the open fingers' clearance to the other blocks")
    if args.curve_plot:
        plot_curves(curves, args.curve_plot, f"{args.data.stem} ({len(labels)} plans): learning curves, "
                                             f"{args.repeats} repeats")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
