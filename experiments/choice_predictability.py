"""How much of a robosuite pick & place outcome the planner's choice alone tells, on the protocol's splits.

The pick & place episodes differ in the planner's choice (the order of the four objects, the pair of faces
and the height each grasp takes) and in the scene. A scorer that *knew* the choice exactly -- which the
learned models must read from 200 steps of joint targets -- would score at most what a classifier of the
choice reaches. Two such classifiers, trained on each repeat's training and validation episodes and tested
on its test episodes (``firp evaluate``'s splits): the training success rate of the episode's order, at
the threshold best on the training episodes; and gradient boosting on the whole choice (each object's
place in the order, face pair and height). What neither reaches is decided by the scene.

    python -m experiments.choice_predictability --data data/robosuite_pick_place.h5 \\
        --out docs/results/robosuite_pick_place_choice_predictability.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from firp.core.episodes import EpisodeDataset
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy, choose_threshold

OBJECTS = ("Milk", "Bread", "Cereal", "Can")


def choice_features(attrs: dict) -> list[float]:
    """Each object's place in the order, then each grasp's face pair and height (from ``choice``:
    ``<order>:<face pairs>:<heights>``, per object in the order's sequence)."""
    order = list(attrs["block_order"])
    _, faces, heights = str(attrs["choice"]).split(":")
    by_object = {name: (int(faces[k]), 1.0 if heights[k] == "h" else 0.0) for k, name in enumerate(order)}
    return [float(order.index(name)) for name in OBJECTS] + [v for name in OBJECTS for v in by_object[name]]


def main(argv: list[str] | None = None) -> int:
    from sklearn.ensemble import GradientBoostingClassifier

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    with EpisodeDataset(args.data) as ds:
        attrs = [ds.demo_attrs(name) for name in ds.demo_names]
        labels = ds.success_labels().astype(bool)
    orders = ["-".join(a["block_order"]) for a in attrs]
    features = np.array([choice_features(a) for a in attrs])
    rows = []
    for repeat in range(args.repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        train = np.concatenate([train, valid])
        overall = labels[train].mean()
        rate = {o: labels[[i for i in train if orders[i] == o]].mean() if any(orders[i] == o for i in train)
                else overall for o in set(orders)}
        threshold, _ = choose_threshold(labels[train], np.array([rate[orders[i]] for i in train]))
        order_ba = balanced_accuracy(labels[test], np.array([rate[orders[i]] for i in test]) >= threshold)
        model = GradientBoostingClassifier(random_state=repeat).fit(features[train], labels[train])
        choice_ba = balanced_accuracy(labels[test], model.predict_proba(features[test])[:, 1] >= 0.5)
        rows.append({"repeat": repeat, "order_success_rate": order_ba, "choice_gradient_boosting": choice_ba})
        print(f"repeat {repeat}: order's success rate {order_ba:.3f}, gradient boosting on the choice {choice_ba:.3f}")
    summary = {k: [float(np.mean([r[k] for r in rows])), float(np.std([r[k] for r in rows], ddof=1))]
               for k in ("order_success_rate", "choice_gradient_boosting")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "episodes": len(labels), "rows": rows,
                                    "mean_std": summary,
                                    "command": "python -m experiments.choice_predictability --data "
                                               f"{args.data} --out {args.out}"}, indent=1))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
