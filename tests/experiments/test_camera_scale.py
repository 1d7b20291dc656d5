"""The camera-scale experiment's projection (the robosuite measurement itself runs in the robosuite environment)."""

import numpy as np
import pytest

from experiments.camera_scale import main, pixels_per_cm, project


def pinhole(focal_px: float, distance_m: float) -> np.ndarray:
    """A camera looking down the world's -z from ``distance_m`` above the origin, pixel = focal * x / depth."""
    return np.array([[focal_px, 0.0, 0.0, 0.0], [0.0, focal_px, 0.0, 0.0], [0.0, 0.0, -1.0, distance_m],
                     [0.0, 0.0, 0.0, 1.0]])


def test_a_centimetre_spans_focal_times_a_centimetre_over_the_depth():
    matrix = pinhole(100.0, 1.0)
    np.testing.assert_allclose(project(matrix, np.array([0.01, 0.0, 0.0])), [1.0, 0.0])
    assert pixels_per_cm(matrix, np.zeros(3)) == pytest.approx((1.0, 1.0))
    assert pixels_per_cm(pinhole(100.0, 2.0), np.zeros(3)) == pytest.approx((0.5, 0.5))  # twice as far


def test_bad_arguments_name_the_flag(capsys):
    with pytest.raises(SystemExit):
        main(["--scenes", "0"])
    assert "--scenes: at least 1" in capsys.readouterr().err
