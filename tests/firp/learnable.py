"""Tiny recorded datasets whose label a working pipeline must be able to learn, and controls it must not.

Each is a real HDF5 file in the project's layout, written by :mod:`firp.core.episodes`. Where the label
shows decides which methods can learn it:

* ``"image"``: a 16 x 16 corner of *every* frame is white for a success and black for a failure.
  Every method that reads an image (A-MLP+image, FIRP, Oracle) can learn it; A-MLP, which reads the
  plan only, cannot.
* ``"plan+future"``: the plan moves joint 1 by +-0.4 rad, and that choice shows in the *later*
  frames only (the first frame's corner is grey): what a plan's consequence looks like. The plan
  readers (A-MLP, A-MLP+image, GRU) learn it from the plan, FIRP must predict the future frames from
  the first frame and the plan, and Oracle reads the executed frames.

``shuffle=True`` draws the cue from a random permutation of the labels, so nothing in the data
tells the label: every method must stay near chance. ``flip`` replaces that fraction of the cues
with the opposite one, so a model cannot be perfect and its validation numbers are not degenerate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from firp.core.contract import make_plan
from firp.core.episodes import EpisodeRecord, consolidate, write_episode_part

T = 16
SIZE = 32
CUES = ("image", "plan+future")


def learnable_dataset(root: Path, cue: str, n: int = 160, shuffle: bool = False, flip: float = 0.0,
                      seed: int = 0) -> Path:
    """Write ``n`` balanced episodes (T = 16, 32 x 32 frames) under ``root`` and return the dataset."""
    if cue not in CUES:
        raise ValueError(f"cue must be one of {CUES}, got {cue!r}")
    rng = np.random.default_rng(seed)
    labels = np.arange(n) % 2 == 1
    shown = rng.permutation(labels) if shuffle else labels.copy()
    flipped = rng.random(n) < flip
    shown[flipped] = ~shown[flipped]
    for i in range(n):
        frames = rng.integers(0, 256, (T, SIZE, SIZE, 3), dtype=np.uint8)
        targets = np.tile([0, 0, 0, -1.5, 0, 1.5, 0, 0.02, 0.02], (T, 1)) + rng.normal(0, 0.05, (T, 9))
        targets[:, 7:] = np.clip(targets[:, 7:], 0.0, 0.04)
        corner = (255, 255, 255) if shown[i] else (0, 0, 0)
        half = SIZE // 2
        if cue == "image":
            frames[:, :half, :half] = corner
        else:
            frames[0, :half, :half] = 128
            frames[1:, :half, :half] = corner
            targets[:, 0] += 0.4 if shown[i] else -0.4
        plan = make_plan(np.arange(T) * 7 // T, targets).astype(np.float32)
        write_episode_part(root / "parts", i, EpisodeRecord(frames, plan, np.zeros((T, 3)), bool(labels[i]),
                                                            {"seed": i, "cue_flipped": bool(flipped[i])}))
    name = f"{cue.replace('+', '_')}{'_shuffled' if shuffle else ''}.h5"
    consolidate(root / "parts", root / name, {"fps": 4, "T": T, "task": "stacking"})
    return root / name
