"""Training speed: seconds per epoch and per model for each method on a dataset's cached features.

Target (issue 3): one model on 640 episodes in <= 10 minutes on 2 cores once features are cached.
Trains each method for a few epochs on the protocol's first split and reports the median epoch
time and the projection to the configured number of epochs.

    python benchmarks/train_speed.py --data data/stacking.h5 --epochs 3 --threads 2
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
from firp.evaluate import METHODS, split_indices
from firp.model.config import EncoderConfig, FIRPConfig
from firp.train import TrainConfig, train_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=3, help="epochs timed per method")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--methods", nargs="+", default=["a_mlp", "a_mlp_image", "gru", "firp_tcr", "oracle"])
    parser.add_argument("--out", type=Path, default=Path("docs/results/train_speed.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base = TrainConfig(threads=args.threads, model=FIRPConfig(encoder=EncoderConfig(image_size=84)))
    data = load_sequences(args.data, base.model.encoder, progress=True)
    train_idx, valid_idx, _ = split_indices(data.labels.numpy(), 0)
    train, valid = data.subset(train_idx), data.subset(valid_idx)
    rows = []
    for name in args.methods:
        cfg = replace(base, epochs=args.epochs, patience=args.epochs, **METHODS[name])
        started = time.perf_counter()
        result = train_model(cfg, train, valid, progress=False)
        wall = time.perf_counter() - started
        per_epoch = wall / len(result.history)
        rows.append({"method": name, "seconds_per_epoch": per_epoch, "epochs_timed": len(result.history),
                     "projected_minutes_at_default_epochs": per_epoch * base.epochs / 60})
        print(f"{name:<12} {per_epoch:7.1f} s/epoch  -> {per_epoch * base.epochs / 60:5.1f} min for {base.epochs} epochs",
              flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "command": f"python benchmarks/train_speed.py --data {args.data} --epochs {args.epochs} --threads {args.threads}",
        "n_train": len(train), "batch_size": base.batch_size, "default_epochs": base.epochs,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__},
        "rows": rows, "median_seconds_per_epoch": statistics.median(r["seconds_per_epoch"] for r in rows)}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
