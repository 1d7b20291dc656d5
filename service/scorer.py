"""The loaded model as the service uses it: bundle + ensemble scorer + feature cache + one lock.

Why a layer between the routes and :class:`firp.ensemble.EnsembleScorer`:

* **One inference at a time, off the event loop.** The routes run :meth:`ServiceModel.run` in a
  worker thread through an ``anyio.CapacityLimiter`` of one token. One token because the vmapped
  members go through ``torch.func.functional_call``, which swaps parameters on a shared module for
  the duration of a call: two threads inside it at once would read each other's weights. CPU
  parallelism comes from torch's intra-op threads (``threads`` setting) and, beyond one core's
  worth, from more processes. Image decoding and plan validation run inside the same token: they
  cost well under a millisecond for a camera frame, less than a second thread hop would.
* **Backbone features cached per image.** A planner scores several plans (or calls several times)
  for the same initial image; the frozen backbone is a pure function of the image, so its features
  are kept in a small LRU keyed by the sha256 of the request's image bytes. A hit skips both the
  PNG decode and the backbone (EfficientNet-Lite0 at 224 px: ~50 ms on one core).
* **Failure step.** Defined here from the members' mean attention (see :func:`failure_steps`).

No micro-batching across requests: each request is one batched forward pass over its own plans
(the members vmapped or looped, all plans at once); concurrent requests queue for the token.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import numpy as np
import torch
from torch import Tensor

from firp.bundle import MANIFEST_NAME, Bundle, load_bundle
from firp.contract import (
    CATEGORIES,
    CATEGORY_INDEX,
    CONTRACT_VERSION,
    DEFAULT_T,
    FPS,
    JOINT_LOWER,
    JOINT_NAMES,
    JOINT_UPPER,
    PLAN_WIDTH,
    make_plan,
    validate_plan,
)
from firp.ensemble import EnsembleScorer

__all__ = ["FeatureCache", "ModelScores", "ServiceModel", "failure_steps", "neutral_plan", "set_torch_threads"]

log = logging.getLogger("service")

T = TypeVar("T")


def failure_steps(attention: Sequence[np.ndarray | None], success: Sequence[bool]) -> list[int | None]:
    """Per plan: the step at which the predicted failure becomes evident, or None.

    The success head pools the predicted future with attention weights that sum to 1 over the
    steps; a step with a large weight is one the prediction rests on. For a plan predicted to fail
    (``success`` false) the failure step is the step with the largest mean attention over the
    members (the earliest such step on ties), counted from 0. None when the plan is predicted to succeed (there is
    no failure to locate) or when no member has attention (A-MLP baselines).
    """
    return [None if ok or w is None else int(np.argmax(w)) for w, ok in zip(attention, success)]


def neutral_plan(t: int) -> np.ndarray:
    """A contract-valid ``(t, 16)`` plan (hold still mid-range, fingers open) for the warm-up."""
    targets = np.tile((JOINT_LOWER + JOINT_UPPER) / 2.0, (t, 1))
    return make_plan(np.full(t, CATEGORY_INDEX["hold"]), targets)


class FeatureCache:
    """A small LRU of backbone features, keyed by image digest. Used under the model's one lock."""

    def __init__(self, size: int):
        self.size = size
        self._items: OrderedDict[bytes, Tensor] = OrderedDict()

    def get(self, key: bytes) -> Tensor | None:
        value = self._items.get(key)
        if value is not None:
            self._items.move_to_end(key)
        return value

    def put(self, key: bytes, value: Tensor) -> None:
        if self.size <= 0:
            return
        self._items[key] = value
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self._items.popitem(last=False)

    def __len__(self) -> int:
        return len(self._items)


@dataclass(frozen=True)
class ModelScores:
    """What one request's plans scored, ready for a response."""

    probabilities: np.ndarray  # (N,)
    member_probabilities: np.ndarray  # (N, M) -- per plan, members in bundle order
    spread: np.ndarray  # (N,)
    success: np.ndarray  # (N,) bool
    failure_steps: list[int | None]
    attention: list[np.ndarray | None]  # per plan (T_i,) mean attention, or None
    threshold: float
    inference_s: float  # time in the backbone + members (not decoding, not validation)
    cache_hit: bool


