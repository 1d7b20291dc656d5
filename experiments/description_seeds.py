"""How much of a small MLP's score on the plan's description is the draw of its seeds and threshold.

``experiments.grasp_clearance`` scores a 64-unit scikit-learn MLP on a description the way the models
train: three seeds, the one best on the validation episodes, its threshold chosen there too. On robosuite's
three-cube stacking (2000 episodes, ``sized_clearance_and_heights``) that gave 0.893 -- exactly the paper's
FIRP - 0.03 -- while the product's heads on the same 27 numbers stay near 0.87. This experiment asks how
much of that 0.893 the learner earns and how much the draw gives: on ``firp evaluate``'s splits it trains
``--seeds`` MLPs per repeat (seeds 0..N-1, the same recipe) and reports, as means over repeats and seeds
(or over the disjoint groups of three seeds):

* one seed at threshold 0.5, and at the threshold chosen on the validation episodes;
* the best of three seeds by validation balanced accuracy (the recipe of ``grasp_clearance``), at 0.5 and
  at the validation threshold;
* the mean probability of three seeds and of all of them, at 0.5 and at the validation threshold (an
  ensemble, as the FIRP ensemble averages its members).

With ``--protocol`` it also reads ``firp evaluate`` records and reports every method's test balanced
accuracy at 0.5 (the protocol's table) and at the threshold chosen on its validation scores (what a
bundle uses: ``firp tune --export`` chooses the threshold there).

With ``--fractions`` it repeats the study on stratified shares of each split's training episodes (the
validation and test episodes unchanged, the share fixed per split and nested: 1/8 inside 1/4 inside 1/2):
a learning curve of what the plan holds -- how much one more doubling of the episodes is worth before
anyone collects it. ``--target`` draws the bar to clear, ``--plot`` the curve.

    python -m experiments.description_seeds --data data/robosuite_stack_three_workspaceview_2000.h5 \\
        --description table_sized_clearance_and_heights --repeats 6 --fractions 0.125 0.25 0.5 \\
        --target 0.893 --out runs/description_curve.json --plot runs/description_curve.png

    python -m experiments.description_seeds --data data/robosuite_stack_three_workspaceview_2000.h5 \\
        --protocol docs/results/robosuite_stack_three_2000_sized_clearance_and_heights_protocol.json \\
        --out docs/results/robosuite_stack_three_2000_description_seeds.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from experiments.grasp_clearance import described, fit_mlp
from firp.core.episodes import EpisodeDataset
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy, choose_threshold

#: the descriptions this experiment can read (the product's ``--plan-description`` names)
DESCRIPTIONS = ("sized_clearance_and_heights", "table_sized_clearance_and_heights", "clearance_and_heights")
GROUP = 3  # seeds per group: grasp_clearance's best-of-three
#: the learning curve's two lines: one model as the protocol scores it, and the seeds' ensemble as a bundle would
CURVE_RECIPES = ("one seed, threshold 0.5", "mean of all {seeds} seeds, validation threshold")


def seed_scores(X: np.ndarray, labels: np.ndarray, train: np.ndarray, valid: np.ndarray, seeds: int,
                ) -> tuple[np.ndarray, np.ndarray]:
    """Probabilities of ``seeds`` MLPs (grasp_clearance's :func:`fit_mlp`, seeds 0..N-1) trained on ``train``:
    on the validation episodes (seeds, n_valid) and on every episode (seeds, N; index it with the test
    episodes)."""
    p_valid, p_all = [], []
    for seed in range(seeds):
        model = fit_mlp(X[train], labels[train], seed)
        p_valid.append(model.predict_proba(X[valid])[:, 1])
        p_all.append(model.predict_proba(X)[:, 1])
    return np.array(p_valid), np.array(p_all)


def scored(y_valid: np.ndarray, p_valid: np.ndarray, y_test: np.ndarray, p_test: np.ndarray,
           valid_threshold: bool) -> tuple[float, float]:
    """(validation, test) balanced accuracy at 0.5 or at the threshold best on the validation episodes."""
    threshold = choose_threshold(y_valid, p_valid)[0] if valid_threshold else 0.5
    return balanced_accuracy(y_valid, p_valid >= threshold), balanced_accuracy(y_test, p_test >= threshold)


def recipes(y_valid: np.ndarray, p_valid: np.ndarray, y_test: np.ndarray, p_test: np.ndarray
            ) -> dict[str, list[float]]:
    """Test balanced accuracy of every way of using ``p_valid`` (S, V) / ``p_test`` (S, N) seeds' scores."""
    seeds = len(p_valid)
    out: dict[str, list[float]] = {}
    for valid_threshold, at in ((False, "threshold 0.5"), (True, "validation threshold")):
        out[f"one seed, {at}"] = [scored(y_valid, p_valid[s], y_test, p_test[s], valid_threshold)[1]
                                  for s in range(seeds)]
        groups = [list(range(g, g + GROUP)) for g in range(0, seeds - GROUP + 1, GROUP)]
        best, mean = [], []
        for group in groups:
            each = [scored(y_valid, p_valid[s], y_test, p_test[s], valid_threshold) for s in group]
            best.append(max(each, key=lambda vt: vt[0])[1])
            mean.append(scored(y_valid, p_valid[group].mean(0), y_test, p_test[group].mean(0), valid_threshold)[1])
        out[f"best of {GROUP} seeds, {at}"] = best
        out[f"mean of {GROUP} seeds, {at}"] = mean
        out[f"mean of all {seeds} seeds, {at}"] = [scored(y_valid, p_valid.mean(0), y_test, p_test.mean(0),
                                                          valid_threshold)[1]]
    return out


def training_share(labels: np.ndarray, train: np.ndarray, fraction: float, repeat: int) -> np.ndarray:
    """A stratified ``fraction`` of the training episodes ``train``: each class's episodes in an order fixed by
    the split (``repeat``), the first ``fraction`` of each (at least one), so smaller shares nest in larger
    ones and every share keeps the training set's class balance."""
    if fraction >= 1.0:
        return train
    rng = np.random.default_rng(10_000 + repeat)
    keep = []
    for label in (False, True):
        members = rng.permutation(train[labels[train] == label])
        keep.append(members[:max(1, round(fraction * len(members)))])
    return np.sort(np.concatenate(keep))


def summarize(per_repeat: list[dict[str, list[float]]]) -> dict[str, dict[str, float]]:
    """Mean, std, min, max and count of every recipe's test balanced accuracies over the repeats."""
    summary = {}
    for name in per_repeat[0]:
        values = np.concatenate([r[name] for r in per_repeat])
        summary[name] = {"mean": float(values.mean()), "std": float(values.std()), "min": float(values.min()),
                         "max": float(values.max()), "n": int(values.size)}
    return summary


def study(X: np.ndarray, labels: np.ndarray, repeats: int, seeds: int, fraction: float = 1.0,
          ) -> tuple[list[dict[str, list[float]]], list[int]]:
    """Every recipe's test balanced accuracies per repeat, the MLPs trained on ``fraction`` of each split's
    training episodes; and the number of training episodes per repeat."""
    per_repeat, sizes = [], []
    for repeat in range(repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        train = training_share(labels, train, fraction, repeat)
        p_valid, p_all = seed_scores(X, labels, train, valid, seeds)
        scores = recipes(labels[valid], p_valid, labels[test], p_all[:, test])
        per_repeat.append(scores)
        sizes.append(len(train))
        print(f"share {fraction:g}, repeat {repeat} ({len(train)} training episodes): "
              + ", ".join(f"{k} {np.mean(v):.3f}" for k, v in scores.items()), flush=True)
    return per_repeat, sizes


def plot_curve(curve: list[dict], seeds: int, target: float | None, path: Path, title: str) -> None:
    """Test balanced accuracy against training episodes (log scale), one line per curve recipe, the repeats'
    spread as error bars, the target as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    x = [point["train_episodes"] for point in curve]
    for recipe in CURVE_RECIPES:
        name = recipe.format(seeds=seeds)
        ax.errorbar(x, [p["summary"][name]["mean"] for p in curve], yerr=[p["summary"][name]["std"] for p in curve],
                    marker="o", capsize=3, label=name)
    if target is not None:
        ax.axhline(target, color="grey", linestyle="--", label=f"target {target:.3f}")
    ax.set_xscale("log", base=2)
    ax.set_xticks(x, [str(round(v)) for v in x])
    ax.set_xlabel("training episodes per split (validation and test unchanged)")
    ax.set_ylabel("test balanced accuracy")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def protocol_thresholds(path: Path) -> dict[str, dict[str, float]]:
    """Every method of a ``firp evaluate`` record: mean test balanced accuracy at 0.5 and at its validation
    threshold over the repeats."""
    record = json.loads(path.read_text())
    by_method: dict[str, list[dict]] = {}
    for row in record["rows"]:
        if "test_balanced_accuracy_valid_threshold" in row:
            by_method.setdefault(row["method"], []).append(row)
    return {method: {"repeats": len(rows),
                     "at_0.5": float(np.mean([r["test_balanced_accuracy"] for r in rows])),
                     "at_validation_threshold": float(np.mean([r["test_balanced_accuracy_valid_threshold"]
                                                               for r in rows]))}
            for method, rows in by_method.items()}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--description", choices=sorted(DESCRIPTIONS), default="sized_clearance_and_heights")
    parser.add_argument("--fractions", type=float, nargs="+", default=None, metavar="F",
                        help="also train on these stratified shares (0 < F < 1) of each split's training episodes")
    parser.add_argument("--target", type=float, default=None, help="the balanced accuracy to clear (with --fractions)")
    parser.add_argument("--plot", type=Path, default=None, help="draw the learning curve here (PNG; with --fractions)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=12, help=f"MLPs per repeat (a multiple of {GROUP})")
    parser.add_argument("--protocol", type=Path, nargs="*", default=[],
                        help="firp evaluate records (JSON) to report at 0.5 and at the validation threshold")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if not args.data.exists():
        parser.error(f"--data: {args.data} does not exist")
    if args.seeds < GROUP or args.seeds % GROUP:
        parser.error(f"--seeds: give a positive multiple of {GROUP}, got {args.seeds}")
    if args.repeats < 1:
        parser.error(f"--repeats: at least 1, got {args.repeats}")
    if args.fractions is not None and not all(0.0 < f < 1.0 for f in args.fractions):
        parser.error(f"--fractions: every share must lie strictly between 0 and 1, got {args.fractions}")
    if args.fractions is not None and len(set(args.fractions)) != len(args.fractions):
        parser.error(f"--fractions: give each share once, got {args.fractions}")
    for flag in ("plot", "target"):
        if getattr(args, flag) is not None and args.fractions is None:
            parser.error(f"--{flag}: draws or judges the learning curve, so it needs --fractions")
    missing = [str(p) for p in args.protocol if not p.exists()]
    if missing:
        parser.error(f"--protocol: no such record: {', '.join(missing)}")

    with EpisodeDataset(args.data) as ds:
        labels = ds.success_labels().astype(bool)
        actions = np.stack([ds.actions(name) for name in ds.demo_names])  # (N, T, 16)
    X = described(actions, 3, args.description)
    per_repeat, full_sizes = study(X, labels, args.repeats, args.seeds)
    summary = summarize(per_repeat)
    print(f"\n{args.description}, {len(labels)} episodes, {args.repeats} repeats x {args.seeds} seeds")
    print(f"{'recipe':48s} {'mean':>6s} {'std':>6s} {'min':>6s} {'max':>6s} {'n':>3s}")
    for name, stats in summary.items():
        print(f"{name:48s} {stats['mean']:6.3f} {stats['std']:6.3f} {stats['min']:6.3f} {stats['max']:6.3f} "
              f"{stats['n']:3d}")
    curve = []
    if args.fractions:
        for fraction in sorted(args.fractions):
            shares, sizes = study(X, labels, args.repeats, args.seeds, fraction)
            curve.append({"fraction": fraction, "train_episodes": float(np.mean(sizes)), "summary": summarize(shares)})
        curve.append({"fraction": 1.0, "train_episodes": float(np.mean(full_sizes)),
                      "summary": summary})
        lines = [recipe.format(seeds=args.seeds) for recipe in CURVE_RECIPES]
        print("\nlearning curve: training episodes per split -> " + " | ".join(lines))
        for point in curve:
            print(f"  {point['train_episodes']:7.0f} (share {point['fraction']:g}): "
                  + " | ".join(f"{point['summary'][name]['mean']:.3f} ± {point['summary'][name]['std']:.3f}"
                               for name in lines))
        if args.target is not None:
            print(f"  target {args.target:.3f}")
        if args.plot is not None:
            plot_curve(curve, args.seeds, args.target, args.plot,
                       f"{args.data.name}\na small MLP on the plan's {args.description}")
            print(f"wrote {args.plot}")
    protocols = {str(p): protocol_thresholds(p) for p in args.protocol}
    for path, methods in protocols.items():
        print(f"\n{path}: method, test balanced accuracy at 0.5 / at the validation threshold")
        for method, m in methods.items():
            print(f"  {method:14s} {m['at_0.5']:.3f} / {m['at_validation_threshold']:.3f}  ({m['repeats']} repeats)")
    report = {"command": "python -m experiments.description_seeds " + shlex.join(argv), "data": str(args.data),
              "episodes": len(labels), "successes": int(labels.sum()), "description": args.description,
              "repeats": args.repeats, "seeds": args.seeds, "summary": summary,
              "per_repeat": per_repeat, "protocols": protocols,
              **({"curve": curve, "target": args.target} if curve else {})}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
