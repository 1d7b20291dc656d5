"""Labelled dataset collection: sample seeds and block orders, plan, execute, record.

Episode ``i`` of a collection uses scene seed ``seed_offset + i`` and a block order drawn from
that seed, so an episode is fully determined by its index: a resumed collection simply skips the
indices already on disk. Workers (separate processes, or Ray actors: :mod:`planner_client.ray_collection`)
each own a World and a planner; each finished episode becomes one atomic part file; the parent shows
progress and, at the end, merges the parts into the robomimic-style HDF5 file in one atomic replace.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from firp.core.contract import DEFAULT_T, FPS
from firp.core.episodes import EpisodeDataset, EpisodeRecord, completed_indices, consolidate, write_episode_part
from planner_client.ik import IKFailure
from planner_client.tamp import Plan, PlannerConfig, TampPlanner, block_orders
from sim_worker.executor import ExecutorConfig, execute_plan
from sim_worker.perception import PoseErrorConfig, observation
from sim_worker.robot import kinematic_chain
from sim_worker.scene import BLOCK_NAMES, CAMERA, RenderConfig, SceneLayout
from sim_worker.tasks import SamplerConfig, check_task, sample_initial_blocks
from sim_worker.world import World

log = logging.getLogger(__name__)

ORDER_STREAM = 11  # separates the block-order draw from the scene and perception streams


def parts_dir_of(out: Path) -> Path:
    """Where a collection into ``out`` keeps its finished episodes until they are merged."""
    return out.with_name(out.name + ".parts")


@dataclass(frozen=True)
class CollectConfig:
    task: str
    episodes: int
    out: Path
    workers: int = 2
    seed_offset: int = 0
    horizon: int = DEFAULT_T
    image_size: int = 84
    pose_error: PoseErrorConfig = field(default_factory=PoseErrorConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    #: episodes ``0 .. framed-1`` keep a frame per step (what the RSSM's prediction terms train on), the rest
    #: only the initial frame (a third of the cost: no rendering while the plan runs); None: every episode
    framed: int | None = None
    #: > 0: every episode also keeps its initial image at this many pixels square, for the plan-conditioned view
    view_size: int = 0
    #: with ``view_size``: also the settled final scene at that size (what an Oracle reads)
    final_view: bool = False

    @property
    def parts_dir(self) -> Path:
        return parts_dir_of(self.out)

    def keeps_frames(self, index: int) -> bool:
        return self.framed is None or index < self.framed


def episode_order(seed: int) -> tuple[str, ...]:
    """The block order used for the episode with scene seed ``seed`` (uniform over all orders)."""
    orders = block_orders(BLOCK_NAMES)
    rng = np.random.default_rng(np.random.SeedSequence([seed, ORDER_STREAM]))
    return orders[int(rng.integers(len(orders)))]


@dataclass(frozen=True)
class PlannedEpisode:
    """An episode before execution: its true initial state, what the planner was told, its plan."""

    task: str
    seed: int
    order: tuple[str, ...]
    true_blocks: np.ndarray  # (n, 4) x, y, z, yaw
    observation: dict
    plan: Plan

    def attrs(self) -> dict:
        """The record attrs that do not depend on the execution."""
        return {"task": self.task, "seed": int(self.seed), "block_order": list(self.order),
                "pose_estimates": self.observation["blocks"], "true_initial_blocks": self.true_blocks.tolist(),
                "grasp_yaws": self.plan.grasp_yaws, "place_targets": self.plan.place_targets}


def plan_episode(planner: TampPlanner, task: str, seed: int, order: tuple[str, ...], pose_error: PoseErrorConfig,
                 layout: SceneLayout = SceneLayout(), sampler: SamplerConfig = SamplerConfig()) -> PlannedEpisode:
    """Initial state from ``seed`` and the plan the planner makes from its noisy estimates of it."""
    true_blocks = sample_initial_blocks(task, seed, layout, sampler)
    obs = observation(true_blocks, seed, layout, pose_error)
    return PlannedEpisode(task, seed, tuple(order), true_blocks, obs, planner.plan(task, obs, order))


def simulate_episode(world: World, planner: TampPlanner, task: str, seed: int, order: tuple[str, ...],
                     pose_error: PoseErrorConfig, sampler: SamplerConfig = SamplerConfig(),
                     record_frames: bool = True, initial_frame: bool = False, view_size: int = 0,
                     final_view: bool = False) -> EpisodeRecord:
    """One labelled episode: initial state from ``seed``, plan from the noisy estimates, execution.

    Without ``record_frames`` the frames are the initial image alone with ``initial_frame`` (1, H, W, 3),
    else a 1-pixel placeholder per step; ``view_size`` > 0 adds the initial image at that size (``view``) and with
    ``final_view`` the settled final scene too (``final_view``)."""
    planned = plan_episode(planner, task, seed, order, pose_error, world.layout, sampler)
    actions = planned.plan.actions
    initial = view = None
    if view_size or (initial_frame and not record_frames):
        world.reset(planned.true_blocks)
        view = world.render(size=view_size)[None] if view_size else None
        initial = world.render()[None] if initial_frame and not record_frames else None
    result = execute_plan(world, task, planned.true_blocks, actions, ExecutorConfig(record_frames=record_frames))
    frames = result.frames if result.frames is not None else (
        initial if initial is not None else np.zeros((len(actions), 1, 1, 3), np.uint8))
    final = world.render(size=view_size)[None] if final_view and view_size else None  # the world is where it ended
    return EpisodeRecord(
        frames=frames,
        actions=actions.astype(np.float32),
        states=result.states,
        success=bool(result.success),
        attrs={
            **planned.attrs(), "reason": result.reason, "final_blocks": result.final_block_poses.tolist(),
            "sim_seconds": result.sim_seconds, "unstable": result.unstable,
        },
        view=view,
        final_view=final,
    )


# -- worker processes --------------------------------------------------------------------------
_worker: dict = {}


def _init_worker(config: CollectConfig) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    _worker["config"] = config
    _worker["world"] = World(SceneLayout(), RenderConfig.for_task(config.task, config.image_size, config.image_size))
    _worker["planner"] = TampPlanner(PlannerConfig(horizon=config.horizon))


def _simulate_one(index: int) -> EpisodeRecord:
    config: CollectConfig = _worker["config"]
    seed = config.seed_offset + index
    return simulate_episode(_worker["world"], _worker["planner"], config.task, seed, episode_order(seed),
                            config.pose_error, config.sampler, record_frames=config.keeps_frames(index),
                            initial_frame=True, view_size=config.view_size, final_view=config.final_view)


# -- the process pool's side of run_collection -------------------------------------------------
_pool: dict = {}


def _pool_init(initializer, initargs: tuple, simulate_one, parts_dir: Path) -> None:
    initializer(*initargs)
    _pool.update(simulate_one=simulate_one, parts_dir=parts_dir)


def attempt_episode(simulate_one, index: int) -> EpisodeRecord | str:
    """``simulate_one(index)``'s record, or why the planner could plan nothing for the scene (logged): an
    unplannable scene gives no episode, on a process pool and on Ray alike."""
    try:
        return simulate_one(index)
    except IKFailure as exc:
        log.warning("episode %d skipped: %s", index, exc)
        return str(exc)


def _pool_collect_one(index: int) -> tuple[int, bool | None]:
    """Simulate and write episode ``index``: its success, or None when the planner could plan nothing."""
    record = attempt_episode(_pool["simulate_one"], index)
    if isinstance(record, str):
        return index, None
    write_episode_part(_pool["parts_dir"], index, record)
    return index, bool(record.success)


def dataset_attrs(config: CollectConfig, layout: SceneLayout = SceneLayout()) -> dict:
    """The dataset's attributes: what it was collected with, and -- where the collection keeps only initial
    frames for some episodes or a view -- the arm's kinematics and the camera's calibration (at the frames'
    size), which the plan-conditioned view reads (a dataset collected as before keeps its attributes, so an
    earlier collection still resumes)."""
    attrs = {
        "env": "firp-mujoco-panda", "task": config.task, "fps": FPS, "T": config.horizon,
        "image_height": config.image_size, "image_width": config.image_size, "camera": CAMERA,
        "block_names": list(BLOCK_NAMES), "seed_offset": config.seed_offset,
        "camera_pose": asdict(RenderConfig.for_task(config.task).camera),
        "pose_error": asdict(config.pose_error), "sampler": asdict(config.sampler),
        "timestep": layout.timestep,
    }
    if config.framed is not None or config.view_size:
        with World(layout, RenderConfig.for_task(config.task, config.image_size, config.image_size)) as world:
            attrs["kinematics"] = kinematic_chain(world.model, world.data).to_dict()
            attrs["camera_calibration"] = world.camera_calibration().to_dict()
        attrs["framed_episodes"] = -1 if config.framed is None else config.framed
        attrs["view_size"] = config.view_size
        if config.final_view:
            attrs["final_view"] = True
    return attrs


def run_collection(*, out: Path, parts_dir: Path, episodes: int, workers: int, initializer, initargs: tuple,
                   simulate_one, attrs: dict, desc: str, progress: bool = True, ray: str | None = None,
                   on_actors=None) -> dict:
    """Collect episodes ``0 .. episodes-1`` into ``out`` with ``workers`` worker processes (resuming).

    ``initializer(*initargs)`` sets up each worker (its world and planner); ``simulate_one(index)``
    simulates episode ``index`` there and returns its :class:`EpisodeRecord`. Both must be module-level
    functions (workers are spawned, never forked: no forked GL contexts). The workers are a process pool
    on this machine, or with ``ray`` (``local``, ``auto`` or an address) Ray actors
    (:mod:`planner_client.ray_collection`, which passes ``on_actors`` the actor handles). Each finished
    episode is one atomic part file; at the end the parts are merged into ``out`` with the dataset
    ``attrs``; the class balance is returned. A scene the planner cannot plan at all (``IKFailure``)
    gives no episode: it is logged, listed in the balance (``unplannable``) and tried again on resume,
    and the other episodes go on.
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    done = completed_indices(out, parts_dir)
    pending = [i for i in range(episodes) if i not in done]
    started = time.perf_counter()
    successes = simulated = 0
    unplannable: list[int] = []
    if pending:
        bar = tqdm(total=episodes, initial=episodes - len(pending), desc=desc, unit="ep", disable=not progress)
        if ray is not None:
            from planner_client.ray_collection import simulate_on_ray

            results = simulate_on_ray(address=ray, actors=workers, pending=pending, parts_dir=parts_dir,
                                      initializer=initializer, initargs=initargs, simulate_one=simulate_one,
                                      on_actors=on_actors)
        else:
            ctx = mp.get_context("spawn")
            pool = ctx.Pool(max(1, min(workers, len(pending))), initializer=_pool_init,
                            initargs=(initializer, initargs, simulate_one, parts_dir))
            results = pool.imap_unordered(_pool_collect_one, pending)
        try:
            for index, success in results:
                if success is None:
                    unplannable.append(index)
                else:
                    successes += success
                    simulated += 1
                bar.update(1)
                bar.set_postfix(success=f"{successes / max(1, simulated):.2f}", unplannable=len(unplannable))
        finally:
            if ray is None:
                pool.terminate()
                pool.join()
        bar.close()
    if pending or not out.exists():
        consolidate(parts_dir, out, attrs)
    with EpisodeDataset(out) as ds:
        balance = ds.class_balance()
    balance["new_episodes"] = len(pending) - len(unplannable)
    if unplannable:  # no plan for the scene: no episode; a resumed collection tries them again
        balance["unplannable"] = sorted(unplannable)
    balance["seconds"] = round(time.perf_counter() - started, 1)
    return balance


def collect(config: CollectConfig, progress: bool = True, ray: str | None = None, on_actors=None) -> dict:
    """Collect ``config.episodes`` episodes into ``config.out`` (resuming), return the class balance;
    on a process pool, or with ``ray`` on Ray actors (:func:`run_collection`)."""
    check_task(config.task)
    return run_collection(out=config.out, parts_dir=config.parts_dir, episodes=config.episodes,
                          workers=config.workers, initializer=_init_worker, initargs=(config,),
                          simulate_one=_simulate_one, attrs=dataset_attrs(config), desc=f"collect {config.task}",
                          progress=progress, ray=ray, on_actors=on_actors)
