"""The robosuite planner's choices meeting robosuite's physics: success per choice, rescues, failure modes.

Two parts, both written to one JSON (and printed as tables):

* **dataset** (``--data``, a ``firp collect --world robosuite`` file; no simulation): the success rate
  of each factor of the drawn choices (the tower's order, each grasp's pair of faces, each grasp's
  height), and the failure modes read from the end states: which moved cube did not end on the tower.
* **survey** (``--seeds N``, simulation; run in the robosuite environment): on scene seeds never used
  for datasets (``--seed`` onwards), the planner's default choice; when it fails, the other choices
  in the loop's order until one succeeds -- how often the default succeeds, and how many of its
  failures another choice rescues (within the loop's budget of 6, and within all choices).

    .venv-robosuite/bin/python -m experiments.robosuite_choices --data data/robosuite_stack_three.h5 \\
        --seeds 50 --workers 2 --out docs/results/robosuite_stack_three_choices.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from experiments.resumable import append_as_done

TABLE_CONTACT = 0.01  # a cube whose centre is within this of its resting height on the table is "on the table"
LOOP_BUDGET = 6


def failure_mode(order: list[str], final_blocks: dict, scene: dict, kind: str) -> str:
    """What did not end on the tower, from the end state: ``middle`` / ``top`` cube left on the table,
    ``tower`` (all three off the table, yet the check failed: tilted or still touching the hand), or ``unstable``."""
    if kind == "unstable":
        return "unstable"
    table, half = scene["table_height"], scene["cube_half"]
    on_table = [name for name in order[1:]
                if final_blocks[name]["position"][2] - table < half[name] + TABLE_CONTACT]
    if not on_table:
        return "tower stands incomplete (tilted, or the check's contacts fail)"
    return " and ".join(f"{'middle' if name == order[1] else 'top'} cube on the table" for name in on_table)


NUT_ON_PEG = 0.02  # the nut's centre within this of the peg's axis: around the peg
NUT_DOWN = 0.03  # ... and within this of the table: down on it


def nut_failure_mode(final_blocks: dict, scene: dict, kind: str) -> str:
    """Where the nut ended, from the end state: stuck up on the peg, beside it on the table, or elsewhere."""
    if kind == "unstable":
        return "unstable"
    (nut,) = final_blocks.values()
    x, y, z = nut["position"]
    off_axis = float(np.hypot(x - scene["peg"][0], y - scene["peg"][1]))
    up = z - scene["table_height"] - scene["nut_half_height"]
    if z < scene["table_height"] - NUT_DOWN:
        return "off the table"
    if off_axis < NUT_ON_PEG:
        return "on the peg, not down (jammed)" if up > NUT_DOWN else "around the peg (the check failed)"
    if up < NUT_DOWN:
        return "on the table beside the peg"
    return "in the air (still held, or resting on something)"


def pick_place_misses(final_blocks: dict, scene: dict, kind: str) -> list[str]:
    """Each object that did not end in its quadrant of the second bin, and where it is: still in the first
    bin, in another quadrant, or off both bins (the same bounds as robosuite's ``not_in_bin``)."""
    if kind == "unstable":
        return ["unstable"]
    from planner_client.robosuite_tamp import RobosuiteTampPlanner

    bin2, size = np.asarray(scene["bin2"], dtype=float), np.asarray(scene["bin_size"], dtype=float)
    bin1 = np.asarray(scene["bin1"], dtype=float)
    misses = []
    for name, final in final_blocks.items():
        pos = np.asarray(final["position"], dtype=float)
        low, high = RobosuiteTampPlanner.quadrant(scene, name)
        inside = bool(np.all(pos[:2] > low) and np.all(pos[:2] < high) and bin2[2] < pos[2] < bin2[2] + 0.1)
        if inside:
            continue  # (robosuite's check also wants the hand away from it: the plans end with the hand above)
        if np.all(np.abs(pos[:2] - bin1[:2]) < size / 2):
            misses.append(f"{name} left in the first bin")
        elif np.all(np.abs(pos[:2] - bin2[:2]) < size / 2):
            misses.append(f"{name} in the second bin, outside its quadrant")
        else:
            misses.append(f"{name} off both bins")
    return misses


def _factors(task: str, attrs: dict) -> dict[str, str]:
    parts = attrs["choice"].split(":")
    if task in ("nut_assembly", "nut_assembly_round"):
        from planner_client.robosuite_tamp import NUT_GRIP_NAMES, NUT_GRIPS

        grip = dict(zip(NUT_GRIP_NAMES, NUT_GRIPS))[parts[4]]
        return {"grasp axis": "across the handle" if parts[1] == "0" else "along the handle",
                "grip point (m outwards of the handle's centre)": f"{grip:+.3f}",
                "release": {"l:q0": "lowered, handle towards the robot", "d:q0": "dropped, handle towards the robot",
                            "d:q1": "dropped, handle to the side"}[f"{parts[2]}:{parts[3]}"]}
    if task == "pick_place":
        order, axes, heights = attrs["block_order"], attrs["grasp_axes"], parts[2]
        out = {"order": "-".join(order), "first object": order[0]}
        for k, name in enumerate(order):
            out[f"{name}: grasp height"] = "high" if heights[k] == "h" else "centre"
            out[f"{name}: pair of faces"] = str(axes[k])
        return out
    return {"order": "-".join(attrs["block_order"]), "grasp axes": "".join(map(str, attrs["grasp_axes"])),
            "grasp heights (middle, top)": parts[2]}


def _failure_mode(task: str, order: list[str], final_blocks: dict, scene: dict, kind: str) -> str:
    if task == "pick_place":
        return "; ".join(pick_place_misses(final_blocks, scene, kind)) or "all in their quadrants (the check failed)"
    if task in ("nut_assembly", "nut_assembly_round"):
        return nut_failure_mode(final_blocks, scene, kind)
    return failure_mode(order, final_blocks, scene, kind)


def analyse_dataset(path: Path) -> dict:
    from firp.core.episodes import EpisodeDataset

    factors: dict[str, Counter] = defaultdict(Counter)
    totals: dict[str, Counter] = defaultdict(Counter)
    modes: Counter = Counter()
    objects: Counter = Counter()  # pick_place: each object that missed its quadrant, over the failures
    default = Counter()
    with EpisodeDataset(path) as ds:
        n = len(ds)
        task = ds.attrs.get("task", "stack_three")
        for i in range(n):
            attrs, success = ds.demo_attrs(i), ds.success(i)
            keys = _factors(task, attrs)
            for factor, value in keys.items():
                totals[factor][value] += 1
                factors[factor][value] += success
            if attrs["is_default_choice"]:
                default["n"] += 1
                default["success"] += success
            if not success:
                modes[_failure_mode(task, attrs["block_order"], attrs["final_blocks"], attrs["scene"], attrs["kind"])] += 1
                if task == "pick_place":
                    objects.update(pick_place_misses(attrs["final_blocks"], attrs["scene"], attrs["kind"]))
        balance = ds.class_balance()
    return {
        "task": task, "episodes": n, "class_balance": balance,
        "success_by_factor": {factor: {value: {"episodes": totals[factor][value],
                                               "success_rate": round(factors[factor][value] / totals[factor][value], 3)}
                                       for value in sorted(totals[factor])} for factor in totals},
        "failure_modes": dict(modes.most_common()),
        **({"objects_missed": dict(objects.most_common())} if objects else {}),
        "default_choice_episodes": dict(default),
    }


_state: dict = {}


def _init(mm: float, deg: float) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from planner_client.robosuite_tamp import RobosuiteTampPlanner
    from robosuite_worker.world import RobosuiteWorld

    _state.update(world=RobosuiteWorld(image_size=32), planner=RobosuiteTampPlanner(), mm=mm, deg=deg)


def _survey_seed(args: tuple[str, int, int]) -> dict:
    """The choices of one scene in the loop's order until one succeeds; a choice the arm cannot reach (IK
    fails) is skipped as the loop skips it, and noted."""
    from planner_client.ik import IKFailure

    task, seed, max_tries = args
    world, planner = _state["world"], _state["planner"]
    start = world.begin(task, seed, _state["mm"], _state["deg"])
    tried = []
    for choice in planner.choices(task, start.observation)[:max_tries]:
        try:
            plan = planner.plan(task, start.observation, choice)
        except IKFailure as exc:
            tried.append({"choice": choice.label(), "unplannable": str(exc)})
            continue
        outcome = world.execute(start, plan.actions, False)
        tried.append({"choice": choice.label(), "success": outcome.success, "kind": outcome.kind,
                      "mode": None if outcome.success else _failure_mode(task, list(choice.order), outcome.final_blocks,
                                                                         start.observation["scene"], outcome.kind)})
        if outcome.success:
            break
    return {"seed": seed, "tried": tried}


def survey_summary(rows: list[dict], max_tries: int) -> dict:
    """Of the scenes whose first plannable choice (what TAMP alone executes) failed: how many another choice
    rescued within the loop's budget (its first ``LOOP_BUDGET`` choices, unplannable ones included, as the
    loop counts them) and within ``max_tries``."""
    executed = [[t for t in r["tried"] if "unplannable" not in t] for r in rows]
    planned = [(r, e) for r, e in zip(rows, executed) if e]
    failed = [(r, e) for r, e in planned if not e[0]["success"]]
    return {
        "scenes": len(rows), "scenes_with_no_plannable_choice": len(rows) - len(planned),
        "default_success_rate": round(1 - len(failed) / len(planned), 3) if planned else None,
        "default_failures": len(failed),
        f"rescued_within_{LOOP_BUDGET}_choices": sum(any(t.get("success") for t in r["tried"][:LOOP_BUDGET])
                                                     for r, _ in failed),
        f"rescued_within_{max_tries}_choices": sum(e[-1]["success"] for _, e in failed),
        "unplannable_choices_skipped": sum(len(r["tried"]) - len(e) for r, e in zip(rows, executed)),
        "default_failure_modes": dict(Counter(e[0]["mode"] for _, e in failed).most_common()),
    }


def survey(task: str, seeds: int, first_seed: int, workers: int, max_tries: int, mm: float, deg: float,
           rows_path: Path) -> dict:
    """Every seed's row is appended to ``rows_path`` as it ends; a rerun skips the seeds found there."""
    from planner_client.loop import read_records

    started = time.perf_counter()
    done = {int(r["seed"]): r for r in read_records(rows_path)}
    wanted = [first_seed + i for i in range(seeds)]
    jobs = [(task, seed, max_tries) for seed in wanted if seed not in done]
    append_as_done(rows_path, _survey_seed, jobs, done=done, key=lambda row: int(row["seed"]), workers=workers,
                   initializer=_init, initargs=(mm, deg), desc=f"survey {task}")
    rows = [done[seed] for seed in wanted]
    return {"seeds": [wanted[0], wanted[-1]], "pose_error": {"mm": mm, "deg": deg}, **survey_summary(rows, max_tries),
            "seconds_this_call": round(time.perf_counter() - started, 1), "rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default=None, choices=["stack_three", "nut_assembly", "nut_assembly_round", "pick_place"],
                        help="the survey's task (default: the dataset's, else stack_three)")
    parser.add_argument("--data", type=Path, default=None, help="a robosuite dataset to analyse (no simulation)")
    parser.add_argument("--seeds", type=int, default=0, help="scene seeds to survey in simulation (0: none)")
    parser.add_argument("--seed", type=int, default=200_000, help="first survey seed (datasets use 0..)")
    parser.add_argument("--max-tries", type=int, default=24, help="choices tried per failing seed at most")
    parser.add_argument("--workers", type=int, default=max(1, os.cpu_count() or 1))
    parser.add_argument("--pose-error-mm", type=float, default=3.0)
    parser.add_argument("--pose-error-deg", type=float, default=3.0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--rows", type=Path, default=None,
                        help="the survey's rows, one per seed as it ends (a rerun resumes); default: "
                             "runs/robosuite_survey_<task>_<seed>.jsonl")
    args = parser.parse_args(argv)
    if args.data is None and args.seeds <= 0:
        parser.error("--data or --seeds: nothing to measure")
    if args.task is None:  # the dataset says its own task; a survey alone defaults to stacking
        args.task = "stack_three"
        if args.data is not None:
            from firp.core.episodes import EpisodeDataset

            with EpisodeDataset(args.data) as ds:
                args.task = str(ds.attrs.get("task", args.task))
    result: dict = {"command": "python -m experiments.robosuite_choices " + " ".join(argv or sys.argv[1:]),
                    "task": args.task, "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    if args.data is not None:
        result["dataset"] = {"path": str(args.data), **analyse_dataset(args.data)}
        print(json.dumps({k: v for k, v in result["dataset"].items()}, indent=1))
    if args.seeds > 0:
        rows = args.rows or Path("runs") / f"robosuite_survey_{args.task}_{args.seed}.jsonl"
        result["survey"] = survey(args.task, args.seeds, args.seed, args.workers, args.max_tries,
                                  args.pose_error_mm, args.pose_error_deg, rows)
        print(json.dumps({k: v for k, v in result["survey"].items() if k != "rows"}, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
