"""Every execution is data: the plans the trial loop executes, recorded as episodes training reads.

Why: collection draws one planner choice per scene, but the loop executes several candidates of the
*same* scene and the sim worker labels each one -- exactly the data a scorer that must rank a
scene's candidates learns from best. ``firp run --record DIR`` keeps all of it: per executed plan the
frames the sim worker rendered (frame ``t`` before step ``t``, frame 0 the scene's initial image),
the plan, the label, and what links and explains it -- ``scene_id`` (task and seed: the candidates
of one scene share it), the candidate and its place in the loop's order, the score the ensemble gave
it and the bundle version that scored it (absent for plans only the baselines executed).

Storage is the project's HDF5 layout, written the way collection writes it: one part file per
execution under ``DIR/executions.h5.parts`` (atomic: written beside, then renamed), merged into
``DIR/executions.h5`` when the run ends, so a killed run loses nothing and a resumed run re-records
nothing it has. Training reads the merged file like any collected dataset (``--data``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from firp.core.contract import FPS
from firp.core.episodes import EpisodeRecord, write_episode_part
from firp.core.episodes.writer import consolidate

__all__ = ["ExecutionRecorder", "SLOTS_PER_TRIAL", "frames_of"]

#: part indices per trial (trial * SLOTS_PER_TRIAL + the candidate's place in the loop's order)
SLOTS_PER_TRIAL = 100


def frames_of(outcome: Any) -> np.ndarray:
    """The frames of an execution asked with ``record_frames``: arrays (in-process) or base64 PNGs (HTTP)."""
    frames = getattr(outcome, "frames", None)
    if frames is not None:
        return np.asarray(frames, dtype=np.uint8)
    encoded = getattr(outcome, "frames_b64", None)
    if not encoded:
        raise ValueError("the simulator returned no frames for an execution recorded with record_frames")
    from world_api.images import decode_png_b64

    return np.stack([decode_png_b64(f) for f in encoded])


@dataclass
class ExecutionRecorder:
    """Writes the loop's executions of one run into ``directory``."""

    directory: Path
    task: str
    horizon: int
    world: str = "mujoco"

    @property
    def out(self) -> Path:
        return self.directory / "executions.h5"

    @property
    def parts_dir(self) -> Path:
        return self.directory / "executions.h5.parts"

    @staticmethod
    def index(trial: int, place: int) -> int:
        if not 0 <= place < SLOTS_PER_TRIAL:
            raise ValueError(f"a trial records at most {SLOTS_PER_TRIAL} candidates, got place {place}")
        return trial * SLOTS_PER_TRIAL + place

    def record(self, *, trial: int, place: int, episode: Any, candidate: str, plan: np.ndarray, outcome: Any,
               frames: np.ndarray, score: float | None, model: dict | None) -> None:
        """One executed plan as an episode part (nothing is written twice: a resumed run skips it)."""
        index = self.index(trial, place)
        attrs = {"task": self.task, "seed": int(episode.seed), "scene_id": f"{self.task}/{int(episode.seed)}",
                 "trial": int(trial), "candidate": candidate, "candidate_index": int(place),
                 "kind": outcome.kind, "reason": outcome.reason, "sim_seconds": float(outcome.sim_seconds),
                 "pose_estimates": episode.observation.get("blocks", {}), "recorded_by": "firp run --record"}
        if score is not None:
            attrs["score"] = float(score)
        if model is not None:
            attrs["scored_by"] = {"name": model.get("name"), "version": model.get("version")}
        record = EpisodeRecord(frames=frames, actions=np.asarray(plan, dtype=np.float32),
                               states=np.zeros((len(plan), 1)), success=bool(outcome.success), attrs=attrs)
        write_episode_part(self.parts_dir, index, record)

    def dataset_attrs(self, image_size: int) -> dict:
        return {"env": "robosuite" if self.world == "robosuite" else "firp-mujoco-panda", "task": self.task,
                "fps": FPS, "T": self.horizon, "image_height": image_size, "image_width": image_size,
                "source": "executions of the trial loop (firp run --record); scene_id links a scene's candidates"}

    def consolidate(self) -> Path | None:
        """Merge the parts into ``executions.h5`` (and what it held before); None when nothing was recorded."""
        if not self.parts_dir.exists() or not any(self.parts_dir.glob("*.h5")):
            return self.out if self.out.exists() else None
        import h5py

        first = next(iter(sorted(self.parts_dir.glob("*.h5"))))
        with h5py.File(first, "r") as f:
            size = int(next(iter(f.values()))["obs"]["agentview_image"].shape[1])
        consolidate(self.parts_dir, self.out, self.dataset_attrs(size))
        return self.out
