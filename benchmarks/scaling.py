"""Scaling out on this machine: episodes/s and trials/s with 1 and 2 workers, Ray's overhead, a projection.

Measured in one run, on an otherwise idle machine (run nothing beside it):

* **collection** -- ``firp collect`` of the same episodes (stacking, seeds 0..N-1) on a process pool of
  1 and 2 workers and on a private Ray cluster of 1 and 2 actors (``--ray local``). Each run's wall time
  is a start (imports, the workers' or Ray's start, each world built), the episodes, and the final merge.
  While a run goes, the benchmark watches its parts folder (``<out>.parts``, one file per finished
  episode) and notes when each episode's file appeared: the steady rate is the episodes after the
  first ``w`` (``w`` workers) over the time from the ``w``-th to the last, when every worker is busy;
  the start is the time to the first episode. Reported: episodes/s steady and end to end, scaling
  efficiency (speed-up / workers) of both, and Ray's overhead per episode against the pool with the
  same number of workers (steady), as a share of one episode's time, plus Ray's extra start;
* **trials** -- the main job's first trials (the shipped stacking bundle; the services launched once and
  warmed up) on 1 and 2 sim workers, as ``firp run --parallel K`` runs them: trials/s and scaling
  efficiency;
* **projection** -- from these, the plans each trial has scored, and the scoring service's measured
  plans/s (``docs/results/service_latency.json``, batches of 32): how many sim cores one scoring
  service keeps busy, which is where a machine count N saturates the service before the sims.

Each configuration runs ``--repeats`` times into a fresh folder; medians are quoted. The end-to-end
collection figures include each run's start (the pool's spawned workers, Ray's cluster and actors
build their worlds): that is what a user of a small collection waits for; the steady-state figures
are what a large one runs at.

    MUJOCO_GL=egl python benchmarks/scaling.py --episodes 32 --trials 8 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import math
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
PROJECTION_CORES = 16  # cores per machine in the projection
PROJECTION_MACHINES = (1, 4, 16, 64)


def _timed(cmd: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    return time.perf_counter() - started


def collection_run(episodes: int, workers: int, ray: bool, horizon: int, poll_s: float = 0.02) -> dict:
    """One ``firp collect`` run into a fresh folder: its wall time and when each episode's part appeared."""
    folder = Path(tempfile.mkdtemp(prefix="firp-scaling-"))
    out = folder / "d.h5"
    parts = out.with_name(out.name + ".parts")  # planner_client.collect.parts_dir_of
    cmd = [sys.executable, "-m", "planner_client", "collect", "--task", "stacking", "--episodes", str(episodes),
           "--workers", str(workers), "-T", str(horizon), "--out", str(out), "--no-progress",
           *(["--ray", "local"] if ray else [])]
    seen: dict[str, float] = {}
    try:
        started = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
        while proc.poll() is None:
            if parts.is_dir():
                now = time.perf_counter() - started
                for name in os.listdir(parts):
                    if name.endswith(".h5"):
                        seen.setdefault(name, now)
            time.sleep(poll_s)
        wall = time.perf_counter() - started
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed with status {proc.returncode}")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    times = sorted(seen.values())
    if len(times) != episodes:
        raise SystemExit(f"saw {len(times)} of {episodes} episodes' parts appear (poll faster?)")
    w = workers
    return {"wall_s": wall, "first_episode_s": times[0], "episode_times_s": times,
            "steady_episodes_per_s": (episodes - w) / (times[-1] - times[w - 1])}


def collection_runs(episodes: int, workers: int, ray: bool, repeats: int, horizon: int) -> dict:
    runs = [collection_run(episodes, workers, ray, horizon) for _ in range(repeats)]
    return {"runs": runs,
            "median_wall_s": statistics.median(r["wall_s"] for r in runs),
            "start_s": statistics.median(r["first_episode_s"] for r in runs),
            "episodes_per_s": statistics.median(r["steady_episodes_per_s"] for r in runs),
            "episodes_per_s_end_to_end": episodes / statistics.median(r["wall_s"] for r in runs)}


