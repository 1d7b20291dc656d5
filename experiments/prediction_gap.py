"""How much would FIRP gain from a perfect world model? Its head on predicted vs real future features.

FIRP classifies a plan from ``[e_1, ê_2..ê_T]``, the features its RSSM predicts from the initial image
under the plan. Its success head is also trained on the *executed* frames' features
``[e_1, e_2..e_T]`` (the paper's L_ce), so the same trained head can score three sequences of the
held-out test episodes:

* ``predicted`` -- the open loop, i.e. what inference computes (re-computed here; it must equal the
  scores the evaluation recorded, which the script checks);
* ``real`` -- the executed frames' features: FIRP with a perfect world model, an upper bound on
  what better prediction could give this head;
* ``first_only`` -- ``e_1`` repeated over the whole plan: no future information at all, what the
  head gets from the initial image and the plan's description alone.

``real − predicted`` is the room a better world model has; ``predicted − first_only`` what the
world model's predictions add now. Reads the checkpoints that ``python -m firp.evaluate`` leaves in
its results directory (no training), compares with the baselines of the same run, prints a table
and writes JSON.

    .venv/bin/python -m experiments.prediction_gap --data data/stacking.h5 \
        --eval-dir runs/eval-stacking-geometry --out docs/results/prediction_gap_stacking_geometry.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from experiments.tcr_ablation import find_checkpoints, load_model
from firp.core.episodes import EpisodeDataset
from firp.data import SequenceData, load_sequences
from firp.evaluate import BASELINES, FIRP_VARIANTS, best_baseline, ensemble_rows, held_out_metrics, \
    mean_std, split_indices, target_margin
from firp.train import predict

SOURCES = ("predicted", "real", "first_only")
REPORTED = ("test_balanced_accuracy", "test_balanced_accuracy_valid_threshold")


@torch.inference_mode()
def head_scores(model: torch.nn.Module, data: SequenceData, source: str, batch_size: int = 128) -> np.ndarray:
    """Success probabilities (N,) of FIRP's head on one of :data:`SOURCES`."""
    if source == "predicted":
        return predict(model, data, batch_size)
    out = []
    for start in range(0, len(data), batch_size):
        feats = data.features[start:start + batch_size]  # (B, T, Db)
        if source == "first_only":
            feats = feats[:, :1].expand_as(feats)  # every frame = the initial image
        logits = model.forward_train(feats, data.actions[start:start + batch_size], sample=False)["logits"]
        out.append(torch.sigmoid(logits))
    return torch.cat(out).numpy()


