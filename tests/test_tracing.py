"""OpenTelemetry tracing across the parts (firp.core.tracing): off by default, on through OTEL_*, and one
trace per trial from the planner client through the scoring service and a world worker.

The parts run as real uvicorn servers on loopback in this process, so their spans and the client's
land in one in-memory exporter; the trace context crosses real HTTP (``traceparent`` headers). A
second test runs the service as its own process with ``OTEL_TRACES_EXPORTER=console`` and finds the
caller's trace id in the spans it prints.
"""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter

from firp.core.tracing import (TracingConfigError, configure_tracing, exporter_names, record_span, span,
                               tracing_requested, use_tracer_provider)
from planner_client.clients import ScoreClient, SimClient
from planner_client.transport import request_id
from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import export_tiny, valid_plans
from tests.loopback import serve_on_loopback
from tests.processes import ServedProcess, clean_env
from world_api.app import create_world_app
from world_api.backend import EpisodeStart, Outcome
from world_api.settings import WorldSettings

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

PLAN = valid_plans(1, 10)[0]


class ScriptedWorld:
    """A world that answers at once: what is traced is the API's path, not a simulator."""

    name = "scripted_world"
    tasks = ("stacking",)
    outcome_kinds = ("success",)
    image_size = 32

    def warm_up(self) -> None:
        pass

    def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float) -> EpisodeStart:
        image = np.random.default_rng(seed).integers(0, 256, (32, 32, 3), dtype=np.uint8)
        return EpisodeStart(task, seed, {"blocks": {}, "scene": {}}, image, np.zeros(9))

    def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool) -> Outcome:
        return Outcome(True, "success", "done", {}, 1.0, False)

    def close(self) -> None:
        pass


@pytest.mark.parametrize("environ, names", [
    ({}, []),
    ({"OTEL_TRACES_EXPORTER": "none"}, []),
    ({"OTEL_TRACES_EXPORTER": "console"}, ["console"]),
    ({"OTEL_TRACES_EXPORTER": "otlp, console"}, ["otlp", "console"]),
    ({"OTEL_EXPORTER_OTLP_ENDPOINT": "http://collector:4318"}, ["otlp"]),  # an endpoint alone means otlp
    ({"OTEL_EXPORTER_OTLP_TRACES_ENDPOINT": "http://collector:4318/v1/traces"}, ["otlp"]),
    ({"OTEL_TRACES_EXPORTER": "console", "OTEL_SDK_DISABLED": "true"}, []),
])
def test_tracing_is_off_unless_the_standard_variables_ask(environ, names):
    assert exporter_names(environ) == names
    assert tracing_requested(environ) == bool(names)
    if not names:
        assert configure_tracing("firp-test", environ) is None


def test_an_exporter_this_install_lacks_is_refused_by_name():
    with pytest.raises(TracingConfigError, match="OTEL_TRACES_EXPORTER names 'zipkin'"):
        configure_tracing("firp-test", {"OTEL_TRACES_EXPORTER": "zipkin"})


def test_without_a_tracer_the_helpers_do_nothing():
    with span(None, "trial") as trace_id:
        assert trace_id is None
    record_span(None, "queue wait", 1, 2)  # no tracer, no error


@pytest.fixture()
def exporter():
    """Every part made in this test traces into one in-memory exporter (and nothing after it)."""
    memory = InMemorySpanExporter()
    provider = TracerProvider()
    provider.add_span_processor(SimpleSpanProcessor(memory))
    use_tracer_provider(provider)
    try:
        yield memory
    finally:
        use_tracer_provider(None)


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory):
    import torch

    torch.manual_seed(0)
    return export_tiny(tmp_path_factory.mktemp("tracing") / "tiny")


def _by_name(spans) -> dict[str, list]:
    out: dict[str, list] = {}
    for s in spans:
        out.setdefault(s.name, []).append(s)
    return out


def _ancestors(s, by_id: dict) -> list:
    """The span's parent, grandparent, ... (spans of this exporter only)."""
    chain = []
    while s.parent is not None and s.parent.span_id in by_id:
        s = by_id[s.parent.span_id]
        chain.append(s)
    return chain


