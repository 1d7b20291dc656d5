"""Tiny random ensembles exported as bundles, shared by the bundle and ensemble tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from firp.bundle import BundleMember, export_bundle
from firp.core.contract import JOINT_LOWER, JOINT_UPPER, make_plan
from firp.model import build_model
from firp.model.encoder import build_backbone

from .model.helpers import TINY

T_RANGE = (8, 16)  # TINY's flattening baselines take at most max_T = 16 steps


def tiny_members(kinds: tuple[str, ...] = ("firp", "firp", "firp")) -> list[BundleMember]:
    """Randomly initialised members, each with its own validation metrics."""
    return [
        BundleMember(kind, TINY, build_model(kind, TINY).eval(), {"balanced_accuracy": 0.5 + 0.1 * k, "loss": 0.7})
        for k, kind in enumerate(kinds)
    ]


def tiny_backbone() -> torch.nn.Module:
    return build_backbone(TINY.encoder).eval()


def export_tiny(out: Path, members: list[BundleMember] | None = None, backbone: torch.nn.Module | None = None,
                **overrides: object) -> Path:
    """Export a tiny bundle with plausible metadata; ``overrides`` replace keyword arguments."""
    kwargs: dict[str, object] = dict(
        name="tiny", task="stacking", threshold=0.5, calibration={"ece": 0.05, "n_val": 40, "n_bins": 10},
        metrics={"balanced_accuracy": 0.7}, training_data_hash="ab" * 32, training_data_path="data/tiny.hdf5",
        t_range=T_RANGE, extra={"seed": 0, "note": "test"},
    )
    kwargs.update(overrides)
    return export_bundle(out, members if members is not None else tiny_members(),
                         backbone=backbone if backbone is not None else tiny_backbone(), **kwargs)


def valid_plans(n: int, t: int, seed: int = 0) -> np.ndarray:
    """``(n, t, 16)`` contract-valid plans: random categories, joint targets inside the limits."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        cats = rng.integers(0, 7, t)
        targets = rng.uniform(JOINT_LOWER, JOINT_UPPER, size=(t, 9))
        out.append(make_plan(cats, targets))
    return np.stack(out)


def random_image(size: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)
