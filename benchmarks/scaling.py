"""Scaling out on this machine: episodes/s and trials/s with 1 and 2 workers, Ray's overhead, a projection.

Measured in one run, on an otherwise idle machine (run nothing beside it):

* **collection** -- ``firp collect`` of the same episodes (stacking, seeds 0..N-1) on a process pool of
  1 and 2 workers and on a private Ray cluster of 1 and 2 actors (``--ray local``): episodes/s,
  scaling efficiency (speed-up / workers), and Ray's overhead per episode against the pool with the
  same number of workers, as a share of one episode's time;
* **trials** -- the main job's first trials (the shipped stacking bundle; the services launched once and
  warmed up) on 1 and 2 sim workers, as ``firp run --parallel K`` runs them: trials/s and scaling
  efficiency;
* **projection** -- from these, the plans each trial has scored, and the scoring service's measured
  plans/s (``docs/results/service_latency.json``, batches of 32): how many sim cores one scoring
  service keeps busy, which is where a machine count N saturates the service before the sims.

Each configuration runs ``--repeats`` times into a fresh folder; medians are quoted. Collection times
include each run's start (the pool's spawned workers, Ray's cluster and actors build their worlds):
that is what a user waits for.

    MUJOCO_GL=egl python benchmarks/scaling.py --episodes 16 --trials 8 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET_EFFICIENCY = 0.85
TARGET_RAY_OVERHEAD = 0.05


def _timed(cmd: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    return time.perf_counter() - started


def collection_seconds(episodes: int, workers: int, ray: bool, repeats: int, horizon: int) -> list[float]:
    times = []
    for _ in range(repeats):
        folder = Path(tempfile.mkdtemp(prefix="firp-scaling-"))
        try:
            cmd = [sys.executable, "-m", "planner_client", "collect", "--task", "stacking", "--episodes",
                   str(episodes), "--workers", str(workers), "-T", str(horizon), "--out", str(folder / "d.h5"),
                   "--no-progress"]
            times.append(_timed(cmd + (["--ray", "local"] if ray else [])))
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    return times


def trial_seconds(trials: int, parallel: int, repeats: int) -> tuple[list[float], list[int]]:
    """Wall time of ``trials`` trials of the main job on ``parallel`` launched sim workers and one launched
    scoring service (the shipped stacking bundle), and the plans each trial had scored. The services
    start once and each sim worker runs one untimed trial first (imports, first frames), so only the
    trials are timed."""
    from firp.core.bundle_format import shipped_bundle_dir
    from planner_client.launcher import Launcher
    from planner_client.loop import RunConfig, run_trials
    from planner_client.tamp import TampPlanner

    times, scored = [], []
    planner = TampPlanner()
    for _ in range(repeats):
        folder = Path(tempfile.mkdtemp(prefix="firp-scaling-"))
        try:
            with Launcher(folder, bundle=shipped_bundle_dir("stacking")) as main:
                extra = [Launcher(folder / f"sim-{k}", sim=True).start() for k in range(1, parallel)]
                sims = [main.sim(), *(launcher.sim() for launcher in extra)]
                try:
                    with main.scorer() as scorer:
                        list(run_trials(RunConfig(trials=parallel, seed=900_000, out=folder / "warm.jsonl"),
                                        sims[0], planner, scorer, sims))
                        started = time.perf_counter()
                        records = list(run_trials(RunConfig(trials=trials, out=folder / "run.jsonl"), sims[0],
                                                  planner, scorer, sims))
                        times.append(time.perf_counter() - started)
                finally:
                    for sim in sims:
                        sim.close()
                    for launcher in extra:
                        launcher.stop()
            # scored one by one, then all candidates in one batch (the rules side by side)
            scored += [len(r.get("scores", [])) + len(r.get("candidate_scores", {})) for r in records]
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    return times, scored


def service_plans_per_second() -> float:
    """The scoring service's throughput on batches of 32, as benchmarks/service_latency.py measured it."""
    return float(json.loads((ROOT / "docs/results/service_latency.json").read_text())["results"]["batch"]["plans_per_s"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--horizon", type=int, default=120)
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "docs/results/scaling.json")
    args = parser.parse_args()

    collection = {}
    for ray in (False, True):
        for workers in (1, 2):
            key = f"{'ray' if ray else 'pool'}_{workers}"
            times = collection_seconds(args.episodes, workers, ray, args.repeats, args.horizon)
            collection[key] = {"seconds": times, "median_s": statistics.median(times),
                               "episodes_per_s": args.episodes / statistics.median(times)}
            print(f"collection {key}: {collection[key]['median_s']:.1f} s", flush=True)
    trials, scored = {}, []
    for parallel in (1, 2):
        times, plans = trial_seconds(args.trials, parallel, args.repeats)
        scored += plans
        trials[f"parallel_{parallel}"] = {"seconds": times, "median_s": statistics.median(times),
                                          "trials_per_s": args.trials / statistics.median(times)}
        print(f"trials parallel {parallel}: {statistics.median(times):.1f} s", flush=True)

    def efficiency(rates: dict, one: str, two: str) -> float:
        return rates[two] / rates[one] / 2

    eps = {k: v["episodes_per_s"] for k, v in collection.items()}
    tps = {k: v["trials_per_s"] for k, v in trials.items()}
    episode_s = 1 / eps["pool_1"]
    result = {
        "collection": collection, "trials": trials,
        "collection_efficiency_pool": efficiency(eps, "pool_1", "pool_2"),
        "collection_efficiency_ray": efficiency(eps, "ray_1", "ray_2"),
        "trial_efficiency": efficiency(tps, "parallel_1", "parallel_2"),
        # Ray's extra time per episode against the pool at the same width, as a share of one episode's time
        "ray_overhead_share": {w: (1 / eps[f"ray_{w}"] - 1 / eps[f"pool_{w}"]) * int(w) / episode_s for w in ("1", "2")},
    }
    # one sim core runs tps["parallel_1"] trials/s, each asking the service to score `scored` plans: the
    # service's measured plans/s over that is how many sim cores it keeps busy before it saturates
    plans_per_s, per_trial = service_plans_per_second(), statistics.mean(scored)
    result["projection"] = {
        "service_plans_per_s": plans_per_s, "plans_scored_per_trial": per_trial,
        "sim_cores_one_service_feeds": plans_per_s / (per_trial * tps["parallel_1"]),
    }
    rows = [(f"collection, pool x{w}: episodes/s", f"{eps[f'pool_{w}']:.3f}") for w in (1, 2)]
    rows += [(f"collection, Ray x{w}: episodes/s", f"{eps[f'ray_{w}']:.3f}") for w in (1, 2)]
    rows += [("collection scaling efficiency at 2 (pool / Ray)",
              f"{result['collection_efficiency_pool']:.2f} / {result['collection_efficiency_ray']:.2f}"),
             ("Ray overhead per episode, share of an episode (x1 / x2)",
              f"{result['ray_overhead_share']['1']:+.3f} / {result['ray_overhead_share']['2']:+.3f}")]
    rows += [(f"trials, --parallel {k}: trials/s", f"{tps[f'parallel_{k}']:.3f}") for k in (1, 2)]
    rows += [("trial scaling efficiency at 2", f"{result['trial_efficiency']:.2f}")]
    rows += [("plans scored per trial (mean)", f"{per_trial:.1f}"),
             ("sim cores one scoring service feeds", f"{result['projection']['sim_cores_one_service_feeds']:.0f}")]
    width = max(len(k) for k, _ in rows)
    table = "\n".join(f"{k:<{width}}  {v:>14}" for k, v in rows)
    print(table)
    command = (f"MUJOCO_GL=egl python benchmarks/scaling.py --episodes {args.episodes} --horizon {args.horizon} "
               f"--trials {args.trials} --repeats {args.repeats}")
    targets = {"scaling efficiency >= 0.85 (collection, pool)": result["collection_efficiency_pool"] >= TARGET_EFFICIENCY,
               "scaling efficiency >= 0.85 (collection, Ray)": result["collection_efficiency_ray"] >= TARGET_EFFICIENCY,
               "scaling efficiency >= 0.85 (trials)": result["trial_efficiency"] >= TARGET_EFFICIENCY,
               "Ray overhead <= 5% of an episode": max(result["ray_overhead_share"].values()) <= TARGET_RAY_OVERHEAD}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": command, "machine": {"cpus": os.cpu_count(),
                                                                    "python": platform.python_version()},
                                    "table": table, "results": result, "targets_met": targets}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
