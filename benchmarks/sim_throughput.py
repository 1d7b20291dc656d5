"""Simulation speed on one core: physics steps/s, camera frames/s, full episodes with frames.

Target (issue 2): a full T=120 episode with rendering in <= 2 s on one core, so that 640 episodes
take <= 11 minutes on 2 cores. Reports medians over repeats; planning time is reported apart
from execution because the planner runs in the client, not in the sim worker.

    MUJOCO_GL=egl python benchmarks/sim_throughput.py --episodes 10
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402

from planner_client.tamp import TampPlanner  # noqa: E402
from planner_client.collect import episode_order  # noqa: E402
from sim_worker.executor import ExecutorConfig, execute_plan  # noqa: E402
from sim_worker.perception import observation  # noqa: E402
from sim_worker.tasks import sample_initial_blocks  # noqa: E402
from sim_worker.world import World  # noqa: E402


def physics_steps_per_second(world: World, steps: int = 5000, repeats: int = 5) -> float:
    world.reset(sample_initial_blocks("stacking", 0))
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        mujoco.mj_step(world.model, world.data, nstep=steps)
        rates.append(steps / (time.perf_counter() - start))
    return statistics.median(rates)


def frames_per_second(world: World, frames: int = 200, repeats: int = 5) -> float:
    world.reset(sample_initial_blocks("stacking", 0))
    world.render()
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(frames):
            world.render()
        rates.append(frames / (time.perf_counter() - start))
    return statistics.median(rates)


def episode_seconds(world: World, planner: TampPlanner, task: str, episodes: int) -> dict:
    plan_s, exec_s, exec_noframes_s = [], [], []
    for seed in range(episodes):
        blocks = sample_initial_blocks(task, seed)
        obs = observation(blocks, seed, world.layout)
        start = time.perf_counter()
        plan = planner.plan(task, obs, episode_order(seed))
        plan_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        execute_plan(world, task, blocks, plan.actions)
        exec_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        execute_plan(world, task, blocks, plan.actions, ExecutorConfig(record_frames=False))
        exec_noframes_s.append(time.perf_counter() - start)
    return {"plan_s": statistics.median(plan_s), "execute_with_frames_s": statistics.median(exec_s),
            "execute_without_frames_s": statistics.median(exec_noframes_s),
            "episodes_per_s_per_core": 1.0 / (statistics.median(plan_s) + statistics.median(exec_s))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("docs/results/sim_throughput.json"))
    args = parser.parse_args()
    world = World()
    planner = TampPlanner()
    result = {
        "physics_steps_per_s": physics_steps_per_second(world),
        "frames_per_s": frames_per_second(world),
        "image_size": [world.render_config.height, world.render_config.width],
        "timestep_s": world.model.opt.timestep,
        "tasks": {task: episode_seconds(world, planner, task, args.episodes) for task in ("stacking", "replacement")},
    }
    rows = [("physics steps/s (3 blocks, arm)", f"{result['physics_steps_per_s']:,.0f}"),
            (f"frames/s at {result['image_size'][0]}x{result['image_size'][1]}", f"{result['frames_per_s']:,.0f}")]
    for task, r in result["tasks"].items():
        rows += [(f"{task}: plan (IK, T=120) s", f"{r['plan_s']:.3f}"),
                 (f"{task}: execute T=120 with frames s", f"{r['execute_with_frames_s']:.3f}"),
                 (f"{task}: execute T=120 without frames s", f"{r['execute_without_frames_s']:.3f}"),
                 (f"{task}: episodes/s per core (plan + execute)", f"{r['episodes_per_s_per_core']:.2f}")]
    width = max(len(k) for k, _ in rows)
    table = "\n".join(f"{k:<{width}}  {v:>10}" for k, v in rows)
    print(table)
    print(f"medians over {args.episodes} episodes per task; target: execute with frames <= 2 s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "command": f"MUJOCO_GL=egl python benchmarks/sim_throughput.py --episodes {args.episodes}",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "mujoco": mujoco.__version__},
        "table": table, "results": result}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