def reported(metrics: dict) -> dict:
    """The balanced accuracies this benchmark reports, of a :func:`held_out_metrics` / ensemble row."""
    return {key: metrics[key] for key in REPORTED}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="the dataset the evaluation ran on")
    parser.add_argument("--eval-dir", type=Path, required=True, help="a firp.evaluate results directory")
    parser.add_argument("--cache-dir", type=Path, default=Path("data/cache"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True, help="JSON to write")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    checkpoints, skipped = find_checkpoints(args.eval_dir, FIRP_VARIANTS) if args.eval_dir.is_dir() else ([], [])
    for message in skipped:
        print(message, file=sys.stderr)
    if not checkpoints:
        print(f"--eval-dir: no finished FIRP runs ({', '.join(FIRP_VARIANTS)}) in {args.eval_dir}", file=sys.stderr)
        return 2
    data = load_sequences(args.data, checkpoints[0].config.model.encoder, args.cache_dir, progress=False)
    labels = data.labels.numpy() > 0.5

    per_run = []
    scored_rows: dict[str, list[dict]] = {source: [] for source in SOURCES}  # per source, rows as ensemble_rows reads
    for ckpt in checkpoints:
        _, valid_idx, test_idx = split_indices(data.labels.numpy(), ckpt.repeat)
        if test_idx.tolist() != ckpt.row["test_index"]:
            raise SystemExit(f"{args.eval_dir}: repeat {ckpt.repeat}'s test split differs from --data's: another dataset?")
        model = load_model(ckpt)
        valid, test = data.subset(valid_idx), data.subset(test_idx)
        entry = {"repeat": ckpt.repeat, "method": ckpt.method}
        for source in SOURCES:
            p_valid, p_test = head_scores(model, valid, source), head_scores(model, test, source)
            entry[source] = reported(held_out_metrics(labels[valid_idx], p_valid, labels[test_idx], p_test))
            scored_rows[source].append({
                "method": ckpt.method, "repeat": ckpt.repeat, "valid_index": valid_idx.tolist(),
                "test_index": test_idx.tolist(), "valid_scores": p_valid, "test_scores": p_test, "train_seconds": 0.0})
            if source == "predicted":  # the recomputed inference path must be the evaluation's
                entry["max_abs_diff_to_recorded_scores"] = float(np.max(np.abs(p_test - np.array(ckpt.row["test_scores"]))))
        per_run.append(entry)
        print(f"repeat {ckpt.repeat} {ckpt.method}: " + ", ".join(
            f"{s} {entry[s]['test_balanced_accuracy']:.3f}" for s in SOURCES), flush=True)

    # one variant alone still gets its row: the table's "ensemble" column is then that model
    by_source = {source: ensemble_rows(rows, data.labels.numpy(), min_members=1) for source, rows in scored_rows.items()}
    ensemble = [{"repeat": row["repeat"], "members": len(row["members"]),
                 **{source: reported(by_source[source][i]) for source in SOURCES}}
                for i, row in enumerate(by_source["predicted"])]

    repeats = sorted({c.repeat for c in checkpoints})
    rows = [json.loads(p.read_text()) for p in sorted(args.eval_dir.glob("r*-*.json"))]
    rows = [r for r in rows if r["repeat"] in repeats]
    baselines = {m: [r["test_balanced_accuracy"] for r in rows if r["method"] == m]
                 for m in BASELINES if any(r["method"] == m for r in rows)}
    oracle = [r["test_balanced_accuracy"] for r in rows if r["method"] == "oracle"]
    best = best_baseline(rows)
    with EpisodeDataset(args.data) as dataset:  # the dataset's world sets the margin, as in firp evaluate
        margin = target_margin(dataset.attrs.get("env"))
    bar = best[1] + margin if best else None

    methods = sorted({e["method"] for e in per_run})
    lines = [f"| FIRP head on | {' | '.join(methods)} | ensemble |", "|---|" + "---|" * (len(methods) + 1)]
    for source in SOURCES:
        cells = [mean_std([e[source]["test_balanced_accuracy"] for e in per_run if e["method"] == m]) for m in methods]
        cells.append(mean_std([e[source]["test_balanced_accuracy"] for e in ensemble]))
        lines.append(f"| {source} | {' | '.join(cells)} |")
    table = "\n".join(lines)
    context = ", ".join(f"{m} {mean_std(v)}" for m, v in baselines.items())
    if oracle:
        context += f", oracle {mean_std(oracle)}"
    print(f"\ntest balanced accuracy (threshold 0.5) over repeats {repeats}\n{table}\n\nsame run: {context}")
    if bar is not None:
        real = float(np.mean([e["real"]["test_balanced_accuracy"] for e in ensemble]))
        print(f"target (best baseline {best[0]} + {margin}) = {bar:.3f}; "
              f"FIRP ensemble with a perfect world model (real features) = {real:.3f}")
    diffs = [e["max_abs_diff_to_recorded_scores"] for e in per_run]
    print(f"recomputed inference scores vs recorded: max |diff| {max(diffs):.2e}")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "command": f"experiments/prediction_gap.py --data {args.data} --eval-dir {args.eval_dir} --out {args.out}",
        "dataset_hash": data.dataset_hash, "repeats": repeats, "sources": SOURCES,
        "per_run": per_run, "ensemble": ensemble,
        "baselines_test_balanced_accuracy": baselines, "oracle_test_balanced_accuracy": oracle,
        "best_baseline": best[0] if best else None, "target": bar, "table": table,
    }, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