def test_one_trace_per_trial_through_the_scoring_service_and_the_world(exporter, tiny_bundle):
    service = create_app(ServiceSettings(bundle=tiny_bundle, threads=1))  # tracing from use_tracer_provider
    world = create_world_app(ScriptedWorld(), WorldSettings())
    with serve_on_loopback(service) as score_at, serve_on_loopback(world) as sim_at:
        sim, scorer = SimClient(f"http://{sim_at}"), ScoreClient(f"http://{score_at}")
        try:
            sim.wait_ready()
            scorer.wait_ready()
            exporter.clear()  # readiness polls are not traced anyway; start from the trial
            tracer = configure_tracing("firp-planner").get_tracer("test")
            with request_id("trial-0-abc"), span(tracer, "trial", {"firp.trial": 0}) as trace_id:
                episode = sim.start("stacking", 7)
                first = scorer.score(episode.image_b64, PLAN, "stacking")
                again = scorer.score(episode.image_b64, PLAN, "stacking")  # the same scene: features cached
                sim.execute(episode, PLAN)
        finally:
            sim.close()
            scorer.close()
    assert first["score"] == again["score"]
    spans = exporter.get_finished_spans()
    by_id = {s.context.span_id: s for s in spans}
    names = _by_name(spans)
    # every span of the trial is in its trace, and nothing else was traced
    assert {format(s.context.trace_id, "032x") for s in spans} == {trace_id}
    assert len(names["trial"]) == 1 and names["trial"][0].parent is None
    # the scoring service: its stages under its server span, under the client's call, under the trial
    assert len(names["queue wait"]) == 2 and len(names["ensemble pass"]) == 2
    assert len(names["backbone"]) == 1, "the second call's image features came from the cache"
    for stage in names["queue wait"] + names["ensemble pass"] + names["backbone"]:
        chain = _ancestors(stage, by_id)
        assert (chain[0].name, chain[0].kind.name) == ("POST /v1/score", "SERVER"), [c.name for c in chain]
        assert chain[1].kind.name == "CLIENT" and chain[-1].name == "trial", [c.name for c in chain]
    ensemble = names["ensemble pass"][0]
    assert ensemble.attributes["firp.plans"] == 1 and ensemble.attributes["firp.pass.plans"] >= 1
    assert ensemble.attributes["firp.model.version"] == first["model"]["version"]
    for queued, ensemble in zip(sorted(names["queue wait"], key=lambda s: s.start_time),
                                sorted(names["ensemble pass"], key=lambda s: s.start_time)):
        assert queued.end_time <= ensemble.start_time  # queued, then computed
    # the world: its queue and the execution under its server span, under the trial
    (execute,) = names["execute"]
    chain = _ancestors(execute, by_id)
    assert (chain[0].name, chain[0].kind.name) == ("POST /v1/episodes/{episode_id}/execute", "SERVER")
    assert chain[1].kind.name == "CLIENT" and chain[-1].name == "trial"
    assert execute.attributes["firp.world"] == "scripted_world"
    assert len(names["world queue wait"]) == 2 and len(names["begin episode"]) == 1


def test_a_deadline_dropped_job_leaves_a_failed_queue_wait(exporter, tiny_bundle):
    """Work dropped at its deadline shows as a queue wait that ended in error, and no pass."""
    app = create_app(ServiceSettings(bundle=tiny_bundle, threads=1))
    with serve_on_loopback(app) as address:
        import httpx

        model = app.state.model
        running, gate = threading.Event(), threading.Event()
        original = model.score_jobs

        def held(jobs):  # the first pass runs only when the test says so
            running.set()
            assert gate.wait(30)
            return original(jobs)

        model.score_jobs = held
        body = {"image": _png_b64(), "plan": PLAN.tolist()}
        try:
            with httpx.Client(base_url=f"http://{address}", timeout=30) as client:
                blocker = threading.Thread(target=lambda: client.post("/v1/score", json=body))
                blocker.start()
                assert running.wait(30)
                dropped = client.post("/v1/score", json=body, headers={"X-Request-Timeout": "0.2"})
                gate.set()
                blocker.join(30)
        finally:
            gate.set()
            model.score_jobs = original
    assert dropped.status_code == 504 and dropped.json()["error"]["rule"] == "deadline_exceeded"
    failed = [s for s in exporter.get_finished_spans() if s.name == "queue wait" and not s.status.is_ok]
    assert len(failed) == 1 and failed[0].status.description == "deadline_exceeded"


def _png_b64() -> str:
    from tests.service.helpers import encode_image

    return encode_image(np.random.default_rng(3).integers(0, 256, (32, 32, 3), dtype=np.uint8))


def test_a_service_process_continues_the_callers_trace_on_the_console(tiny_bundle):
    """``OTEL_TRACES_EXPORTER=console`` on a real service process: its spans carry the trace id of the
    ``traceparent`` the caller sent, and name the service."""
    import httpx

    trace_id = "4bf92f3577b34da6a3ce929d0e0e4736"
    env = clean_env("FIRP_SERVICE_", OTEL_TRACES_EXPORTER="console", OTEL_SERVICE_NAME="scoring-under-test",
                    OTEL_BSP_SCHEDULE_DELAY="100")
    served = ServedProcess("service", ["--bundle", str(tiny_bundle), "--port", "0"], env, capture_stdout=True)
    with served:
        r = httpx.post(f"{served.base}/v1/score", json={"image": _png_b64(), "plan": PLAN.tolist()}, timeout=30,
                       headers={"traceparent": f"00-{trace_id}-00f067aa0ba902b7-01"})
        assert r.status_code == 200
    printed = _console_spans(served.stdout)
    ours = [s for s in printed if s["context"]["trace_id"] == f"0x{trace_id}"]
    assert {"queue wait", "backbone", "ensemble pass", "POST /v1/score"} <= {s["name"] for s in ours}
    assert {s["resource"]["attributes"]["service.name"] for s in ours} == {"scoring-under-test"}


def test_a_bad_exporter_stops_the_service_with_a_usage_error(tiny_bundle):
    import subprocess
    import sys

    from tests.processes import ROOT

    env = clean_env("FIRP_SERVICE_", OTEL_TRACES_EXPORTER="zipkin")
    out = subprocess.run([sys.executable, "-m", "service", "--bundle", str(tiny_bundle), "--port", "0"], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "OTEL_TRACES_EXPORTER names 'zipkin'" in out.stderr


def _console_spans(text: str) -> list[dict]:
    """The JSON objects ConsoleSpanExporter printed (one indented object per span)."""
    decoder, spans, i = json.JSONDecoder(), [], 0
    while (i := text.find("{", i)) != -1:
        try:
            obj, end = decoder.raw_decode(text, i)
        except ValueError:
            i += 1
            continue
        if isinstance(obj, dict) and "context" in obj and "name" in obj:
            spans.append(obj)
        i = end
    return spans
