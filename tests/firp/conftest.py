"""Every method test (tests/firp) starts from the same random state, on one CPU thread (tests/torch_fixtures.py).

One thread: the tensors here are tiny, and with two OpenMP threads each op waits at a barrier for
the second core; when that core is busy (a benchmark or a sim worker next to the tests) every op
costs a scheduler slice (~8 ms instead of ~0.02 ms), which turns a 5 s test file into minutes.
"""

import numpy as np
import pytest

from firp.core.contract import make_plan
from firp.core.episodes import EpisodeRecord, consolidate, write_episode_part
from tests.torch_fixtures import _one_thread, _seed  # noqa: F401  (autouse fixtures)

TINY_T = 10


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """20 recorded episodes (T=10, 32x32) whose label shows in the image corner: a real HDF5 file."""
    root = tmp_path_factory.mktemp("evaldata")
    rng = np.random.default_rng(0)
    for i in range(20):
        success = bool(i % 2)
        frames = rng.integers(0, 255, (TINY_T, 32, 32, 3), dtype=np.uint8)
        frames[:, :8, :8] = 255 if success else 0  # the image tells the label apart
        targets = np.tile([0, 0, 0, -1.5, 0, 1.5, 0, 0.02, 0.02], (TINY_T, 1)) + rng.normal(0, 0.001, (TINY_T, 9))
        plan = make_plan(np.arange(TINY_T) % 7, targets).astype(np.float32)
        write_episode_part(root / "parts", i, EpisodeRecord(frames, plan, np.zeros((TINY_T, 3)), success, {"seed": i}))
    consolidate(root / "parts", root / "tiny.h5", {"fps": 4, "T": TINY_T, "task": "stacking"})
    return root / "tiny.h5"
