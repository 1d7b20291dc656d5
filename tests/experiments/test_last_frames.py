"""The last-frames picture: successes above, failures below, from a real recorded dataset."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from experiments.last_frames import caption, main, pick
from firp.core.episodes import EpisodeDataset


def test_the_first_successes_and_failures_are_picked_in_episode_order():
    labels = np.array([False, True, True, False, True, False, False])
    assert pick(labels, 2) == ([1, 2], [0, 3])
    assert pick(labels, 10) == ([1, 2, 4], [0, 3, 5, 6])


def test_the_picture_is_written_with_a_row_per_class(tiny_dataset, tmp_path):
    out = tmp_path / "frames.png"
    assert main(["--data", str(tiny_dataset), "--per-class", "3", "--out", str(out)]) == 0
    width, height = Image.open(out).size
    assert width > height > 300  # three columns of two rows, with titles
    with EpisodeDataset(tiny_dataset) as ds:
        assert caption(ds, "demo_1") == "demo_1\nsuccess"
        assert caption(ds, "demo_0") == "demo_0\nfailure"  # our world's episodes record no failure mode


def test_bad_arguments_name_the_flag(tiny_dataset, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "x.png")])
    assert "--data" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--data", str(tiny_dataset), "--per-class", "0", "--out", str(tmp_path / "x.png")])
    assert "--per-class" in capsys.readouterr().err
