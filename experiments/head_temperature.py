"""What the attention temperature L does: the success head alone on real frame features.

Trains the feature projection + success head (no RSSM) on the protocol's first stacking split
for 200 steps of batch 32, for the paper's L = 20 and a sharp L = 0.05, at two learning rates,
and reports training loss and validation balanced accuracy every 50 steps. With the cosine in
[-1, 1], L = 20 makes the attention practically a mean over the 120 steps, which dilutes the
late frames where a failure shows.

    python -m experiments.head_temperature --data data/stacking.h5
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from firp.data import load_sequences
from firp.evaluate import split_indices
from firp.losses import classification_loss
from firp.metrics import balanced_accuracy
from firp.model.config import EncoderConfig, HeadConfig
from firp.model.encoder import FeatureProjection
from firp.model.head import SuccessHead

VARIANTS = [("L=20, lr=1e-3", 20.0, 1e-3), ("L=0.05, lr=1e-3", 0.05, 1e-3),
            ("L=0.05, lr=3e-3", 0.05, 3e-3), ("L=20, lr=3e-3", 20.0, 3e-3)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", type=Path, default=Path("docs/results/head_temperature.json"))
    args = parser.parse_args()
    torch.set_num_threads(2)
    enc = EncoderConfig(image_size=84)
    data = load_sequences(args.data, enc, progress=False)
    train_idx, valid_idx, _ = split_indices(data.labels.numpy(), 0)
    x, y = data.features[train_idx], data.labels[train_idx]
    xv, yv = data.features[valid_idx], data.labels[valid_idx].numpy() > 0.5
    results = {}
    for name, temperature, lr in VARIANTS:
        torch.manual_seed(0)
        proj, head = FeatureProjection(enc), SuccessHead(HeadConfig(temperature=temperature), enc.feature_dim)
        opt = torch.optim.Adam([*proj.parameters(), *head.parameters()], lr=lr)
        curve = []
        for step in range(1, args.steps + 1):
            idx = torch.randint(0, len(train_idx), (32,))
            loss = classification_loss(head(proj(x[idx]))[0], y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            if step % 50 == 0:
                with torch.no_grad():
                    p = torch.sigmoid(head(proj(xv))[0]).numpy()
                curve.append({"step": step, "train_loss": float(loss.detach()),
                              "valid_balanced_accuracy": balanced_accuracy(yv, p >= 0.5)})
        results[name] = curve
        print(f"{name:<16} " + "  ".join(f"step {c['step']}: loss {c['train_loss']:.3f} val BA {c['valid_balanced_accuracy']:.3f}"
                                          for c in curve), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": f"python -m experiments.head_temperature --data {args.data}",
                                    "results": results}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
