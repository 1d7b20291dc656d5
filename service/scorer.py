"""The loaded model as the service uses it: bundle + ensemble scorer + feature cache + one lock.

Why a layer between the routes and :class:`firp.serving.EnsembleScorer`:

* **One forward pass at a time, off the event loop.** Passes run in a worker thread through an
  ``anyio.CapacityLimiter`` of one token, which keeps the one core the service is sized for free of
  contention (the fused path holds plain tensors and would be safe from several threads). CPU
  parallelism comes from torch's intra-op threads (``threads`` setting) and, beyond that, from more
  processes. Image decoding and plan validation run inside
  the same token: they cost well under a millisecond for a camera frame.
* **Several requests per pass.** :meth:`ServiceModel.score_jobs` scores the plans of several
  requests (each with its own scene) in one pass per plan length; :mod:`service.batching` feeds it
  the requests that queued while the previous pass ran (micro-batching, a setting).
* **Backbone features cached per image.** A planner scores several plans (or calls several times)
  for the same initial image; the frozen backbone is a pure function of the image, so its features
  are kept in a small LRU keyed by the sha256 of the request's image bytes. A hit skips both the
  PNG decode and the backbone (EfficientNet-Lite0 at the shipped 84 px: ~11-15 ms on one core).
* **Failure step.** Defined here from the members' mean attention (see :func:`failure_steps`).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import numpy as np
import torch
from torch import Tensor

from firp.bundle import Bundle, load_bundle
from firp.core.bundle_format import MANIFEST_NAME, bundle_version
from firp.core.decisions import EVIDENCE_KEY, is_informative
from firp.core.contract import (
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
from firp.serving import EnsembleScorer
from service.statistics import InferenceStatistics

__all__ = ["FeatureCache", "JobTimeline", "ModelScores", "ScoreJob", "ServiceModel", "failure_steps", "neutral_plan",
           "set_torch_threads"]

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


@dataclass
class JobTimeline:
    """When a job's stages ran (``time.time_ns()``), written by the batcher and the worker thread and
    read back on the request's side to record its trace spans (:mod:`firp.core.tracing`)."""

    queued_ns: int | None = None  # entered the micro-batcher's queue
    taken_ns: int | None = None  # taken into a pass
    backbone_ns: tuple[int, int] | None = None  # image decoded and its features computed (None: cached)
    members_ns: tuple[int, int] | None = None  # the ensemble's pass over every plan of the batch
    pass_jobs: int = 0  # requests that shared the pass
    pass_plans: int = 0


@dataclass(frozen=True)
class ScoreJob:
    """One request's scoring work: its image (cache key + decoder) and its plans.

    ``fields`` names each plan for validation errors (``plan``, ``plans[3]``); None means the plans
    were validated already.
    """

    image_key: bytes
    load_image: Callable[[], np.ndarray]
    plans: Sequence[object]
    fields: Sequence[str] | None
    timeline: JobTimeline = field(default_factory=JobTimeline)


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
    name: str = ""  # the bundle that scored them: after a hot swap, not necessarily the one a route saw first
    version: str = ""


