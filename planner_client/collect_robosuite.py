"""Labelled datasets in the robosuite world: per episode a seeded scene and a planner choice drawn from it.

As in our world (:mod:`planner_client.collect`), episode ``i`` uses scene seed ``seed_offset + i`` and
the planner's choice for it (for ``stack_three``: the tower's order and each grasp's pair of faces) is
drawn from that seed, so an episode is fully determined by its index and a resumed collection skips
what is on disk. The label comes from the robosuite environment's own success check. Runs in the
robosuite environment (``.venv-robosuite``): ``firp collect --world robosuite`` hands over to it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firp.core.contract import FPS
from firp.core.episodes import EpisodeRecord
from planner_client.collect import parts_dir_of, run_collection
from planner_client.ik import IKFailure
from planner_client.robosuite_tamp import TASK_HORIZONS, Choice, RobosuiteTampPlanner

__all__ = ["CHOICE_STREAM", "RobosuiteCollectConfig", "collect_robosuite", "episode_choice", "planned_choice",
           "simulate_episode"]

CHOICE_STREAM = 13  # separates the choice draw from the scene and perception streams
MAX_CHOICE_TRIES = 64  # drawn choices tried per scene before it counts as unplannable


@dataclass(frozen=True)
class RobosuiteCollectConfig:
    task: str
    episodes: int
    out: Path
    workers: int = 2
    seed_offset: int = 0
    image_size: int = 84
    camera: str = "agentview"
    pose_error_mm: float = 3.0
    pose_error_deg: float = 3.0

    @property
    def parts_dir(self) -> Path:
        return parts_dir_of(self.out)

    @property
    def horizon(self) -> int:
        return TASK_HORIZONS[self.task]


def episode_choice(seed: int, choices: list[Choice]) -> Choice:
    """The planner's choice for the episode with scene seed ``seed``: uniform over every choice."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, CHOICE_STREAM]))
    return choices[int(rng.integers(len(choices)))]


def planned_choice(planner: RobosuiteTampPlanner, task: str, observation: dict, seed: int
                   ) -> tuple[Choice, object, int]:
    """The episode's choice, its plan and how many drawn choices were unreachable: when the arm cannot reach
    a choice's poses (IK fails), the next one of a permutation drawn from the same seed is taken -- still
    determined by the seed alone. After ``MAX_CHOICE_TRIES`` unreachable choices the scene counts as
    unplannable (IKFailure): pick_place has 3072 choices, and trying them all would take many minutes."""
    choices = planner.choices(task, observation)
    first = episode_choice(seed, choices)
    rng = np.random.default_rng(np.random.SeedSequence([seed, CHOICE_STREAM, 1]))
    tries = [first, *(choices[i] for i in rng.permutation(len(choices)) if choices[i] != first)]
    for skipped, choice in enumerate(tries[:MAX_CHOICE_TRIES]):
        try:
            return choice, planner.plan(task, observation, choice), skipped
        except IKFailure:
            continue
    raise IKFailure(f"seed {seed}: none of {min(len(tries), MAX_CHOICE_TRIES)} choices of the {task} planner "
                    "is reachable in this scene")


def simulate_episode(world, planner: RobosuiteTampPlanner, task: str, seed: int, pose_error_mm: float,
                     pose_error_deg: float, record_frames: bool = True) -> EpisodeRecord:
    """One labelled episode: the seeded scene, the plan for its drawn choice, the execution."""
    start = world.begin(task, seed, pose_error_mm, pose_error_deg)
    choices = planner.choices(task, start.observation)
    choice, plan, skipped = planned_choice(planner, task, start.observation, seed)
    outcome = world.execute(start, plan.actions, record_frames)
    horizon = len(plan.actions)
    frames = outcome.frames if outcome.frames is not None else np.zeros((horizon, 1, 1, 3), np.uint8)
    states = outcome.states if outcome.states is not None else np.zeros((horizon, 1))
    return EpisodeRecord(
        frames=frames, actions=plan.actions.astype(np.float32), states=states, success=bool(outcome.success),
        attrs={"task": task, "seed": int(seed), "choice": choice.label(), "choice_index": choices.index(choice),
               "is_default_choice": choice == choices[0], "unreachable_choices_skipped": skipped,
               "block_order": list(choice.order), "grasp_axes": list(choice.axes), "pose_estimates": start.observation["blocks"],
               "scene": start.observation["scene"], "grasp_yaws": plan.grasp_yaws,
               "place_targets": plan.place_targets, "kind": outcome.kind, "reason": outcome.reason,
               "final_blocks": outcome.final_blocks, "sim_seconds": outcome.sim_seconds,
               "unstable": outcome.unstable})


# -- worker processes --------------------------------------------------------------------------
_worker: dict = {}


def _init_worker(config: RobosuiteCollectConfig) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from robosuite_worker.world import RobosuiteWorld

    _worker["config"] = config
    _worker["world"] = RobosuiteWorld(image_size=config.image_size, camera=config.camera)
    _worker["planner"] = RobosuiteTampPlanner()


def _simulate_one(index: int) -> EpisodeRecord:
    config: RobosuiteCollectConfig = _worker["config"]
    return simulate_episode(_worker["world"], _worker["planner"], config.task, config.seed_offset + index,
                            config.pose_error_mm, config.pose_error_deg)


def _check_camera(config: RobosuiteCollectConfig) -> None:
    """A camera the task lacks fails here (:class:`robosuite_worker.world.UnknownCamera`), before any worker starts:
    in a worker it would surface as a pool's traceback. Costs one environment made and closed (1-3 s)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from robosuite_worker.world import RobosuiteWorld

    world = RobosuiteWorld(image_size=config.image_size, camera=config.camera)
    try:
        world.env(config.task)
    finally:
        world.close()


def dataset_attrs(config: RobosuiteCollectConfig) -> dict:
    import robosuite

    from robosuite_worker.tasks import check_task
    from robosuite_worker.world import CONTROL_HZ, SETTLE_SECONDS

    return {"env": "robosuite", "robosuite_version": robosuite.__version__, "task": config.task,
            "robosuite_env": check_task(config.task).env, "fps": FPS, "T": config.horizon,
            "image_height": config.image_size, "image_width": config.image_size, "camera": config.camera,
            "seed_offset": config.seed_offset, "control_hz": CONTROL_HZ, "settle_seconds": SETTLE_SECONDS,
            "pose_error": {"mm": config.pose_error_mm, "deg": config.pose_error_deg},
            "choices": "uniform over the planner's choices (planner_client.collect_robosuite.episode_choice)"}


def collect_robosuite(config: RobosuiteCollectConfig, progress: bool = True, ray: str | None = None) -> dict:
    """Collect ``config.episodes`` robosuite episodes into ``config.out`` (resuming), return the class balance;
    on a process pool, or with ``ray`` on Ray actors (:func:`planner_client.collect.run_collection`)."""
    if config.task not in TASK_HORIZONS:
        raise ValueError(f"task: the robosuite world has no task {config.task!r}; one of {list(TASK_HORIZONS)}")
    _check_camera(config)
    return run_collection(out=config.out, parts_dir=config.parts_dir, episodes=config.episodes,
                          workers=config.workers, initializer=_init_worker, initargs=(config,),
                          simulate_one=_simulate_one, attrs=dataset_attrs(config),
                          desc=f"collect robosuite {config.task}", progress=progress, ray=ray)
