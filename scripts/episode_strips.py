"""Picture strips of one successful and one failed episode per task, for the README.

Runs seeds in order with the planner's default block order until it has one success and one
failure per task, then saves 8 evenly spaced camera frames (with the step and action category
under each) as ``docs/pictures/<task>_<outcome>.png``.

    MUJOCO_GL=egl python scripts/episode_strips.py --size 128
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from PIL import Image, ImageDraw  # noqa: E402

from firp.core.contract import CATEGORIES, split_plan  # noqa: E402
from planner_client.tamp import TampPlanner  # noqa: E402
from sim_worker.executor import execute_plan  # noqa: E402
from sim_worker.perception import observation  # noqa: E402
from sim_worker.scene import RenderConfig  # noqa: E402
from sim_worker.tasks import TASK_NAMES, sample_initial_blocks  # noqa: E402
from sim_worker.world import World  # noqa: E402


def strip(frames: np.ndarray, categories: np.ndarray, title: str, n: int = 8) -> Image.Image:
    steps = np.linspace(0, len(frames) - 1, n).round().astype(int)
    size = frames.shape[1]
    label_h = 16
    canvas = Image.new("RGB", (n * size, size + 2 * label_h), "white")
    draw = ImageDraw.Draw(canvas)
    draw.text((4, 2), title, fill="black")
    for k, t in enumerate(steps):
        canvas.paste(Image.fromarray(frames[t]), (k * size, label_h))
        draw.text((k * size + 3, size + label_h + 2), f"t={t} {CATEGORIES[categories[t]]}"[:22], fill="black")
    return canvas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--out", type=Path, default=Path("docs/pictures"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    planner = TampPlanner()
    for task in TASK_NAMES:
        world = World(render=RenderConfig.for_task(task, args.size, args.size))
        wanted = {True, False}
        for seed in range(100):
            blocks = sample_initial_blocks(task, seed)
            plan = planner.plan(task, observation(blocks, seed, world.layout))
            result = execute_plan(world, task, blocks, plan.actions)
            if result.success not in wanted:
                continue
            wanted.discard(result.success)
            outcome = "success" if result.success else "failure"
            title = f"{task}, seed {seed}, order {'-'.join(plan.order)}: {outcome} ({result.reason})"
            path = args.out / f"{task}_{outcome}.png"
            strip(result.frames, split_plan(plan.actions)[0], title).save(path)
            print(f"wrote {path}: {title}")
            if not wanted:
                break


if __name__ == "__main__":
    main()