class ServiceModel:
    """A verified bundle ready to score, plus what the routes report about it."""

    def __init__(self, bundle: Bundle, feature_cache_size: int = 64, device: str = "cpu"):
        self.bundle = bundle
        self.scorer = EnsembleScorer(bundle, device=device)
        self.cache = FeatureCache(feature_cache_size)
        self.limiter = anyio.CapacityLimiter(1)
        # The bundle's identity: manifest.json records the sha256 of every weights file, so its own
        # digest changes with any change to the bundle. A manifest may also carry a human version.
        digest = hashlib.sha256((bundle.path / MANIFEST_NAME).read_bytes()).hexdigest()
        self.version = bundle_version(bundle.path, bundle.manifest)
        self.digest = digest
        self.warmup_ms: float | None = None
        self.statistics = InferenceStatistics()  # the V2 statistics extension's counters (service.statistics)

    @classmethod
    def load(cls, path: str | Path, feature_cache_size: int = 64, device: str = "cpu") -> ServiceModel:
        """Load and verify the bundle (raises :class:`firp.bundle.BundleError` naming file and rule)."""
        return cls(load_bundle(path), feature_cache_size, device)

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

    @property
    def evidence(self) -> dict | None:
        """The manifest's decision evidence (firp.core.decisions), if the bundle carries it."""
        return self.bundle.manifest.get(EVIDENCE_KEY)

    @property
    def informative(self) -> bool | None:
        """Whether the validation interval lies above 0.5 (None: no evidence in the bundle)."""
        return is_informative(self.evidence)

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
            "informative": self.informative,
            "decision_evidence": self.evidence,
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
        """Score a neutral plan, alone and in a batch, so that the first real request does not pay for
        lazy initialisation; returns milliseconds.
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
        :class:`~firp.core.contract.PlanValidationError` names ``fields[i]`` and the step/column."""
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
        result = self.score_jobs([ScoreJob(image_key, load_image, plans, None)])[0]
        if isinstance(result, BaseException):
            raise result
        return result

    def score_jobs(self, jobs: Sequence[ScoreJob]) -> list[ModelScores | Exception]:
        """Score several requests' plans in as few forward passes as possible (micro-batching).

        Each job is validated (unless its ``fields`` is None: already validated) and its image
        features looked up or computed on its own, so a bad plan or image fails only its own job
        (its entry is the exception); then every plan of every good job goes through the members
        in one call per plan length, each plan with its own scene's features. ``inference_s`` of
        each job is the time of the whole pass it shared (backbone of the images it needed +
        members).
        """
        out: list[ModelScores | Exception | None] = [None] * len(jobs)
        checked: dict[int, list[np.ndarray]] = {}
        for j, job in enumerate(jobs):
            try:
                checked[j] = list(job.plans) if job.fields is None else self.validate_plans(job.plans, job.fields)
            except Exception as exc:  # noqa: BLE001 - the job's own error (422 ...), reported to it alone
                out[j] = exc
        start = time.perf_counter()
        decode_s = 0.0
        feats: dict[int, Tensor] = {}
        hits: dict[int, bool] = {}
        for j in checked:
            key = jobs[j].image_key
            cached = self.cache.get(key)
            hits[j] = cached is not None
            if cached is None:
                t0, wall0 = time.perf_counter(), time.time_ns()
                try:
                    image = jobs[j].load_image()
                except Exception as exc:  # noqa: BLE001 - a bad image fails its own job only
                    out[j] = exc
                    continue
                finally:
                    decode_s += time.perf_counter() - t0
                cached = self.scorer.image_features(image)
                self.cache.put(key, cached)
                jobs[j].timeline.backbone_ns = (wall0, time.time_ns())
            feats[j] = cached
        # (job, plan index) of every plan to score, grouped by plan length
        by_length: dict[int, list[tuple[int, int]]] = {}
        for j in feats:
            for i, p in enumerate(checked[j]):
                by_length.setdefault(p.shape[0], []).append((j, i))
        n_members = self.n_members
        members_start = time.time_ns()
        parts = {j: (np.empty(len(checked[j])), np.empty(len(checked[j])), np.empty(len(checked[j]), dtype=bool),
                     np.empty((len(checked[j]), n_members)), [None] * len(checked[j])) for j in feats}
        for rows in by_length.values():
            keys = {jobs[j].image_key for j, _ in rows}
            # one scene: one feature row for all plans (fused members project it once)
            f = feats[rows[0][0]] if len(keys) == 1 else torch.cat([feats[j] for j, _ in rows])
            result = self.scorer.score_features(f, np.stack([checked[j][i] for j, i in rows]))
            for r, (j, i) in enumerate(rows):
                probs, spread, success, members, attention = parts[j]
                probs[i], spread[i], success[i] = result.probabilities[r], result.spread[r], result.success[r]
                members[i] = result.member_probabilities[:, r]
                attention[i] = None if result.weights is None else result.weights[r]
        elapsed = time.perf_counter() - start - decode_s
        members_ns = (members_start, time.time_ns())
        n_plans = sum(len(checked[j]) for j in feats)
        for j in feats:
            jobs[j].timeline.members_ns, jobs[j].timeline.pass_jobs, jobs[j].timeline.pass_plans = members_ns, len(feats), n_plans
        for j, (probs, spread, success, members, attention) in parts.items():
            steps = failure_steps(attention, success.tolist())
            out[j] = ModelScores(probs, members, spread, success, steps, attention, self.scorer.threshold, elapsed,
                                 hits[j], self.name, self.version)
        return out  # type: ignore[return-value]


def set_torch_threads(threads: int) -> None:
    """torch's intra-op thread count for inference (process-wide)."""
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
