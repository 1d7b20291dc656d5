"""Collecting a robosuite dataset: the project's HDF5 layout, labels from the world, resume, the CLI's rules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firp.core.episodes import EpisodeDataset
from planner_client.collect_robosuite import RobosuiteCollectConfig, collect_robosuite, episode_choice
from planner_client.robosuite_tamp import RobosuiteTampPlanner

ROOT = Path(__file__).resolve().parents[2]


def test_the_choice_is_drawn_from_the_seed_alone_and_covers_the_choices(world):
    choices = RobosuiteTampPlanner().choices("stack_three", world.begin("stack_three", 0, 3.0, 3.0).observation)
    drawn = [episode_choice(seed, choices) for seed in range(400)]
    assert drawn == [episode_choice(seed, choices) for seed in range(400)]
    assert len(set(drawn)) == len(choices)


def test_a_tiny_collection_reads_back_and_resumes(tmp_path):
    out = tmp_path / "stack_three.h5"
    config = RobosuiteCollectConfig(task="stack_three", episodes=2, out=out, workers=1, image_size=16)
    first = collect_robosuite(config, progress=False)
    assert (first["total"], first["new_episodes"]) == (2, 2)
    grown = collect_robosuite(RobosuiteCollectConfig(task="stack_three", episodes=3, out=out, workers=1,
                                                     image_size=16), progress=False)
    assert (grown["total"], grown["new_episodes"]) == (3, 1)
    with EpisodeDataset(out) as ds:
        assert len(ds) == 3 and ds.attrs["env"] == "robosuite" and ds.attrs["T"] == 80
        for i in range(3):
            episode = ds.episode(i)
            assert episode.frames.shape == (80, 16, 16, 3) and episode.actions.shape == (80, 16)
            assert episode.states.shape[0] == 80 and np.abs(episode.states).sum() > 0
            assert episode.attrs["seed"] == i and episode.attrs["kind"] in ("success", "not_done", "unstable")
            assert episode.attrs["reason"].startswith("StackThree: ")
            assert episode.success == (episode.attrs["kind"] == "success")
            assert not np.array_equal(episode.frames[0], episode.frames[-1])  # the arm moved in view


@pytest.mark.parametrize(("args", "message"), [
    (["--task", "stacking"], "--task: 'stacking' is not a task of the robosuite world"),
    (["--task", "stack_three", "--horizon", "60"], "--horizon: the robosuite world's tasks have a fixed T"),
    (["--task", "nut_assembly", "--camera", "workspaceview"],
     "--camera: 'workspaceview' is not a camera of the nut_assembly task; one of"),
])
def test_the_cli_names_the_field_and_the_rule(tmp_path, args, message):
    out = subprocess.run([sys.executable, "-m", "planner_client", "collect", "--world", "robosuite", "--episodes", "1",
                          "--out", str(tmp_path / "x.h5"), *args], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    assert out.returncode == 2 and message in out.stderr, out.stderr
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "x.h5.parts").exists()


def test_an_unreachable_choice_gives_way_to_the_next_one_drawn_from_the_seed(world):
    from planner_client.collect_robosuite import planned_choice
    from planner_client.ik import IKFailure

    class Reachless(RobosuiteTampPlanner):
        def plan(self, task, observation, choice=None):
            if choice == episode_choice(5, self.choices(task, observation)):
                raise IKFailure("out of reach")
            return super().plan(task, observation, choice)

    observation = world.begin("stack_three", 5, 3.0, 3.0).observation
    planner = Reachless()
    first, plan, skipped = planned_choice(planner, "stack_three", observation, 5)
    assert first != episode_choice(5, planner.choices("stack_three", observation)) and skipped == 1
    assert planned_choice(planner, "stack_three", observation, 5)[0] == first and plan.actions.shape == (80, 16)
    assert planned_choice(RobosuiteTampPlanner(), "stack_three", observation, 5)[0] == episode_choice(
        5, planner.choices("stack_three", observation))
