"""Simulated perception: the object poses a camera-based pose estimator would hand a planner.

The rendered image always shows the true scene; the planner only gets these estimates. The error
is seeded (so an episode is reproducible) and Gaussian with a configurable size; zero is allowed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_worker.scene import BLOCK_NAMES, SceneLayout

PERCEPTION_STREAM = 7  # separates the perception random stream from the scene sampler's


@dataclass(frozen=True)
class PoseErrorConfig:
    """Standard deviations of the pose estimate's error (defaults: a few mm, a few degrees)."""

    xy_std: float = 0.003  # metres
    z_std: float = 0.001  # metres
    yaw_std_deg: float = 3.0

    @classmethod
    def none(cls) -> "PoseErrorConfig":
        return cls(0.0, 0.0, 0.0)

    @classmethod
    def from_mm_deg(cls, error_mm: float, error_deg: float) -> "PoseErrorConfig":
        """The error the command lines and the HTTP API describe with two numbers.

        ``error_mm`` is the in-plane std; the height error is capped at 1 mm because blocks rest
        on a known surface, so a depth estimate is far better than the in-plane one.
        """
        return cls(xy_std=error_mm / 1000.0, z_std=min(error_mm, 1.0) / 1000.0, yaw_std_deg=error_deg)


def estimate_block_poses(true_poses: np.ndarray, seed: int, config: PoseErrorConfig = PoseErrorConfig()) -> np.ndarray:
    """Noisy estimates ``(n, 4)`` of block poses (x, y, z, yaw), seeded by the episode seed."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, PERCEPTION_STREAM]))
    true_poses = np.asarray(true_poses, dtype=float)
    n = len(true_poses)
    noise = np.column_stack([
        rng.normal(0.0, 1.0, (n, 2)) * config.xy_std,
        rng.normal(0.0, 1.0, n) * config.z_std,
        np.radians(rng.normal(0.0, 1.0, n) * config.yaw_std_deg),
    ])
    est = true_poses + noise
    est[:, 3] = (est[:, 3] + np.pi / 4) % (np.pi / 2) - np.pi / 4
    return est


def observation(true_poses: np.ndarray, seed: int, layout: SceneLayout,
                config: PoseErrorConfig = PoseErrorConfig()) -> dict:
    """What the planner receives: estimated block poses by name, plus the fixed boxes' layout."""
    est = estimate_block_poses(true_poses, seed, config)
    return {
        "blocks": {name: {"position": est[i, :3].tolist(), "yaw": float(est[i, 3])}
                   for i, name in enumerate(BLOCK_NAMES)},
        "scene": layout.as_dict(),
    }
