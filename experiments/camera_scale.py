"""How many millimetres one pixel of a robosuite task's image spans where its objects lie.

A scorer that must tell where on a nut's handle the fingers close (grip points 4-5 mm apart) can only
read that from the image if a few millimetres are visible at the image's size. This experiment projects
each object of the scene at rest, and the same point moved 1 cm along the world's x (away from the robot's
base, towards the default camera) and y (sideways), through the task's camera with robosuite's own
camera matrices, over several scenes; it reports pixels per centimetre and millimetres per pixel along
each axis (medians over objects and scenes).

Runs in the robosuite environment:

    MUJOCO_GL=egl .venv-robosuite/bin/python -m experiments.camera_scale --task nut_assembly \\
        --out docs/results/robosuite_camera_scale.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

STEP_M = 0.01  # the displacement projected (1 cm)


def project(matrix: np.ndarray, point: np.ndarray) -> np.ndarray:
    """A world point ``(3,)`` -> its pixel ``(2,)`` through a 4x4 camera transform (robosuite's convention)."""
    h = matrix @ np.append(point, 1.0)
    return h[:2] / h[2]


def pixels_per_cm(matrix: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """Pixels one centimetre spans at ``point`` along the world's x and y."""
    here = project(matrix, point)
    return tuple(float(np.linalg.norm(project(matrix, point + STEP_M * axis) - here) / (100 * STEP_M))
                 for axis in np.eye(3)[:2])


def measure(task: str, camera: str, image_size: int, scenes: int) -> dict:
    from robosuite.utils.camera_utils import get_camera_transform_matrix

    from robosuite_worker.tasks import body_pose, check_task
    from robosuite_worker.world import RobosuiteWorld

    world = RobosuiteWorld(image_size=image_size, camera=camera, tasks=(task,))
    spec = check_task(task)
    rows = []
    try:
        for seed in range(scenes):
            world.begin(task, seed, pose_error_mm=0.0, pose_error_deg=0.0)  # the scene at rest, as episodes start
            env = world.env(task)
            matrix = get_camera_transform_matrix(env.sim, camera, image_size, image_size)
            for name, body in spec.objects(env).items():
                x, y = pixels_per_cm(matrix, body_pose(env, body)[0])
                rows.append({"seed": seed, "object": name, "px_per_cm_x": x, "px_per_cm_y": y})
    finally:
        world.close()
    x = float(np.median([r["px_per_cm_x"] for r in rows]))
    y = float(np.median([r["px_per_cm_y"] for r in rows]))
    return {"task": task, "camera": camera, "image_size": image_size, "scenes": scenes,
            "px_per_cm_x": x, "px_per_cm_y": y, "mm_per_px_x": 10.0 / x, "mm_per_px_y": 10.0 / y, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", nargs="+", default=["nut_assembly"], help="robosuite tasks (firp's names)")
    parser.add_argument("--camera", default="agentview")
    parser.add_argument("--image-size", type=int, default=84)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    if args.scenes < 1:
        parser.error("--scenes: at least 1")
    if args.image_size < 8:
        parser.error("--image-size: at least 8 pixels")
    results = [measure(task, args.camera, args.image_size, args.scenes) for task in args.task]
    print(f"{'task':<16} {'camera':<14} {'px':>4} {'px/cm x':>8} {'px/cm y':>8} {'mm/px x':>8} {'mm/px y':>8}")
    for r in results:
        print(f"{r['task']:<16} {r['camera']:<14} {r['image_size']:>4} {r['px_per_cm_x']:>8.2f} {r['px_per_cm_y']:>8.2f} "
              f"{r['mm_per_px_x']:>8.1f} {r['mm_per_px_y']:>8.1f}")
    if args.out:
        command = "python -m experiments.camera_scale " + shlex.join(sys.argv[1:] if argv is None else argv)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": command, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
