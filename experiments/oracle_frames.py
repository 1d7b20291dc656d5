"""Can the executed frames show the label? The success check on the state of the last recorded frame.

The Oracle baseline scores a plan from its executed frames. Its ceiling is what those frames show: a
dataset's frame ``t`` is rendered at the *start* of plan step ``t``, in both worlds, so the last
frame precedes the last step and the settling after the plan (1 s in robosuite's world, 1.5 s in
ours), during which an object may still slide, drop or topple -- and the label is the check at the
very end. This experiment restores each episode's recorded state at its last frame (``states[-1]``)
into the task's world and runs the same check there (no simulation, no rendering): robosuite's
``_check_success`` for a ``firp collect --world robosuite`` dataset, our world's ``judge`` for one of
ours. Then it compares with the label:

* ``agree`` -- the last frame's state already has the label's outcome;
* ``decided_after`` -- it does not: the outcome is decided after the frames end, and no image model
  of those frames can know it. The balanced accuracy of "the check at the last frame" as a predictor
  of the label is an upper bound for an Oracle that reads the last frame perfectly (it would still
  have to see what the check sees, through an 84 px camera with the arm in the view).

    .venv-robosuite/bin/python -m experiments.oracle_frames --data data/robosuite_nut_assembly.h5 \\
        --out docs/results/robosuite_nut_assembly_oracle_frames.json
    .venv/bin/python -m experiments.oracle_frames --data data/stacking.h5 --out docs/results/stacking_oracle_frames.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm


def balanced_accuracy(predicted: list[bool], labels: list[bool]) -> float:
    p, y = np.asarray(predicted), np.asarray(labels)
    rates = [float(np.mean(p[y == c] == c)) for c in (True, False) if np.any(y == c)]
    return float(np.mean(rates))


def check_at(env, state: np.ndarray) -> bool:
    """robosuite's success check on ``state`` (qpos then qvel, as the collection records them)."""
    sim = env.sim
    nq, nv = sim.model.nq, sim.model.nv
    sim.data.qpos[:] = state[:nq]
    sim.data.qvel[:] = state[nq:nq + nv]
    sim.forward()
    return bool(env._check_success())


def our_world_check(task: str):
    """Our world's verdict on a recorded state (``mj_setState`` of the physics state, then ``judge``)."""
    import mujoco

    from sim_worker.scene import RenderConfig, SceneLayout
    from sim_worker.tasks import judge
    from sim_worker.world import STATE_SPEC, World

    world = World(SceneLayout(), RenderConfig.for_task(task, 16, 16))

    def check(state: np.ndarray) -> bool:
        if not np.isfinite(state).all():
            return False
        mujoco.mj_setState(world.model, world.data, state, STATE_SPEC)
        mujoco.mj_forward(world.model, world.data)
        return bool(judge(task, world.block_states(), world.layout).success)

    return check


def robosuite_check(task: str):
    from robosuite_worker.world import RobosuiteWorld

    env = RobosuiteWorld().env(task)
    env.reset()
    return lambda state: check_at(env, state)


def analyse(path: Path, limit: int | None = None) -> dict:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from firp.core.episodes import EpisodeDataset

    with EpisodeDataset(path) as ds:
        attrs = ds.attrs
        task = attrs.get("task") or ds.demo_attrs(0)["task"]
        world = "robosuite" if attrs.get("env") == "robosuite" else "mujoco"
        check = robosuite_check(task) if world == "robosuite" else our_world_check(task)
        n = len(ds) if limit is None else min(limit, len(ds))
        labels, at_last, first_frame = [], [], []
        kinds: Counter = Counter()
        for i in tqdm(range(n), desc=f"check at the last frame ({world} {task})", unit="ep"):
            states = ds.states(i)
            label = bool(ds.success(i))
            last = check(states[-1])
            labels.append(label)
            at_last.append(last)
            first_frame.append(check(states[0]))
            kinds[f"label {'success' if label else 'failure'}, last frame {'success' if last else 'failure'}"] += 1
    agree = sum(a == b for a, b in zip(labels, at_last))
    return {
        "data": str(path), "world": world, "task": task, "episodes": n, "successes": int(sum(labels)),
        "agree": agree, "decided_after": n - agree, "decided_after_fraction": (n - agree) / n,
        "cells": dict(kinds),
        "balanced_accuracy_of_the_check_at_the_last_frame": balanced_accuracy(at_last, labels),
        "successes_already_at_the_first_frame": int(sum(first_frame)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a firp collect --world robosuite dataset")
    parser.add_argument("--limit", type=int, default=None, help="the first N episodes only")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if not args.data.is_file():
        print(f"--data: no dataset at {args.data}", file=sys.stderr)
        return 2
    result = analyse(args.data, args.limit)
    result["command"] = "python -m experiments.oracle_frames " + " ".join(argv if argv is not None else sys.argv[1:])
    result["python"] = platform.python_version()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{result['episodes']} episodes: the last frame's state has the label's outcome in {result['agree']}, "
          f"not in {result['decided_after']} ({100 * result['decided_after_fraction']:.1f}%); balanced accuracy of "
          f"the check at the last frame {result['balanced_accuracy_of_the_check_at_the_last_frame']:.3f}")
    for cell, count in sorted(result["cells"].items()):
        print(f"  {cell}: {count}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