class ServiceModel:
    """A verified bundle ready to score, plus what the routes report about it."""

    def __init__(self, bundle: Bundle, feature_cache_size: int = 64):
        self.bundle = bundle
        self.scorer = EnsembleScorer(bundle)
        self.cache = FeatureCache(feature_cache_size)
        self.limiter = anyio.CapacityLimiter(1)
        # The bundle's identity: manifest.json records the sha256 of every weights file, so its own
        # digest changes with any change to the bundle. A manifest may also carry a human version.
        digest = hashlib.sha256((bundle.path / MANIFEST_NAME).read_bytes()).hexdigest()
        extra = bundle.manifest.get("extra") or {}
        self.version = str(bundle.manifest.get("version") or extra.get("version") or digest[:12])
        self.digest = digest
        self.warmup_ms: float | None = None

    @classmethod
    def load(cls, path: str | Path, feature_cache_size: int = 64) -> ServiceModel:
        """Load and verify the bundle (raises :class:`firp.bundle.BundleError` naming file and rule)."""
        return cls(load_bundle(path), feature_cache_size)

    # ---------------------------------------------------------------- identity and contract

    @property
    def name(self) -> str:
        return self.bundle.name

    @property
    def task(self) -> str:
        return self.bundle.task

    @property
    def t_min(self) -> int:
        return self.bundle.t_range.t_min

    @property
    def t_max(self) -> int:
        return self.bundle.t_range.t_max

    @property
    def image_size(self) -> int:
        return self.bundle.encoder_config.image_size

    @property
    def n_members(self) -> int:
        return self.scorer.n_members

    def manifest_summary(self) -> dict[str, Any]:
        """The manifest as /v1/model reports it (see service.schemas.ModelInfo)."""
        m = self.bundle.manifest
        enc = self.bundle.encoder_config
        return {
            "name": self.name,
            "version": self.version,
            "task": self.task,
            "sha256": self.digest,
            "created_utc": m.get("created_utc"),
            "format_version": m.get("format_version"),
            "threshold": self.bundle.threshold,
            "members": [{"kind": e.get("kind"), "validation": e.get("validation", {})} for e in m["members"]],
            "metrics": m.get("validation", {}),
            "calibration": m.get("calibration", {}),
            "training_data": m.get("training_data", {}),
            "contract": {
                "version": CONTRACT_VERSION,
                "plan_width": PLAN_WIDTH,
                "categories": list(CATEGORIES),
                "joint_names": list(JOINT_NAMES),
                "joint_lower": JOINT_LOWER.tolist(),
                "joint_upper": JOINT_UPPER.tolist(),
                "fps": FPS,
                "t_min": self.t_min,
                "t_max": self.t_max,
            },
            "image": {
                "size": self.image_size,
                "backbone": enc.backbone,
                "normalization": enc.resolved_normalization,
                "resize": f"any accepted image is resized to {self.image_size}x{self.image_size} (bilinear, "
                          "antialiased, as in training; non-square images are stretched)",
            },
        }

    # ---------------------------------------------------------------- scoring

    async def run(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` in a worker thread while holding the model's one inference token."""
        return await anyio.to_thread.run_sync(fn, limiter=self.limiter)

    def warm_up(self) -> float:
        """Score a neutral plan through both member paths (vmap for few plans, loop for many) so
        that the first real request does not pay for lazy initialisation; returns milliseconds.
        Fails if the bundle produces non-finite scores."""
        t = min(max(DEFAULT_T, self.t_min), self.t_max)
        image = np.zeros((self.image_size, self.image_size, 3), dtype=np.uint8)
        start = time.perf_counter()
        feats = self.scorer.image_features(image)
        for n in (1, 9):
            result = self.scorer.score_features(feats, np.stack([neutral_plan(t)] * n))
            if not np.isfinite(result.probabilities).all():
                raise RuntimeError(f"warm-up of bundle {self.bundle.path} produced non-finite scores")
        self.warmup_ms = (time.perf_counter() - start) * 1000.0
        return self.warmup_ms

    def validate_plans(self, plans: Sequence[object], fields: Sequence[str]) -> list[np.ndarray]:
        """Each plan through the contract's one validator with the bundle's T range; the
        :class:`~firp.contract.PlanValidationError` names ``fields[i]`` and the step/column."""
        # The validator sums rows: for 1e308-sized numbers numpy warns about overflow, which a
        # warnings filter set to "error" would turn into a 500. The values are refused anyway.
        with np.errstate(over="ignore", invalid="ignore"):
            return [validate_plan(p, self.bundle.t_range, field=f) for p, f in zip(plans, fields)]

    def score(self, image_key: bytes, load_image: Callable[[], np.ndarray], plans: Sequence[np.ndarray]) -> ModelScores:
        """Score validated ``plans`` (any mix of lengths) for one image.

        ``image_key`` identifies the image's bytes (the feature cache's key); ``load_image`` decodes
        it and is only called on a cache miss. Plans of equal length go through the members as one
        batch; a request mixing lengths gets one batch per length, results in request order.
        """
        feats = self.cache.get(image_key)
        hit = feats is not None
        start = time.perf_counter()
        if feats is None:
            image = load_image()
            start = time.perf_counter()
            feats = self.scorer.image_features(image)
            self.cache.put(image_key, feats)
        n = len(plans)
        probs = np.empty(n)
        spread = np.empty(n)
        success = np.empty(n, dtype=bool)
        members = np.empty((n, self.n_members))
        attention: list[np.ndarray | None] = [None] * n
        by_length: dict[int, list[int]] = {}
        for i, p in enumerate(plans):
            by_length.setdefault(p.shape[0], []).append(i)
        for idx in by_length.values():
            result = self.scorer.score_features(feats, np.stack([plans[i] for i in idx]))
            probs[idx] = result.probabilities
            spread[idx] = result.spread
            success[idx] = result.success
            members[idx] = result.member_probabilities.T
            if result.weights is not None:
                for j, i in enumerate(idx):
                    attention[i] = result.weights[j]
        elapsed = time.perf_counter() - start
        steps = failure_steps(attention, success.tolist())
        return ModelScores(probs, members, spread, success, steps, attention, self.scorer.threshold, elapsed, hit)


def set_torch_threads(threads: int) -> None:
    """torch's intra-op thread count for inference (process-wide)."""
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
