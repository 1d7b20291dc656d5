"""The services one run talks to: given by URL, or launched here on loopback for the run's duration.

With no ``--sim`` / ``--service`` the run launches both (``--parallel K``: K sim workers, one service);
``--sim`` may list several running sim workers, comma-separated (:class:`planner_client.launcher.Launcher`,
logs beside the run file); given one URL, it launches only the other. A launched sim worker is
used through :class:`RestartingSim` and a launched scoring service through :class:`RestartingScorer`,
so either one killed mid-run is restarted and no trial is lost.
Given URLs are checked for readiness first, so a wrong URL fails before anything is launched.
"""

from __future__ import annotations

from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from firp.core.bundle_format import require_bundle, shipped_bundle_dir
from planner_client.clients import ScoreClient, SimClient
from planner_client.launcher import Launcher
from planner_client.loop import Scorer


@dataclass(frozen=True)
class ServicePlan:
    """What the run asked for (URLs may be None: launch that part)."""

    task: str
    out_dir: Path
    sim_url: str | None = None
    service_url: str | None = None
    bundle: Path | None = None
    score: bool = True
    api_key: str | None = None
    ready_timeout: float = 120.0
    world: str = "mujoco"  # or "robosuite": which world's worker a launched sim is
    parallel: int = 1  # sim workers launched when sim_url is None: one trial runs on each at a time
    launch_sims: bool = True  # False: the trials bring their own world (Ray actors), launch no sim worker

    @property
    def sim_urls(self) -> list[str]:
        """The running sim workers given (``sim_url`` may list several, comma-separated)."""
        return [u.strip() for u in (self.sim_url or "").split(",") if u.strip()]

    def launcher_options(self) -> dict:
        """How the launched services start: the world's worker, and the service under an interpreter with
        torch (the robosuite environment has none: there the main environment's runs it)."""
        if self.world != "robosuite":
            return {}
        from planner_client.robosuite_env import service_python

        return {"sim_module": "robosuite_worker", "service_python": str(service_python())}

    def bundle_to_launch(self) -> Path | None:
        """The bundle the launched service loads, checked to exist; None if no service is launched.
        Raises :class:`firp.core.bundle_format.MissingBundle` before anything starts."""
        if not self.score or self.service_url is not None:
            return None
        return require_bundle(self.bundle or shipped_bundle_dir(self.task), self.task)


@dataclass
class Services:
    sim: Any  # a planner_client.backend.SimBackend: the first of ``sims`` (None: no sim worker, Ray's trials)
    scorer: Scorer | None  # a ScoreClient, or a RestartingScorer when the run launched the service
    launcher: Launcher | None
    sims: list = field(default_factory=list)  # every sim backend; trials run on them in parallel
    sim_launchers: list[Launcher] = field(default_factory=list)  # the launched sim workers beyond the first

    @property
    def sim_restarts(self) -> int:
        launchers = [self.launcher, *self.sim_launchers]
        return sum(launcher.sim_restarts for launcher in launchers if launcher is not None and launcher.runs_sim)

    @property
    def service_restarts(self) -> int:
        return 0 if self.launcher is None else self.launcher.service_restarts


@contextmanager
def open_services(plan: ServicePlan) -> Iterator[Services]:
    """Ready clients for the run; everything opened or launched here is closed/stopped on exit."""
    bundle = plan.bundle_to_launch()
    with ExitStack() as stack:
        sim = scorer = None
        sims = []
        for url in plan.sim_urls:
            sims.append(stack.enter_context(SimClient(url)))
            sims[-1].wait_ready(plan.ready_timeout)
        sim = sims[0] if sims else None
        if plan.score and plan.service_url:
            scorer = stack.enter_context(ScoreClient(plan.service_url, plan.api_key))
            scorer.wait_ready(plan.ready_timeout)
        launcher = None
        launch_sim = sim is None and plan.launch_sims
        if launch_sim or bundle is not None:
            launcher = stack.enter_context(Launcher(plan.out_dir, bundle=bundle, sim=launch_sim,
                                                    ready_timeout=plan.ready_timeout, **plan.launcher_options()))
        sim_launchers = []
        if launch_sim:
            sim = launcher.sim()
            stack.callback(sim.close)
            sims.append(sim)
            # the other sim workers, each in a launcher of its own (its own logs folder, its own restarts)
            for k in range(1, plan.parallel):
                extra = stack.enter_context(Launcher(plan.out_dir / f"sim-{k}", sim=True,
                                                     ready_timeout=plan.ready_timeout, **plan.launcher_options()))
                sim_launchers.append(extra)
                sims.append(extra.sim())
                stack.callback(sims[-1].close)
        if bundle is not None:
            scorer = stack.enter_context(launcher.scorer(plan.api_key))
        yield Services(sim, scorer, launcher, sims, sim_launchers)