def driver_write_seconds(episodes: int, horizon: int, writes: int = 20) -> float:
    """Median time the collecting process spends writing one returned episode (``write_episode_part``:
    frames, plan, states into an atomic part file). On Ray this is the driver's serial share of every
    episode, so ``1 / write_s`` bounds a cluster's episodes/s however many machines simulate."""
    from firp.core.episodes import EpisodeDataset, write_episode_part

    folder = Path(tempfile.mkdtemp(prefix="firp-scaling-"))
    try:
        subprocess.run([sys.executable, "-m", "planner_client", "collect", "--task", "stacking", "--episodes",
                        str(episodes), "--workers", "1", "-T", str(horizon), "--out", str(folder / "d.h5"),
                        "--no-progress"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        with EpisodeDataset(folder / "d.h5") as dataset:
            record = dataset.episode(0)
        times = []
        for k in range(writes):
            started = time.perf_counter()
            write_episode_part(folder / "parts", k, record)
            times.append(time.perf_counter() - started)
        return statistics.median(times)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


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
    """The scoring service's throughput on batches of 32 with the shipped stacking bundle, as
    benchmarks/service_latency.py measured it (docs/results/service_latency_geometry_bundle.json)."""
    measured = json.loads((ROOT / "docs/results/service_latency_geometry_bundle.json").read_text())
    return float(measured["results"]["batch"]["plans_per_s"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--horizon", type=int, default=120)
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "docs/results/scaling.json")
    args = parser.parse_args()

    collection = {}
    for ray in (False, True):
        for workers in (1, 2):
            key = f"{'ray' if ray else 'pool'}_{workers}"
            collection[key] = c = collection_runs(args.episodes, workers, ray, args.repeats, args.horizon)
            print(f"collection {key}: {c['median_wall_s']:.1f} s for {args.episodes} episodes, first after "
                  f"{c['start_s']:.1f} s, steady {c['episodes_per_s']:.3f} episodes/s", flush=True)
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
    eps_e2e = {k: v["episodes_per_s_end_to_end"] for k, v in collection.items()}
    tps = {k: v["trials_per_s"] for k, v in trials.items()}
    episode_s = 1 / eps["pool_1"]
    result = {
        "collection": collection, "trials": trials,
        "collection_efficiency_pool": efficiency(eps, "pool_1", "pool_2"),
        "collection_efficiency_ray": efficiency(eps, "ray_1", "ray_2"),
        "collection_efficiency_end_to_end": {"pool": efficiency(eps_e2e, "pool_1", "pool_2"),
                                             "ray": efficiency(eps_e2e, "ray_1", "ray_2"), "episodes": args.episodes},
        "trial_efficiency": efficiency(tps, "parallel_1", "parallel_2"),
        # Ray's extra time per episode against the pool at the same width (steady state), as a share of
        # one episode's time on one worker; and Ray's extra start (cluster, actors), paid once per run
        "ray_overhead_share": {w: (1 / eps[f"ray_{w}"] - 1 / eps[f"pool_{w}"]) * int(w) / episode_s for w in ("1", "2")},
        "ray_extra_start_s": {w: collection[f"ray_{w}"]["start_s"] - collection[f"pool_{w}"]["start_s"]
                              for w in ("1", "2")},
    }
    # one sim core runs tps["parallel_1"] trials/s, each asking the service to score `scored` plans: the
    # service's measured plans/s over that is how many sim cores it keeps busy before it saturates
    plans_per_s, per_trial = service_plans_per_second(), statistics.mean(scored)
    write_s = driver_write_seconds(2, args.horizon)
    feeds = plans_per_s / (per_trial * tps["parallel_1"])
    result["projection"] = {
        "service_plans_per_s": plans_per_s, "plans_scored_per_trial": per_trial,
        "sim_cores_one_service_feeds": feeds,
        "driver_write_s_per_episode": write_s, "driver_bound_episodes_per_s": 1 / write_s,
        # N machines of `cores` cores each, every core a sim at the measured one-worker rate and the
        # measured efficiency at 2: collection until the driver's writes saturate; trials until the
        # scoring services do (one service feeds `feeds` sim cores)
        "machines": [{"machines": m, "cores": m * PROJECTION_CORES,
                      "collection_episodes_per_s": min(m * PROJECTION_CORES * eps["ray_1"] * result["collection_efficiency_ray"],
                                                       1 / write_s),
                      "collection_bound": "driver" if m * PROJECTION_CORES * eps["ray_1"]
                      * result["collection_efficiency_ray"] > 1 / write_s else "sims",
                      "trials_per_s": m * PROJECTION_CORES * tps["parallel_1"] * result["trial_efficiency"],
                      "scoring_services_needed": math.ceil(m * PROJECTION_CORES / feeds)}
                     for m in PROJECTION_MACHINES],
    }
    rows = [(f"collection, pool x{w}: episodes/s (steady / end to end)",
             f"{eps[f'pool_{w}']:.3f} / {eps_e2e[f'pool_{w}']:.3f}") for w in (1, 2)]
    rows += [(f"collection, Ray x{w}: episodes/s (steady / end to end)",
              f"{eps[f'ray_{w}']:.3f} / {eps_e2e[f'ray_{w}']:.3f}") for w in (1, 2)]
    rows += [("first episode after, s (pool x1 / x2, Ray x1 / x2)",
              " / ".join(f"{collection[k]['start_s']:.1f}" for k in ("pool_1", "pool_2", "ray_1", "ray_2")))]
    e2e = result["collection_efficiency_end_to_end"]
    rows += [("collection scaling efficiency at 2, steady (pool / Ray)",
              f"{result['collection_efficiency_pool']:.2f} / {result['collection_efficiency_ray']:.2f}"),
             (f"collection scaling efficiency at 2, end to end, {args.episodes} episodes (pool / Ray)",
              f"{e2e['pool']:.2f} / {e2e['ray']:.2f}"),
             ("Ray overhead per episode, share of an episode (x1 / x2)",
              f"{result['ray_overhead_share']['1']:+.3f} / {result['ray_overhead_share']['2']:+.3f}"),
             ("Ray's extra start per run, s (x1 / x2)",
              f"{result['ray_extra_start_s']['1']:+.1f} / {result['ray_extra_start_s']['2']:+.1f}")]
    rows += [(f"trials, --parallel {k}: trials/s", f"{tps[f'parallel_{k}']:.3f}") for k in (1, 2)]
    rows += [("trial scaling efficiency at 2", f"{result['trial_efficiency']:.2f}")]
    rows += [("plans scored per trial (mean)", f"{per_trial:.1f}"),
             ("sim cores one scoring service feeds", f"{feeds:.0f}"),
             ("driver's write per episode, ms (bounds a cluster at episodes/s)", f"{write_s * 1e3:.1f} ({1 / write_s:.0f})")]
    rows += [(f"projection, {p['machines']} x {PROJECTION_CORES} cores: episodes/s ({p['collection_bound']}), "
              f"trials/s, services", f"{p['collection_episodes_per_s']:.1f}, {p['trials_per_s']:.1f}, "
              f"{p['scoring_services_needed']}") for p in result["projection"]["machines"]]
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
