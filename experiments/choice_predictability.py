"""How much of a robosuite outcome the planner's choice, or the plan read in each grasp's frame, tells.

The episodes of a robosuite dataset differ in the planner's choice (the objects' order, the pair of faces
and the height each grasp takes) and in the scene. Three classifiers, each trained on a repeat's training
and validation episodes and tested on its test episodes (``firp evaluate``'s splits), bound what a
learned scorer could take from the plan:

* the training success rate of the episode's order, at the threshold best on the training episodes;
* gradient boosting on the whole choice (each object's place in the order, and each moved object's face
  pair and grasp height) -- what knowing the choice exactly, which the learned models must read from the
  plan's joint targets, gives;
* gradient boosting on the plan's grasp-frame description (:func:`firp.model.plan_geometry.plan_geometry`,
  forward kinematics of the plan's joint targets at each grasp and release: where each grasp closes
  relative to the other objects' grasp points and to the place targets). robosuite's Panda has the
  kinematics of the description's DH model (its grip site within 7 mm of the DH tool point, its fingers
  closing along the same axis), and every number is relative, so its base's place in the world does
  not matter. This is the input the ``product`` preset gives every plan-reading model.

What none reaches is decided by what the plan does not carry: the scene beyond the planner's beliefs.

    python -m experiments.choice_predictability --data data/robosuite_pick_place.h5 \\
        --out docs/results/robosuite_pick_place_choice_predictability.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from firp.core.episodes import EpisodeDataset
from firp.data import stratified_split
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy, choose_threshold

CLASSIFIERS = ("order_success_rate", "choice_gradient_boosting", "plan_geometry_gradient_boosting")


def choice_features(attrs: dict, objects: list[str]) -> list[float]:
    """Each object's place in the order, then each object's face pair and grasp height (``-1`` for an
    object the plan does not move, the tower's base). ``choice`` reads ``<order>:<face pairs>:<heights>``,
    one face digit and one height letter per *moved* object in the order's sequence -- the last ones."""
    order = list(attrs["block_order"])
    _, faces, heights = str(attrs["choice"]).split(":")
    moved = order[len(order) - len(faces):]
    by_object = {name: (float(faces[k]), 1.0 if heights[k] == "h" else 0.0) for k, name in enumerate(moved)}
    return ([float(order.index(name)) for name in objects]
            + [v for name in objects for v in by_object.get(name, (-1.0, -1.0))])


def grasp_frame_features(actions: np.ndarray, max_picks: int) -> np.ndarray:
    """``(N, T, 16)`` raw plans -> ``(N, geometry_dim(max_picks))``, the product preset's description."""
    import torch

    from firp.model.plan_geometry import plan_geometry

    return plan_geometry(torch.as_tensor(actions, dtype=torch.float64), None, max_picks).numpy()


def main(argv: list[str] | None = None) -> int:
    from sklearn.ensemble import GradientBoostingClassifier

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--fractions", nargs="+", type=float, default=[0.25, 0.5, 0.75],
                        help="also train the grasp-frame classifier on these shares of each repeat's training "
                             "episodes (stratified, seeded): does it still gain from more episodes?")
    args = parser.parse_args(argv)
    with EpisodeDataset(args.data) as ds:
        attrs = [ds.demo_attrs(name) for name in ds.demo_names]
        labels = ds.success_labels().astype(bool)
        actions = np.stack([ds.actions(name) for name in ds.demo_names])  # (N, T, 16)
    objects = sorted({name for a in attrs for name in a["block_order"]})
    moved = max(len(str(a["choice"]).split(":")[1]) for a in attrs)
    orders = ["-".join(a["block_order"]) for a in attrs]
    features = {"choice_gradient_boosting": np.array([choice_features(a, objects) for a in attrs]),
                "plan_geometry_gradient_boosting": grasp_frame_features(actions, moved)}
    rows = []
    for repeat in range(args.repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        train = np.concatenate([train, valid])
        overall = labels[train].mean()
        rate = {o: labels[[i for i in train if orders[i] == o]].mean() if any(orders[i] == o for i in train)
                else overall for o in set(orders)}
        threshold, _ = choose_threshold(labels[train], np.array([rate[orders[i]] for i in train]))
        row = {"repeat": repeat,
               "order_success_rate": balanced_accuracy(labels[test], np.array([rate[orders[i]] for i in test]) >= threshold)}
        for name, X in features.items():
            model = GradientBoostingClassifier(random_state=repeat).fit(X[train], labels[train])
            row[name] = balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)
        X = features["plan_geometry_gradient_boosting"]
        for fraction in args.fractions:
            share, _ = stratified_split(labels[train].astype(int), 1.0 - fraction, seed=repeat)
            model = GradientBoostingClassifier(random_state=repeat).fit(X[train[share]], labels[train[share]])
            row[f"plan_geometry_gradient_boosting@{fraction:g}"] = balanced_accuracy(
                labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)
        rows.append(row)
        print(f"repeat {repeat}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "repeat"))
    summary = {k: [float(np.mean([r[k] for r in rows])), float(np.std([r[k] for r in rows], ddof=1))]
               for k in rows[0] if k != "repeat"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "episodes": len(labels), "objects": objects,
                                    "picks_described": moved, "rows": rows, "mean_std": summary,
                                    "training_episodes": len(train),
                                    "command": "python -m experiments.choice_predictability --data "
                                               f"{args.data} --out {args.out}"}, indent=1))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
