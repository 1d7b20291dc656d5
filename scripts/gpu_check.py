"""A short check that training and scoring run on a GPU and agree with the CPU: ``--device cuda`` end to end.

Trains the generic preset's FIRP (small sizes, the plan's events through a 7-joint chain) for a few epochs on
a synthetic set whose label the plan decides, on ``--device``, then scores held-out plans with the trained
model on that device and on the CPU, and reports seconds per epoch and the largest difference between the
two devices' probabilities. Takes well under five minutes on a GPU machine; here (no GPU) it runs with
``--device cpu`` in the tests, and ``--device cuda`` fails with torch's own explanation.

    python scripts/gpu_check.py --device cuda --out runs/gpu_check.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from firp.core.kinematics import ChainJoint, KinematicChain, Pose  # noqa: E402
from firp.data import SequenceData  # noqa: E402
from firp.model.config import EncoderConfig, FIRPConfig, HeadConfig, PlanEventsConfig, RSSMConfig  # noqa: E402
from firp.train import TrainConfig, predict, resolve_device, train_model  # noqa: E402


def synthetic_chain() -> KinematicChain:
    """Seven revolute joints alternating about z and y, 0.1-0.3 m apart: an arm, not any particular one."""
    joints = tuple(ChainJoint(f"j{i}", Pose((0.0, 0.0, 0.1 + 0.03 * i)), (0.0, 0.0, 1.0) if i % 2 == 0 else
                              (0.0, 1.0, 0.0)) for i in range(7))
    return KinematicChain(joints, tool=Pose((0.0, 0.0, 0.1)))


def synthetic_data(n: int, T: int, backbone_dim: int, seed: int = 0) -> SequenceData:
    """Plans of category runs and smooth joint targets; success when the hand ends high (what the plan decides)."""
    g = torch.Generator().manual_seed(seed)
    cats = torch.randint(0, 7, (n, T // 4 + 1), generator=g).repeat_interleave(4, dim=1)[:, :T]
    plans = torch.zeros(n, T, 16)
    plans.scatter_(2, cats.unsqueeze(-1), 1.0)
    plans[..., 7:14] = torch.cumsum(0.05 * torch.randn(n, T, 7, generator=g), dim=1)
    plans[..., 14:] = 0.02
    from firp.model.kinematics import ChainFK

    with torch.no_grad():
        height = ChainFK(synthetic_chain())(plans[:, -1, 7:14])[0][:, 2]
    labels = (height > height.median()).float()
    features = torch.randn(n, T, backbone_dim, generator=g) * 0.5 + labels[:, None, None]
    data = SequenceData(features, plans, labels, "synthetic", [f"demo_{i}" for i in range(n)])
    data.attrs["kinematics"] = synthetic_chain().to_dict()
    return data


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python scripts/gpu_check.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cuda")
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = parser.parse_args(argv)
    try:
        device = resolve_device(args.device)
    except ValueError as exc:
        parser.error(str(exc))
    model_cfg = FIRPConfig(encoder=EncoderConfig(backbone="small_cnn", feature_dim=32, small_cnn_channels=(16, 64)),
                           rssm=RSSMConfig(deter_dim=64, hidden=64), head=HeadConfig(temperature=0.05),
                           events=PlanEventsConfig(enabled=True, hidden=32), action_chunk=4)
    cfg = TrainConfig(epochs=args.epochs, batch_size=32, threads=2, model=model_cfg)
    data = synthetic_data(args.episodes, 32, model_cfg.encoder.backbone_dim)
    cfg = cfg.fit_to_data(data)
    cut = int(0.75 * len(data))
    train, held_out = data.subset(list(range(cut))), data.subset(list(range(cut, len(data))))
    started = time.perf_counter()
    result = train_model(cfg, train, held_out, progress=False, device=str(device))
    seconds = time.perf_counter() - started
    on_cpu = predict(result.model, held_out)
    on_device = predict(result.model.to(device), held_out)
    figures = {
        "device": str(device), "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__, "episodes": len(data), "epochs": len(result.history),
        "seconds_per_epoch": round(seconds / max(1, len(result.history)), 3),
        "valid_balanced_accuracy": round(result.best_val_balanced_accuracy, 3),
        "max_probability_difference_device_vs_cpu": float(abs(on_cpu - on_device).max()),
    }
    print("| figure | value |\n|---|---|")
    for key, value in figures.items():
        print(f"| {key} | {value} |")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(figures, indent=1))
    ok = math.isfinite(figures["max_probability_difference_device_vs_cpu"]) and \
        figures["max_probability_difference_device_vs_cpu"] < 1e-3
    print("OK: the device trains and scores as the CPU does" if ok else "FAILED: the device disagrees with the CPU")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
