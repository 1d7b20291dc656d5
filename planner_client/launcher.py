"""The embedded launcher: the scoring service and the sim worker as local subprocesses for one run.

``with Launcher(out_dir, bundle=...) as services:`` starts both on free loopback ports (in parallel),
waits for their ``/readyz``, and gives ``services.service_url`` / ``services.sim_url``; leaving the
block stops them (SIGTERM, then SIGKILL). Their logs go to ``<out_dir>/logs/``. A run pointed at an
already running sim worker launches only the service (``sim=False``); one pointed at a running
service launches only the sim worker (no ``bundle``).

A long run must not lose trials to a crashed sim worker. ``services.sim()`` returns a
:class:`RestartingSim`: a simulator backend that, when the worker is unreachable or failing after
the client's retries, restarts it (on a new port) and repeats the call. Episodes are determined by
(task, seed, pose error), so the :class:`SimClient` re-creates an episode the new worker does not
know, and the trial carries on as if nothing happened; ``services.sim_restarts`` counts restarts.
The scoring service gets the same treatment through ``services.scorer()`` (a
:class:`RestartingScorer`): scoring is stateless, so a repeated call on a new service process gives
the same answer; ``services.service_restarts`` counts those restarts.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Callable, Generic, Mapping, Sequence, TypeVar

import numpy as np

from planner_client.clients import RemoteEpisode, RemoteOutcome, ScoreClient, SimClient
from planner_client.processes import ManagedServer
from planner_client.transport import RetryPolicy, ServiceUnavailable

log = logging.getLogger("planner_client.launcher")
R = TypeVar("R")
C = TypeVar("C", SimClient, ScoreClient)


class Launcher:
    """Runs the sim worker (unless ``sim=False``) and, when a bundle is given, the scoring service,
    until :meth:`stop`."""

    def __init__(self, out_dir: Path, bundle: Path | None = None, *, sim: bool = True, ready_timeout: float = 180.0,
                 stop_timeout: float = 10.0, sim_args: Sequence[str] = (), service_args: Sequence[str] = (),
                 env: Mapping[str, str] | None = None, sim_module: str = "sim_worker",
                 sim_python: str = sys.executable, service_python: str = sys.executable):
        """``sim_module`` is the world's worker (``sim_worker``, or ``robosuite_worker`` run by ``sim_python``
        in the robosuite environment); ``service_python`` an interpreter with the service's torch."""
        if not sim and bundle is None:
            raise ValueError("nothing to launch: no sim worker (sim=False) and no bundle for the scoring service")
        log_dir = Path(out_dir) / "logs"
        common = {"ready_timeout": ready_timeout, "stop_timeout": stop_timeout,
                  "env": {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **(env or {})}}
        self._sim_server: ManagedServer | None = None
        if sim:
            self._sim_server = ManagedServer(
                sim_module,
                lambda port: [sim_python, "-m", sim_module, "serve", "--host", "127.0.0.1", "--port",
                              str(port), *sim_args],
                log_dir, **common)
        self.service_server: ManagedServer | None = None
        if bundle is not None:
            self.service_server = ManagedServer(
                "service",
                lambda port: [service_python, "-m", "service", "--host", "127.0.0.1", "--port", str(port),
                              "--bundle", str(bundle), *service_args],
                log_dir, **common)

    @property
    def sim_server(self) -> ManagedServer:
        if self._sim_server is None:
            raise RuntimeError("no sim worker: the launcher was started with sim=False")
        return self._sim_server

    @property
    def runs_sim(self) -> bool:
        return self._sim_server is not None

    @property
    def servers(self) -> list[ManagedServer]:
        return [s for s in (self.service_server, self._sim_server) if s is not None]

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> "Launcher":
        """Start all servers together and wait for each; if one fails, stop all and raise its error."""
        try:
            for server in self.servers:
                server.spawn()
            for server in self.servers:
                server.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        for server in self.servers:
            server.stop()

    def __enter__(self) -> "Launcher":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- where they are -----------------------------------------------------------------------
    @property
    def sim_url(self) -> str:
        return self.sim_server.url

    @property
    def service_url(self) -> str:
        if self.service_server is None:
            raise RuntimeError("no scoring service: the launcher was started without a bundle")
        return self.service_server.url

    @property
    def sim_restarts(self) -> int:
        return max(0, self.sim_server.starts - 1)

    @property
    def service_restarts(self) -> int:
        return 0 if self.service_server is None else max(0, self.service_server.starts - 1)

    # -- recovery -------------------------------------------------------------------------------
    def sim_alive(self) -> bool:
        return self.sim_server.alive()

    @staticmethod
    def restart(server: ManagedServer) -> str:
        """Stop ``server`` if it still runs, start a new one on a new port; its URL."""
        log.warning("restarting the %s (was at %s, %s)", server.name, server.url,
                    "running" if server.alive() else "dead")
        return server.restart()

    def restart_sim(self) -> str:
        """Stop the sim worker if it still runs, start a new one on a new port; its URL."""
        return self.restart(self.sim_server)

    def restart_sim_if_dead(self) -> bool:
        """Restart the sim worker if its process has exited; whether it did."""
        if self.sim_alive():
            return False
        self.restart_sim()
        return True

    # -- clients --------------------------------------------------------------------------------
    def sim(self, **client_options) -> "RestartingSim":
        """A simulator backend on this launcher's sim worker that survives the worker dying."""
        return RestartingSim(self, **client_options)

    def score_client(self, api_key: str | None = None, **client_options) -> ScoreClient:
        """A plain client of the launched service (no restarts: for callers that handle failures)."""
        return ScoreClient(self.service_url, api_key, **client_options)

    def scorer(self, api_key: str | None = None, **client_options) -> "RestartingScorer":
        """A scoring client on this launcher's service that survives the service dying."""
        if self.service_server is None:
            raise RuntimeError("no scoring service: the launcher was started without a bundle")
        return RestartingScorer(self, api_key, **client_options)


