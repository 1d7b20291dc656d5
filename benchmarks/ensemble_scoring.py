"""Ensemble scoring: members run by vmap vs a plain loop, and the cost of the backbone.

Builds an M-member bundle of randomly initialised FIRP members (default FIRPConfig sizes: the
member cost does not depend on the weights' values), then times the member computation of
:class:`firp.ensemble.EnsembleScorer` with ``strategy="loop"`` and ``strategy="vmap"`` for N plans
of T steps, interleaving the two so that load from other processes hits both alike. Reports min
and median over repeats; checks that both strategies agree. The backbone runs once per call and
is timed apart (``--backbone efficientnet_lite0`` for the real one).

    python benchmarks/ensemble_scoring.py --threads 1 --repeats 15
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from firp.bundle import BundleMember, export_bundle, load_bundle
from firp.contract import JOINT_LOWER, JOINT_UPPER, make_plan
from firp.ensemble import EnsembleScorer
from firp.model import EncoderConfig, FIRPConfig, build_model
from firp.model.encoder import build_backbone


def random_plans(n: int, t: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([make_plan(rng.integers(0, 7, t), rng.uniform(JOINT_LOWER, JOINT_UPPER, (t, 9))) for _ in range(n)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=5)
    ap.add_argument("--T", type=int, default=120)
    ap.add_argument("--N", type=int, nargs="+", default=[1, 32])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--backbone", choices=["small_cnn", "efficientnet_lite0"], default="small_cnn")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    image_size = 224 if args.backbone == "efficientnet_lite0" else 64
    cfg = FIRPConfig(encoder=EncoderConfig(backbone=args.backbone, image_size=image_size))
    members = [BundleMember("firp", cfg, build_model("firp", cfg)) for _ in range(args.members)]
    backbone = build_backbone(cfg.encoder) if args.backbone == "small_cnn" else None
    with tempfile.TemporaryDirectory() as tmp:
        path = export_bundle(Path(tmp) / "bench", members, name="bench", task="bench", threshold=0.5,
                             calibration={"ece": 0.0, "n_val": 0}, metrics={}, training_data_hash="-",
                             training_data_path="-", t_range=(8, 400), backbone=backbone)
        bundle = load_bundle(path)
    scorers = {s: EnsembleScorer(bundle, strategy=s) for s in ("loop", "vmap")}
    image = np.random.default_rng(0).integers(0, 256, (224, 224, 3), dtype=np.uint8)

    results: dict[str, object] = {
        "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0], "torch": torch.__version__, "threads": args.threads,
        "members": args.members, "T": args.T, "config": "FIRPConfig() defaults", "runs": {},
    }
    with torch.inference_mode():
        times = []
        for _ in range(max(3, args.repeats // 3)):
            start = time.perf_counter()
            feats = scorers["loop"].encoder.backbone_features(image[None])
            times.append(time.perf_counter() - start)
        results["backbone_ms"] = {"name": args.backbone, "image_size": image_size, "min": 1e3 * min(times),
                                  "median": 1e3 * statistics.median(times)}
        for n in args.N:
            actions = torch.from_numpy(random_plans(n, args.T)).float()
            f = feats.expand(n, -1)
            ref = scorers["loop"]._run_members(f, actions)[0]
            got = scorers["vmap"]._run_members(f, actions)[0]
            max_diff = float((torch.sigmoid(ref) - torch.sigmoid(got)).abs().max())
            timings: dict[str, list[float]] = {"loop": [], "vmap": []}
            for s in timings:  # warm-up
                scorers[s]._run_members(f, actions)
            for _ in range(args.repeats):
                for s in timings:
                    start = time.perf_counter()
                    scorers[s]._run_members(f, actions)
                    timings[s].append(1e3 * (time.perf_counter() - start))
            row = {s: {"min_ms": min(v), "median_ms": statistics.median(v)} for s, v in timings.items()}
            row["max_abs_prob_diff"] = max_diff
            results["runs"][f"N={n}"] = row  # type: ignore[index]
            print(f"N={n:3d} T={args.T}: loop min {row['loop']['min_ms']:.1f} / median "
                  f"{row['loop']['median_ms']:.1f} ms | vmap min {row['vmap']['min_ms']:.1f} / median {row['vmap']['median_ms']:.1f} ms"
                  f" | max |dp| {max_diff:.1e}", flush=True)
    print(f"backbone ({args.backbone}) once per call: {results['backbone_ms']}")  # type: ignore[index]
    print(f"load average at start: {results['load_avg_1min']:.2f} on {results['cpus']} CPUs")
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
