"""Ensemble scoring: members fused vs a plain loop, and the cost of the backbone.

Builds an M-member bundle of randomly initialised FIRP members (default FIRPConfig sizes: the
member cost does not depend on the weights' values), or loads ``--bundle DIR`` (e.g. the shipped
``models/stacking``), then times the member computation of
:class:`firp.serving.EnsembleScorer` with each ``--strategies`` (default ``loop fused``) for
N plans of T steps, interleaving them so that load from other processes hits all alike. Reports
min and median over repeats, and each strategy's largest probability difference from the loop.
The backbone runs once per call and is timed apart (``--backbone efficientnet_lite0`` for the
real one).

    python benchmarks/ensemble_scoring.py --threads 1 --repeats 15
    python benchmarks/ensemble_scoring.py --bundle models/stacking --N 1 8 32 --repeats 20
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
from firp.core.contract import JOINT_LOWER, JOINT_UPPER, make_plan
from firp.serving import EnsembleScorer
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
    ap.add_argument("--bundle", type=Path, default=None,
                    help="time this bundle's members (its backbone, image size and T range) instead of random ones")
    ap.add_argument("--strategies", nargs="+", choices=["loop", "fused"], default=["loop", "fused"])
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    if args.bundle is not None:
        bundle = load_bundle(args.bundle)
        image_size, config_name = bundle.encoder_config.image_size, f"bundle {args.bundle}"
        args.backbone, args.members = bundle.encoder_config.backbone, len(bundle.models)
        if not bundle.t_range.t_min <= args.T <= bundle.t_range.t_max:
            ap.error(f"--T {args.T} is outside the bundle's T range {bundle.t_range}")
    else:
        image_size, config_name = (224 if args.backbone == "efficientnet_lite0" else 64), "FIRPConfig() defaults"
        cfg = FIRPConfig(encoder=EncoderConfig(backbone=args.backbone, image_size=image_size))
        members = [BundleMember("firp", cfg, build_model("firp", cfg)) for _ in range(args.members)]
        backbone = build_backbone(cfg.encoder) if args.backbone == "small_cnn" else None
        with tempfile.TemporaryDirectory() as tmp:
            path = export_bundle(Path(tmp) / "bench", members, name="bench", task="bench", threshold=0.5,
                                 calibration={"ece": 0.0, "n_val": 0}, metrics={}, training_data_hash="-",
                                 training_data_path="-", t_range=(8, 400), backbone=backbone)
            bundle = load_bundle(path)
    strategies = ["loop"] + [s for s in args.strategies if s != "loop"]  # the loop is the reference
    scorers = {s: EnsembleScorer(bundle, strategy=s) for s in strategies}
    image = np.random.default_rng(0).integers(0, 256, (image_size, image_size, 3), dtype=np.uint8)

    import sys

    results: dict[str, object] = {
        "command": "python benchmarks/ensemble_scoring.py " + " ".join(sys.argv[1:]),
        "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0], "torch": torch.__version__, "threads": args.threads,
        "members": args.members, "T": args.T, "config": config_name, "runs": {},
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
            ref = torch.sigmoid(scorers["loop"]._run_members(feats, actions)[0])
            diffs = {s: float((torch.sigmoid(scorers[s]._run_members(feats, actions)[0]) - ref).abs().max())
                     for s in strategies[1:]}
            timings: dict[str, list[float]] = {s: [] for s in strategies}
            for s in timings:  # warm-up
                scorers[s]._run_members(feats, actions)
            for _ in range(args.repeats):
                for s in timings:
                    start = time.perf_counter()
                    scorers[s]._run_members(feats, actions)
                    timings[s].append(1e3 * (time.perf_counter() - start))
            row: dict[str, object] = {s: {"min_ms": min(v), "median_ms": statistics.median(v)} for s, v in timings.items()}
            row["max_abs_prob_diff_from_loop"] = diffs
            results["runs"][f"N={n}"] = row  # type: ignore[index]
            cells = " | ".join(f"{s} min {min(v):.1f} / median {statistics.median(v):.1f} ms" for s, v in timings.items())
            diff_text = ", ".join(f"{s} {d:.1e}" for s, d in diffs.items())
            print(f"N={n:3d} T={args.T}: {cells} | max |dp| vs loop: {diff_text}", flush=True)
    print(f"backbone ({args.backbone}) once per call: {results['backbone_ms']}")  # type: ignore[index]
    print(f"load average at start: {results['load_avg_1min']:.2f} on {results['cpus']} CPUs")
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
