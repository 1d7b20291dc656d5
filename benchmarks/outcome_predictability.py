"""How predictable is a task's outcome from privileged scene geometry, with this many episodes?

A yardstick for the learned models: from the recorded *ground truth* of each episode -- true initial
block poses in pick order, their pairwise distances, yaw (as cos/sin of 4*yaw: a cube's symmetry),
the perception error the planner worked with, and the place targets -- two standard classifiers
(logistic regression, gradient boosting; scikit-learn) predict success under 5-fold stratified
cross-validation. No model sees this information at inference; if even these stay near chance, the
outcome is a complex function of the geometry that a dataset of this size does not pin down.

    .venv/bin/python benchmarks/outcome_predictability.py data/stacking.h5 data/replacement.h5
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from sklearn.ensemble import GradientBoostingClassifier
from sklearn.linear_model import LogisticRegression
from sklearn.metrics import balanced_accuracy_score
from sklearn.model_selection import StratifiedKFold, cross_val_predict
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from firp.episodes import EpisodeDataset


def geometry_features(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(N, F)`` privileged features and ``(N,)`` success labels of a recorded dataset."""
    rows, labels = [], []
    with EpisodeDataset(path) as ds:
        names = list(ds.attrs["block_names"])
        for demo in ds.demo_names:
            attrs = ds.demo_attrs(demo)
            order = [names.index(c) for c in attrs["block_order"]]
            blocks = np.asarray(attrs["true_initial_blocks"])[order]  # (3, 4) x, y, z, yaw in pick order
            estimates = np.array([attrs["pose_estimates"][c]["position"] for c in attrs["block_order"]])
            pairs = [np.linalg.norm(blocks[i, :2] - blocks[j, :2]) for i in range(3) for j in range(i + 1, 3)]
            targets = np.asarray(attrs["place_targets"])
            rows.append(np.concatenate([
                blocks.ravel(), pairs, np.cos(4 * blocks[:, 3]), np.sin(4 * blocks[:, 3]),
                (estimates[:, :2] - blocks[:, :2]).ravel(), targets[:, :2].ravel(),
            ]))
            labels.append(ds.success(demo))
    return np.array(rows), np.array(labels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("docs/results/outcome_predictability.json"))
    args = parser.parse_args()
    results = []
    for path in args.datasets:
        X, y = geometry_features(path)
        cv = StratifiedKFold(5, shuffle=True, random_state=0)
        for name, model in [("logistic_regression", LogisticRegression(max_iter=2000)),
                            ("gradient_boosting", GradientBoostingClassifier(random_state=0))]:
            pred = cross_val_predict(make_pipeline(StandardScaler(), model), X, y, cv=cv)
            results.append({"dataset": str(path), "episodes": int(len(y)), "features": int(X.shape[1]),
                            "classifier": name, "balanced_accuracy_5fold": round(balanced_accuracy_score(y, pred), 3)})
    print("| dataset | episodes | classifier | balanced accuracy (5-fold CV) |\n|---|---|---|---|")
    for r in results:
        print(f"| {r['dataset']} | {r['episodes']} | {r['classifier']} | {r['balanced_accuracy_5fold']:.3f} |")
    args.out.write_text(json.dumps({"command": "benchmarks/outcome_predictability.py "
                                    + " ".join(map(str, args.datasets)), "results": results}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
