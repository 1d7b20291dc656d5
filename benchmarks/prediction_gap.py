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

    .venv/bin/python benchmarks/prediction_gap.py --data data/stacking.h5 \
        --eval-dir runs/eval-stacking-geometry --out docs/results/prediction_gap_stacking_geometry.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from firp.data import SequenceData, load_sequences
from firp.evaluate import BASELINES, FIRP_VARIANTS, split_indices
from firp.metrics import balanced_accuracy, choose_threshold
from firp.model.baselines import build_model
from firp.train import TrainConfig, _with_loss_weights, predict

SOURCES = ("predicted", "real", "first_only")
TARGET_MARGIN = 0.05  # the bar: the FIRP ensemble >= best non-oracle baseline + 0.05


def load_trained(checkpoint: Path) -> torch.nn.Module:
    """The best-epoch model of a finished ``firp.evaluate`` run (safetensors + its JSON config)."""
    state = json.loads((checkpoint / "state.json").read_text())
    if not state.get("finished"):
        raise SystemExit(f"{checkpoint}: training did not finish; run firp.evaluate to the end first")
    cfg = TrainConfig.from_dict(state["config"])
    model = build_model(cfg.kind, _with_loss_weights(cfg))
    model.load_state_dict(load_file(checkpoint / "best.safetensors"))  # normaliser/geometry stats are buffers
    return model.eval()


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


def scored(y_valid: np.ndarray, p_valid: np.ndarray, y_test: np.ndarray, p_test: np.ndarray) -> dict:
    threshold, _ = choose_threshold(y_valid, p_valid)
    return {"test_balanced_accuracy": balanced_accuracy(y_test, p_test >= 0.5),
            "test_balanced_accuracy_valid_threshold": balanced_accuracy(y_test, p_test >= threshold)}


def mean_std(values: list[float]) -> str:
    """Mean ± sample std, as firp.evaluate's table writes them."""
    if not values:
        return "—"
    return f"{statistics.mean(values):.3f} ± {statistics.stdev(values) if len(values) > 1 else 0.0:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="the dataset the evaluation ran on")
    parser.add_argument("--eval-dir", type=Path, required=True, help="a firp.evaluate results directory")
    parser.add_argument("--cache-dir", type=Path, default=Path("data/cache"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True, help="JSON to write")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = [json.loads(p.read_text()) for p in sorted(args.eval_dir.glob("r*-*.json"))]
    firp_rows = [r for r in rows if r["method"] in FIRP_VARIANTS]
    if not firp_rows:
        print(f"--eval-dir: no finished FIRP runs ({', '.join(FIRP_VARIANTS)}) in {args.eval_dir}", file=sys.stderr)
        return 2
    encoder = TrainConfig.from_dict(firp_rows[0]["config"]).model.encoder
    data = load_sequences(args.data, encoder, args.cache_dir, progress=False)
    labels = data.labels.numpy() > 0.5

    per_run, members = [], {}  # members[repeat][source] = [(p_valid, p_test), ...]
    for row in firp_rows:
        repeat, method = row["repeat"], row["method"]
        _, valid_idx, test_idx = split_indices(data.labels.numpy(), repeat)
        if test_idx.tolist() != row["test_index"]:
            raise SystemExit(f"{args.eval_dir}: repeat {repeat}'s test split differs from --data's: another dataset?")
        model = load_trained(args.eval_dir / f"r{repeat}-{method}" / "checkpoint")
        valid, test = data.subset(valid_idx), data.subset(test_idx)
        entry = {"repeat": repeat, "method": method}
        for source in SOURCES:
            p_valid, p_test = head_scores(model, valid, source), head_scores(model, test, source)
            entry[source] = scored(labels[valid_idx], p_valid, labels[test_idx], p_test)
            members.setdefault(repeat, {}).setdefault(source, []).append((p_valid, p_test))
            if source == "predicted":  # the recomputed inference path must be the evaluation's
                entry["max_abs_diff_to_recorded_scores"] = float(np.max(np.abs(p_test - np.array(row["test_scores"]))))
        per_run.append(entry)
        print(f"repeat {repeat} {method}: " + ", ".join(
            f"{s} {entry[s]['test_balanced_accuracy']:.3f}" for s in SOURCES), flush=True)

    ensemble = []
    for repeat, by_source in sorted(members.items()):
        _, valid_idx, test_idx = split_indices(data.labels.numpy(), repeat)
        entry = {"repeat": repeat, "members": len(by_source["predicted"])}
        for source, pairs in by_source.items():
            p_valid = np.mean([p for p, _ in pairs], axis=0)
            p_test = np.mean([p for _, p in pairs], axis=0)
            entry[source] = scored(labels[valid_idx], p_valid, labels[test_idx], p_test)
        ensemble.append(entry)

    repeats = sorted(members)
    baseline_rows = [r for r in rows if r["method"] in BASELINES and r["repeat"] in repeats]
    baselines = {m: [r["test_balanced_accuracy"] for r in baseline_rows if r["method"] == m]
                 for m in BASELINES if any(r["method"] == m for r in baseline_rows)}
    oracle = [r["test_balanced_accuracy"] for r in rows if r["method"] == "oracle" and r["repeat"] in repeats]
    best_name = max(baselines, key=lambda m: np.mean(baselines[m])) if baselines else None
    bar = float(np.mean(baselines[best_name])) + TARGET_MARGIN if best_name else None

    lines = [f"| FIRP head on | {' | '.join(sorted({e['method'] for e in per_run}))} | ensemble |", "|---|"]
    methods = sorted({e["method"] for e in per_run})
    lines[1] += "---|" * (len(methods) + 1)
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
        print(f"target (best baseline {best_name} + {TARGET_MARGIN}) = {bar:.3f}; "
              f"FIRP ensemble with a perfect world model (real features) = {real:.3f}")
    diffs = [e["max_abs_diff_to_recorded_scores"] for e in per_run]
    print(f"recomputed inference scores vs recorded: max |diff| {max(diffs):.2e}")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "command": f"benchmarks/prediction_gap.py --data {args.data} --eval-dir {args.eval_dir} --out {args.out}",
        "dataset_hash": data.dataset_hash, "repeats": repeats, "sources": SOURCES,
        "per_run": per_run, "ensemble": ensemble,
        "baselines_test_balanced_accuracy": baselines, "oracle_test_balanced_accuracy": oracle,
        "best_baseline": best_name, "target": bar, "table": table,
    }, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