class _Restarting(Generic[C]):
    """Calls through a client of one launched server; restarts the server when it stops answering.

    The client first retries with backoff (a busy or briefly unreachable server recovers by
    itself); only when that fails is the server restarted -- dead or hung alike -- and the call
    repeated, at most ``max_restarts`` times per call. Rejected requests (4xx) are not retried.
    Only for calls that may be repeated: executing a plan and scoring one are both deterministic.
    """

    def __init__(self, launcher: Launcher, server: ManagedServer, what: str, connect: Callable[[str], C],
                 max_restarts: int):
        self.launcher = launcher
        self.server = server
        self.what = what  # for messages: "sim worker", "scoring service"
        self.max_restarts = max_restarts
        self._connect = connect
        self.client: C = connect(server.url)

    def _call(self, call: Callable[[C], R]) -> R:
        for restart in range(self.max_restarts + 1):
            if self.client.base_url != self.server.url:  # someone else restarted it meanwhile
                self._reconnect()
            try:
                return call(self.client)
            except ServiceUnavailable as exc:
                if restart == self.max_restarts:
                    raise ServiceUnavailable(exc.service, exc.url,
                                             f"{exc} (gave up after {self.max_restarts} restarts of the "
                                             f"{self.what}; its log: {self.server.log_path})") from exc
                log.warning("%s failed (%s); restarting it", self.what, exc)
                self.launcher.restart(self.server)
                self._reconnect()
        raise AssertionError("unreachable")

    @property
    def base_url(self) -> str:
        """The server's URL now (a restart may have moved it)."""
        return self.server.url

    def _reconnect(self) -> None:
        self.client.close()
        self.client = self._connect(self.server.url)

    def close(self) -> None:
        self.client.close()


class RestartingScorer(_Restarting[ScoreClient]):
    """A :class:`ScoreClient` that restarts the launcher's scoring service when it stops answering."""

    def __init__(self, launcher: Launcher, api_key: str | None = None, max_restarts: int = 2,
                 retry: RetryPolicy = RetryPolicy(), **client_options):
        assert launcher.service_server is not None
        super().__init__(launcher, launcher.service_server, "scoring service",
                         lambda url: ScoreClient(url, api_key, retry=retry, **client_options), max_restarts)

    def score(self, image_b64: str, plan: np.ndarray, task: str) -> dict:
        return self._call(lambda c: c.score(image_b64, plan, task))

    def score_batch(self, image_b64: str, plans: Sequence[np.ndarray], task: str) -> dict:
        return self._call(lambda c: c.score_batch(image_b64, plans, task))

    def model(self) -> dict:
        return self._call(lambda c: c.model())

    def __enter__(self) -> "RestartingScorer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RestartingSim(_Restarting[SimClient]):
    """A :class:`SimClient` that restarts the launcher's sim worker when it stops answering."""

    def __init__(self, launcher: Launcher, max_restarts: int = 2, retry: RetryPolicy = RetryPolicy(),
                 **client_options):
        super().__init__(launcher, launcher.sim_server, "sim worker",
                         lambda url: SimClient(url, retry=retry, **client_options), max_restarts)

    def start(self, task: str, seed: int) -> RemoteEpisode:
        return self._call(lambda c: c.start(task, seed))

    def execute(self, episode: RemoteEpisode, plan: np.ndarray, record_frames: bool = False) -> RemoteOutcome:
        return self._call(lambda c: c.execute(episode, plan, record_frames))

    def delete(self, episode: RemoteEpisode) -> None:
        """Free the episode on the worker; a worker that died meanwhile has forgotten it anyway."""
        try:
            self.client.delete(episode)
        except ServiceUnavailable:
            pass
