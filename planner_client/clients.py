"""HTTP clients of the two services: the sim worker (episodes, execution) and the scoring service.

:class:`SimClient` satisfies :class:`planner_client.backend.SimBackend` exactly like the embedded
simulator, so the trial loop runs unchanged against either. An episode is fully determined by
(task, seed, pose error), so when the worker no longer knows an episode (it expired, or the worker
was restarted) the client starts it again, checks that it is the same, and retries: executions
never depend on the worker's memory.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from firp.core.contract import validate_plan
from planner_client.transport import JsonHttp, RequestRejected, RetryPolicy, ServiceError

SCORE_FIELDS = ("score", "success", "threshold", "member_scores", "spread", "failure_step", "model", "elapsed_ms")


@dataclass
class RemoteEpisode:
    """An episode on a sim worker; ``episode_id``/``expires_at`` change if the client re-creates it."""

    episode_id: str
    task: str
    seed: int
    observation: dict = field(repr=False)
    image_b64: str = field(repr=False)
    image_size: tuple[int, int]  # (height, width)
    robot: dict = field(repr=False)
    pose_error: dict
    created_at: str
    expires_at: str


@dataclass(frozen=True)
class RemoteOutcome:
    success: bool
    reason: str
    sim_seconds: float
    unstable: bool
    final_blocks: dict = field(repr=False)
    frames_b64: list[str] | None = field(default=None, repr=False)  # only when asked for
    kind: str = "success"


class SimClient:
    """The sim worker's API as the planner's simulator backend."""

    def __init__(self, base_url: str, *, pose_error_mm: float | None = None, pose_error_deg: float | None = None,
                 timeout: float = 120.0, connect_timeout: float = 3.0, retry: RetryPolicy = RetryPolicy()):
        # the worker drops a call still queued when this client would have given up on it anyway
        self.http = JsonHttp("sim worker", base_url, timeout=timeout, connect_timeout=connect_timeout, retry=retry,
                             headers={"X-Request-Timeout": f"{timeout:g}"})
        self.pose_error_mm = pose_error_mm
        self.pose_error_deg = pose_error_deg

    @property
    def base_url(self) -> str:
        return self.http.base_url

    def wait_ready(self, timeout: float = 60.0) -> None:
        self.http.wait_ready(timeout)

    def start(self, task: str, seed: int) -> RemoteEpisode:
        body: dict = {"task": task, "seed": int(seed)}
        if self.pose_error_mm is not None:
            body["pose_error_mm"] = self.pose_error_mm
        if self.pose_error_deg is not None:
            body["pose_error_deg"] = self.pose_error_deg
        d = self.http.request("POST", "/v1/episodes", json=body).json()
        return RemoteEpisode(
            episode_id=d["episode_id"], task=d["task"], seed=d["seed"], observation=d["observation"],
            image_b64=d["image"], image_size=(d["image_size"]["height"], d["image_size"]["width"]), robot=d["robot"],
            pose_error=d["pose_error"], created_at=d["created_at"], expires_at=d["expires_at"],
        )

    def execute(self, episode: RemoteEpisode, plan: np.ndarray, record_frames: bool = False) -> RemoteOutcome:
        """Execute ``plan`` from the episode's initial state (re-creating the episode if it is gone)."""
        body = {"plan": np.asarray(plan, dtype=float).tolist(), "record_frames": record_frames}
        try:
            d = self.http.request("POST", f"/v1/episodes/{episode.episode_id}/execute", json=body).json()
        except RequestRejected as exc:
            if exc.status != 404 or exc.rule != "unknown_episode":
                raise
            self._recreate(episode)
            d = self.http.request("POST", f"/v1/episodes/{episode.episode_id}/execute", json=body).json()
        return RemoteOutcome(d["success"], d["reason"], d["sim_seconds"], d["unstable"], d["final_blocks"],
                             d.get("frames"), d["kind"])

    def _recreate(self, episode: RemoteEpisode) -> None:
        fresh = self.start(episode.task, episode.seed)
        if fresh.observation != episode.observation or fresh.image_b64 != episode.image_b64:
            raise ServiceError(self.http.name, self.base_url,
                               f"episode {episode.task}/{episode.seed} was gone from the sim worker at "
                               f"{self.base_url} and starting it again gave a different episode (different worker "
                               f"settings: image size or pose error?); refusing to execute on it")
        episode.episode_id = fresh.episode_id
        episode.created_at, episode.expires_at = fresh.created_at, fresh.expires_at

    def delete(self, episode: RemoteEpisode) -> None:
        """Free the episode on the worker now (it would expire anyway); an unknown episode is fine."""
        try:
            self.http.request("DELETE", f"/v1/episodes/{episode.episode_id}")
        except RequestRejected as exc:
            if exc.status != 404:
                raise

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> "SimClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ScoreClient:
    """The scoring service's ``POST /v1/score``: the success probability of a plan for an image."""

    def __init__(self, base_url: str, api_key: str | None = None, *, api_key_header: str = "X-API-Key",
                 timeout: float = 30.0, connect_timeout: float = 3.0, retry: RetryPolicy = RetryPolicy()):
        # the service drops work still queued when this client would have given up on it anyway
        headers = {"X-Request-Timeout": f"{timeout:g}", **({api_key_header: api_key} if api_key else {})}
        self.http = JsonHttp("scoring service", base_url, timeout=timeout, connect_timeout=connect_timeout,
                             retry=retry, headers=headers)

    @property
    def base_url(self) -> str:
        return self.http.base_url

    def wait_ready(self, timeout: float = 60.0) -> None:
        """Block until ``GET /readyz`` answers 200 (the bundle is loaded); raise naming the URL if not."""
        self.http.wait_ready(timeout)

    def score(self, image_b64: str, plan: np.ndarray, task: str) -> dict:
        """The service's JSON answer (fields: score, success, threshold, member_scores, spread,
        failure_step, model, elapsed_ms). The plan is checked against the contract here first, so a
        malformed plan fails before the network, with the same field and rule the service would give."""
        plan = validate_plan(plan)
        body = {"image": image_b64, "plan": plan.tolist(), "task": task}
        answer = self.http.request("POST", "/v1/score", json=body).json()
        missing = [f for f in ("score", "success") if f not in answer]
        if missing:
            raise ServiceError(self.http.name, self.base_url + "/v1/score",
                               f"scoring service at {self.base_url} answered without {missing}: {str(answer)[:300]}")
        return answer

    def score_batch(self, image_b64: str, plans: Sequence[np.ndarray], task: str) -> dict:
        """``POST /v1/score/batch``: every plan for one image in one call (one image decode, one backbone pass);
        the answer's ``results`` are in the plans' order. Each plan is checked against the contract first."""
        checked = [validate_plan(p, field=f"plans[{i}]").tolist() for i, p in enumerate(plans)]
        answer = self.http.request("POST", "/v1/score/batch",
                                   json={"image": image_b64, "plans": checked, "task": task}).json()
        results = answer.get("results")
        if not isinstance(results, list) or len(results) != len(checked) or "threshold" not in answer:
            raise ServiceError(self.http.name, self.base_url + "/v1/score/batch",
                               f"scoring service at {self.base_url} answered without {len(checked)} results and a "
                               f"threshold: {str(answer)[:300]}")
        return answer

    def model(self) -> dict:
        """``GET /v1/model``: name, version, task, threshold, contract T range, ... of the loaded bundle.
        The trial loop reads it once per run, to check plans fit the bundle and to tie records to a model."""
        return self.http.request("GET", "/v1/model").json()

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> "ScoreClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
