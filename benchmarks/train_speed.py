"""Training speed: seconds per epoch and per model for each method on a dataset's cached features.

Target: one model on 640 episodes in <= 10 minutes on 2 cores once features are cached.
Trains each method (a preset's recipe, ``--preset``; the committed figures are ``product`` without the
plan's description, ``--no-plan-geometry``) for a few epochs
on the protocol's first split and reports the median epoch time, its projection to the product runs'
epoch budget (``--budget-epochs``, 80) and to a tuning study of ``--trials`` such models.

    python benchmarks/train_speed.py --data data/stacking.h5 --epochs 3 --threads 2 --no-plan-geometry
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from firp.data import load_sequences
from firp.evaluate import method_config, split_indices
from firp.presets import PRESETS
from firp.train import train_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=3, help="epochs timed per method")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--methods", nargs="+", default=["a_mlp", "a_mlp_image", "gru", "firp_tcr", "oracle"])
    parser.add_argument("--budget-epochs", type=int, default=80, help="epochs of a product training run")
    parser.add_argument("--trials", type=int, default=6, help="models in a tuning study")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="product")
    parser.add_argument("--plan-geometry", action=argparse.BooleanOptionalAction, default=None,
                        help="override the preset's plan description")
    parser.add_argument("--out", type=Path, default=Path("docs/results/train_speed.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base = replace(PRESETS[args.preset].with_overrides(plan_geometry=args.plan_geometry), threads=args.threads,
                   epochs=args.budget_epochs)
    data = load_sequences(args.data, base.model.encoder, progress=True)
    train_idx, valid_idx, _ = split_indices(data.labels.numpy(), 0)
    train, valid = data.subset(train_idx), data.subset(valid_idx)
    rows = []
    print(f"| method | s / epoch | min / model ({base.epochs} epochs) | min / study ({args.trials} models) |")
    print("|---|---|---|---|")
    for name in args.methods:
        cfg = method_config(name, replace(base, epochs=args.epochs, patience=args.epochs))
        started = time.perf_counter()
        result = train_model(cfg, train, valid, progress=False)
        wall = time.perf_counter() - started
        per_epoch = wall / len(result.history)
        rows.append({"method": name, "seconds_per_epoch": round(per_epoch, 2), "epochs_timed": len(result.history),
                     "projected_minutes_per_model": round(per_epoch * base.epochs / 60, 2),
                     "projected_minutes_per_study": round(per_epoch * base.epochs * args.trials / 60, 1)})
        print(f"| {name} | {per_epoch:.2f} | {per_epoch * base.epochs / 60:.1f} | "
              f"{per_epoch * base.epochs * args.trials / 60:.0f} |", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "command": f"python benchmarks/train_speed.py --data {args.data} --epochs {args.epochs} --threads {args.threads} "
                   f"--budget-epochs {args.budget_epochs} --trials {args.trials} --preset {args.preset}"
                   + ("" if args.plan_geometry is None else " --plan-geometry" if args.plan_geometry else " --no-plan-geometry"),
        "n_train": len(train), "batch_size": base.batch_size, "budget_epochs": base.epochs,
        "model": base.model.to_dict(),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__},
        "rows": rows, "median_seconds_per_epoch": statistics.median(r["seconds_per_epoch"] for r in rows)}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
