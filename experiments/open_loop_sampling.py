"""Does training FIRP's open loop on means (``LossConfig.open_loop_sample=False``) help it learn sooner?

Retrains one finished tuning trial's config (same split, same seed) with the open loop rolled on
means instead of samples, and prints both validation curves side by side; writes JSON.

    .venv/bin/python -m experiments.open_loop_sampling --data data/stacking.h5 \
        --reference runs/tune-firp-stacking-prod3/trial_0002 --epochs 40
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import torch

from firp.data import load_sequences
from firp.train import TrainConfig, train_model
from firp.tune import tuning_split


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--reference", type=Path, required=True, help="a finished trial's checkpoint directory")
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--work", type=Path, default=Path("runs/open-loop-sampling"))
    parser.add_argument("--out", type=Path, default=Path("docs/results/open_loop_sampling.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    state = json.loads((args.reference / "state.json").read_text())
    ref = TrainConfig.from_dict(state["config"])
    cfg = replace(ref, epochs=args.epochs, threads=args.threads,
                  model=replace(ref.model, loss=replace(ref.model.loss, open_loop_sample=False)))
    data = load_sequences(args.data, cfg.model.encoder, "data/cache", progress=False)
    train_idx, valid_idx = tuning_split(data.labels.numpy())
    result = train_model(cfg, data.subset(train_idx), data.subset(valid_idx), checkpoint_dir=args.work, progress=True)
    means = [r["val_balanced_accuracy"] for r in result.history]
    samples = [r["val_balanced_accuracy"] for r in state["history"]][: args.epochs]
    print("epoch | samples (reference) | means")
    for epoch, (a, b) in enumerate(zip(samples, means)):
        print(f"{epoch:5d} | {a:.3f} | {b:.3f}")
    args.out.write_text(json.dumps({
        "command": f"experiments/open_loop_sampling.py --data {args.data} --reference {args.reference} "
                   f"--epochs {args.epochs} --threads {args.threads}",
        "reference_threads": ref.threads, "threads": args.threads,
        "validation_balanced_accuracy": {"samples_reference": samples, "means": means},
        "best": {"samples_reference": max(samples), "means": result.best_val_balanced_accuracy},
    }, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
