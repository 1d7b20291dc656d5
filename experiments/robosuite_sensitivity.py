"""How much of a robosuite plan's outcome do the scene's last millimetres decide? The pre-execution ceiling
in the robosuite world, measured as ``experiments.outcome_sensitivity`` measures it in ours.

Per episode (scene seed ``--seed-offset + i``, the plan a ``firp collect --world robosuite`` dataset records
for that seed: its drawn choice, planned from the perceived poses), the plan is executed once from the
scene at rest and ``--perturbations`` more times from the same scene with every object moved in the plane
(``--xy-mm`` standard deviation per axis) and turned (``--yaw-deg``) -- by default the planner's own
perception error, so a predictor that knew the scene as well as the planner does could not tell these
scenes apart. The plan is fixed; only robosuite's contact physics sees the difference.

The share of plans whose outcome flips under some perturbation, and the balanced accuracy of thresholding
each plan's perturbed success rate against its unperturbed outcome (best threshold, and chosen by 5-fold
cross-validation): no scorer that reads the initial scene to that precision can beat it by more than this
estimate's noise, whatever its architecture. Each episode is appended to a JSONL file as soon as it is
done; a rerun resumes.

    .venv-robosuite/bin/python -m experiments.robosuite_sensitivity --task stack_three --episodes 40 \\
        --out runs/robosuite_sensitivity_stack_three.jsonl --report docs/results/robosuite_stack_three_sensitivity.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from experiments.outcome_sensitivity import analyse
from experiments.resumable import run_seeds

PERTURB_STREAM = 29  # separates the perturbation draws from the scene, perception and choice streams

_state: dict = {}


def shifts(names: list[str], seed: int, k: int, xy_std_m: float, yaw_std_deg: float) -> dict[str, tuple]:
    """Draw ``k`` of episode ``seed``: every object's (dx, dy, dyaw)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, PERTURB_STREAM, k]))
    return {name: (float(rng.normal(0.0, xy_std_m)), float(rng.normal(0.0, xy_std_m)),
                   float(np.radians(rng.normal(0.0, yaw_std_deg)))) for name in sorted(names)}


def _init(task: str, perturbations: int, xy_std_m: float, yaw_std_deg: float, mm: float, deg: float) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from planner_client.robosuite_tamp import RobosuiteTampPlanner
    from robosuite_worker.world import RobosuiteWorld

    _state.update(world=RobosuiteWorld(image_size=32), planner=RobosuiteTampPlanner(), task=task, k=perturbations,
                  xy=xy_std_m, yaw=yaw_std_deg, mm=mm, deg=deg)


def run_episode(seed: int) -> dict:
    """The dataset's plan for ``seed``, executed from the scene at rest and from ``k`` shifted scenes."""
    from planner_client.collect_robosuite import planned_choice
    from planner_client.ik import IKFailure

    world, planner, task = _state["world"], _state["planner"], _state["task"]
    start = world.begin(task, seed, _state["mm"], _state["deg"])
    try:
        choice, plan, _ = planned_choice(planner, task, start.observation, seed)
    except IKFailure as exc:
        return {"seed": seed, "unplannable": str(exc)}
    base = world.execute(start, plan.actions, False)
    names = list(start.observation["blocks"])
    outcomes, reasons = [], []
    for k in range(_state["k"]):
        result = world.execute(start, plan.actions, False, shift=shifts(names, seed, k, _state["xy"], _state["yaw"]))
        outcomes.append(bool(result.success))
        reasons.append(result.reason)
    return {"seed": seed, "choice": choice.label(), "success": bool(base.success), "reason": base.reason,
            "perturbed_success": outcomes, "perturbed_reasons": reasons}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, choices=["stack_three", "nut_assembly", "nut_assembly_round",
                                                          "pick_place"])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed-offset", type=int, default=0, help="first scene seed (a dataset's are 0..)")
    parser.add_argument("--perturbations", type=int, default=6)
    parser.add_argument("--xy-mm", type=float, default=3.0, help="in-plane shift, standard deviation per axis")
    parser.add_argument("--yaw-deg", type=float, default=3.0, help="turn about z, standard deviation")
    parser.add_argument("--pose-error-mm", type=float, default=3.0, help="the planner's perception error")
    parser.add_argument("--pose-error-deg", type=float, default=3.0)
    parser.add_argument("--workers", type=int, default=max(1, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, required=True, help="JSONL of the episodes (a rerun resumes)")
    parser.add_argument("--report", type=Path, required=True)
    args = parser.parse_args(argv)
    for flag, value in (("--episodes", args.episodes), ("--perturbations", args.perturbations),
                        ("--workers", args.workers)):
        if value < 1:
            parser.error(f"{flag}: must be at least 1, got {value}")
    started = time.perf_counter()
    wanted = [args.seed_offset + i for i in range(args.episodes)]
    done = run_seeds(args.out, run_episode, wanted, workers=args.workers, initializer=_init,
                     initargs=(args.task, args.perturbations, args.xy_mm / 1000.0, args.yaw_deg, args.pose_error_mm,
                               args.pose_error_deg), desc=f"sensitivity {args.task}")
    records = [done[s] for s in wanted]
    planned = [r for r in records if "unplannable" not in r]
    if len({r["success"] for r in planned}) < 2:
        parser.error(f"the {len(planned)} plans' outcomes are of one class; ask for more --episodes")
    result = {"task": args.task, "episodes": len(records), "unplannable": len(records) - len(planned),
              "seeds": [wanted[0], wanted[-1]], "perturbation": {"xy_mm_std": args.xy_mm, "yaw_deg_std": args.yaw_deg},
              "pose_error": {"mm": args.pose_error_mm, "deg": args.pose_error_deg}, **analyse(planned),
              "seconds_this_call": round(time.perf_counter() - started, 1),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "command": "python -m experiments.robosuite_sensitivity " + " ".join(argv or sys.argv[1:])}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k not in ("machine",)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
