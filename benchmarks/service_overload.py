"""The scoring service under overload and during a hot swap, as an operator would try it.

Starts ``python -m service`` on loopback with the given bundle (the admission settings as given),
then:

* **overload** -- ``--clients`` keep-alive clients each post ``/v1/score/batch`` with ``--batch``
  plans back to back for ``--seconds``; a refused client (503) waits as the planner client does
  (its ``Retry-After``, stretched by up to half by the client's jitter). A prober polls ``/readyz`` every 50 ms throughout. The clients are coroutines
  spread over ``--client-processes`` processes and the prober runs in its own, so that a client's
  time is not spent waiting for another client's turn at its interpreter. Reported: accepted
  requests (200) p50 / p99 latency, refused requests (503 ``overloaded``) p50 / p99 latency and
  whether each carried ``Retry-After``, any other status or transport error, ``/readyz`` p99, plans/s.
* **server side** -- the service runs with JSON request logs; each request's latency as the service
  saw it (from its first byte to its answer) is read back from them, by status: what the clients
  measure beyond that is their own share of the two cores and the network stack.
* **swap** -- ``--swap-clients`` clients post ``/v1/score`` back to back; after a second the script
  calls ``POST /v2/repository/models/{name}/load`` with a copy of the bundle whose manifest says
  it is another version (the same weights: what is measured is the swap's mechanics -- load,
  verify, warm-up off the serving path, switch). Reported: failed requests (target 0), the load
  call's duration, and the time from the load call to the first answer naming the new version.

Targets: accepted p99 <= 500 ms, refused p99 <= 20 ms, ``/readyz`` p99 <= 50 ms; swap: 0 failed
requests, the new version answering within 10 s of the load call.

``--floor`` runs the same clients against ``benchmarks/refusing_server.py`` instead -- a server that refuses
every request at once without reading it, at the service's niceness, while ``--floor-busy`` processes keep
as many cores busy as the service's inference (one torch thread) -- so the refusals' latency at the clients
is what the clients, the loopback and the scheduler alone cost on this machine.

    python benchmarks/service_overload.py --out docs/results/service_overload.json
    python benchmarks/service_overload.py --floor --out docs/results/service_overload_floor.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_latency import ROOT, Server, fail, free_port, pct, png_b64, random_plans  # noqa: E402

from planner_client.transport import RetryPolicy  # noqa: E402

TARGETS = {"accepted_p99_ms": 500.0, "refused_p99_ms": 20.0, "readyz_p99_ms": 50.0, "swap_failed_requests": 0,
           "swap_new_version_s": 10.0}


def probe_readyz(base: str, seconds: float, out) -> None:  # noqa: ANN001 - a multiprocessing queue
    """``GET /readyz`` every 50 ms for ``seconds``; the latencies (ms) go to ``out``. Run in a process of
    its own, so the clients' threads do not delay it on its side."""
    probes = []
    stop_at = time.monotonic() + seconds
    with httpx.Client(base_url=base, timeout=10) as client:
        while time.monotonic() < stop_at:
            start = time.perf_counter()
            client.get("/readyz")
            probes.append((time.perf_counter() - start) * 1000.0)
            time.sleep(0.05)
    out.put(probes)


def client_process(base: str, body: bytes, clients: int, seconds: float, start_at: float, out) -> None:  # noqa: ANN001
    """``clients`` keep-alive clients posting ``body`` to /v1/score/batch back to back until ``start_at +
    seconds`` (``time.time()``); a refused one waits its Retry-After. Results go to ``out``. The clients
    are coroutines of one event loop, not threads: a thread that got its answer would wait for the
    interpreter's lock behind its siblings, and time that wait as the service's latency."""
    import asyncio

    accepted: list[float] = []
    refused: list[float] = []
    without_retry_after = 0
    other: list[str] = []
    headers = {"content-type": "application/json"}

    async def client() -> None:
        nonlocal without_retry_after
        async with httpx.AsyncClient(base_url=base, timeout=60) as http:
            await asyncio.sleep(max(0.0, start_at - time.time()))
            while time.time() < start_at + seconds:
                start = time.perf_counter()
                try:
                    r = await http.post("/v1/score/batch", content=body, headers=headers)
                except httpx.HTTPError as exc:
                    other.append(repr(exc))
                    continue
                ms = (time.perf_counter() - start) * 1000.0
                if r.status_code == 200:
                    accepted.append(ms)
                elif r.status_code == 503 and r.json()["error"]["rule"] == "overloaded":
                    refused.append(ms)
                    without_retry_after += "retry-after" not in r.headers
                else:
                    other.append(f"{r.status_code}: {r.text[:200]}")
                if r.status_code == 503:  # as the planner client waits: Retry-After, stretched by its jitter
                    await asyncio.sleep(RetryPolicy().wait(1, float(r.headers.get("retry-after", "1"))))

    async def everyone() -> None:
        await asyncio.gather(*(client() for _ in range(clients)))

    asyncio.run(everyone())
    out.put({"accepted": accepted, "refused": refused, "without_retry_after": without_retry_after, "other": other})


def overload(base: str, image: str, plans: list, clients: int, seconds: float, processes: int) -> dict[str, Any]:
    """``clients`` clients in ``processes`` processes, and the /readyz prober in one more: a load generator
    whose own threads share as little as possible (Python's GIL) with what they time."""
    import multiprocessing

    # encoded once: client threads re-encoding 30k floats per request would load the 2 cores more than
    # the service does, and time the clients' GIL instead of the service
    body = json.dumps({"image": image, "plans": plans}).encode()
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    start_at = time.time() + 3.0  # every process started and connected
    shares = [clients // processes + (1 if k < clients % processes else 0) for k in range(processes)]
    workers = [context.Process(target=client_process, args=(base, body, n, seconds, start_at, out))
               for n in shares if n]
    prober = context.Process(target=probe_readyz, args=(base, seconds + 3.0, out))
    for proc in (*workers, prober):
        proc.start()
    results = [out.get(timeout=seconds + 120) for _ in range(len(workers) + 1)]
    for proc in (*workers, prober):
        proc.join(timeout=30)
    probes = next(r for r in results if isinstance(r, list))
    parts = [r for r in results if isinstance(r, dict)]
    accepted = [ms for r in parts for ms in r["accepted"]]
    refused = [ms for r in parts for ms in r["refused"]]
    other = [e for r in parts for e in r["other"]]
    return {"clients": clients, "client_processes": len(workers), "batch": len(plans), "seconds": seconds,
            "accepted": len(accepted), "accepted_p50_ms": pct(accepted, 50) if accepted else None,
            "accepted_p99_ms": pct(accepted, 99) if accepted else None, "accepted_max_ms": max(accepted, default=None),
            "refused": len(refused), "refused_p50_ms": pct(refused, 50) if refused else None,
            "refused_p99_ms": pct(refused, 99) if refused else None,
            "refused_without_retry_after": sum(r["without_retry_after"] for r in parts),
            "other_errors": len(other), "first_other_errors": other[:5],
            "plans_per_s": len(accepted) * len(plans) / seconds,
            "readyz_probes": len(probes), "readyz_p50_ms": pct(probes, 50), "readyz_p99_ms": pct(probes, 99)}


def loop_lag_buckets(base: str) -> dict[float, float]:
    """The service's ``firp_event_loop_lag_seconds`` histogram now: upper bound (s) -> cumulative count."""
    text = httpx.get(f"{base}/metrics", timeout=30).text
    found = re.findall(r'firp_event_loop_lag_seconds_bucket\{le="([^"]+)"\} (\S+)', text)
    return {float(le): float(count) for le, count in found}


def loop_lag(before: dict[float, float], after: dict[float, float]) -> dict[str, Any]:
    """How late the service's event loop woke its 50 ms probe during the run: the probes' count and the
    bucket bounds below which half and 99% of them fell (a histogram gives bounds, not exact quantiles)."""
    bounds = sorted(after)
    counts = [after[b] - before.get(b, 0.0) for b in bounds]
    total = counts[-1]

    def bound(q: float) -> float | None:
        return next((b for b, c in zip(bounds, counts) if c >= q * total), None) if total else None

    return {"probes": int(total), "p50_at_most_ms": _ms(bound(0.5)), "p99_at_most_ms": _ms(bound(0.99)),
            "over_100_ms": int(total - next((c for b, c in zip(bounds, counts) if b >= 0.1), total))}


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else (math.inf if math.isinf(seconds) else seconds * 1000.0)


def server_side(log, start: int) -> dict[str, Any]:
    """Latency per route and status as the service logged it (JSON request lines), from offset ``start``."""
    log.seek(start)
    by: dict[str, list[float]] = {}
    for line in log.read().splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if entry.get("logger") == "service.access":
            by.setdefault(f"{entry['route']} {entry['status']}", []).append(float(entry["latency_ms"]))
    return {key: {"requests": len(v), "p50_ms": pct(v, 50), "p99_ms": pct(v, 99)} for key, v in sorted(by.items())}


def swap(base: str, name: str, image: str, plan: list, clients: int, bundle: Path) -> dict[str, Any]:
    answers: list[tuple[float, int, str | None]] = []
    lock = threading.Lock()
    stop = threading.Event()

    body = json.dumps({"image": image, "plan": plan}).encode()
    headers = {"content-type": "application/json"}

    def worker() -> None:
        with httpx.Client(base_url=base, timeout=60) as client:
            while not stop.is_set():
                try:
                    r = client.post("/v1/score", content=body, headers=headers)
                    version = r.json()["model"]["version"] if r.status_code == 200 else None
                    row = (time.monotonic(), r.status_code, version)
                except httpx.HTTPError as exc:
                    row = (time.monotonic(), -1, repr(exc))
                with lock:
                    answers.append(row)

    threads = [threading.Thread(target=worker) for _ in range(clients)]
    for t in threads:
        t.start()
    time.sleep(1.0)
    called = time.monotonic()
    r = httpx.post(f"{base}/v2/repository/models/{name}/load", json={"parameters": {"bundle": str(bundle)}},
                   timeout=120)
    load_s = time.monotonic() - called
    new = r.json().get("version") if r.status_code == 200 else None
    time.sleep(1.0)
    stop.set()
    for t in threads:
        t.join()
    firsts = [at for at, status, version in answers if status == 200 and version == new]
    return {"clients": clients, "load_status": r.status_code, "load_s": load_s, "new_version": new,
            "requests": len(answers), "failed_requests": sum(1 for _, status, _ in answers if status != 200),
            "new_version_after_s": (min(firsts) - called) if firsts else None}


def _busy(seconds: float) -> None:
    """One core kept busy (pure Python: one interpreter, one core) for ``seconds``."""
    stop_at = time.monotonic() + seconds
    while time.monotonic() < stop_at:
        sum(range(10_000))


def floor(args: argparse.Namespace, image: str, plans: list) -> dict[str, Any]:
    """The clients against a server that refuses everything at once (see the module docstring)."""
    import multiprocessing

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    nice = (lambda: os.nice(args.service_nice)) if args.service_nice else None
    server = subprocess.Popen([sys.executable, str(Path(__file__).with_name("refusing_server.py")), "--port", str(port)],
                              cwd=ROOT, preexec_fn=nice)
    busy = [multiprocessing.get_context("spawn").Process(target=_busy, args=(args.seconds + 10.0,))
            for _ in range(args.floor_busy)]
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(f"{base}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                if time.monotonic() > deadline or server.poll() is not None:
                    fail("benchmarks/refusing_server.py did not start")
                time.sleep(0.2)
        for proc in busy:
            proc.start()
            if args.service_nice:
                os.setpriority(os.PRIO_PROCESS, proc.pid, args.service_nice)
        return overload(base, image, plans, args.clients, args.seconds, args.client_processes)
    finally:
        for proc in busy:
            proc.terminate()
        server.terminate()
        server.wait(timeout=10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=ROOT / "models" / "stacking")
    ap.add_argument("--T", type=int, default=120)
    ap.add_argument("--clients", type=int, default=64)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--client-processes", type=int, default=8,
                    help="processes the clients are spread over (the /readyz prober has one more of its own)")
    ap.add_argument("--service-nice", type=int, default=10,
                    help="the service's niceness: the clients share its cores, and a client that waits for a core "
                         "after its answer arrived would time the scheduler, not the service (0: same priority)")
    ap.add_argument("--swap-clients", type=int, default=8)
    ap.add_argument("--setting", action="append", default=[], metavar="NAME=VALUE",
                    help="a service setting for the run (e.g. max_queued_plans=128); repeatable")
    ap.add_argument("--ready-timeout", type=float, default=300.0)
    ap.add_argument("--floor", action="store_true",
                    help="the clients against benchmarks/refusing_server.py: what they measure with no service logic")
    ap.add_argument("--floor-busy", type=int, default=1,
                    help="with --floor: cores kept busy beside it, as the service's inference keeps (1 torch thread)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "service_overload.json")
    args = ap.parse_args()
    manifest = json.loads((args.bundle / "manifest.json").read_text()) if (args.bundle / "manifest.json").is_file() \
        else fail(f"no bundle at {args.bundle}")
    settings = dict(s.split("=", 1) for s in args.setting)
    rng = np.random.default_rng(0)
    image = png_b64(rng.integers(0, 256, (84, 84, 3), dtype=np.uint8))
    plans = random_plans(args.batch, args.T, seed=2)
    if args.floor:
        o = floor(args, image, plans)
        result = {"floor": o, "busy_cores": args.floor_busy, "server_nice": args.service_nice,
                  "client_processes": args.client_processes, "T": args.T, "targets": TARGETS,
                  "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
                  "command": "python benchmarks/service_overload.py " + " ".join(sys.argv[1:])}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print("\n| the clients against a server that only refuses | value | the service's target |\n|---|---|---|")
        print(f"| refused (503 overloaded) | {o['refused']} · p50 {o['refused_p50_ms']:.1f} ms · p99 "
              f"{o['refused_p99_ms']:.1f} ms | p99 ≤ 20 ms |")
        print(f"| /readyz | p50 {o['readyz_p50_ms']:.1f} ms · p99 {o['readyz_p99_ms']:.1f} ms | p99 ≤ 50 ms |")
        print(f"| other errors | {o['other_errors']} | 0 |\nwrote {args.out}")
        return
    with tempfile.TemporaryDirectory() as tmp:
        other = Path(tmp) / args.bundle.name
        shutil.copytree(args.bundle, other)
        changed = json.loads((other / "manifest.json").read_text())
        changed.setdefault("extra", {})["note"] = "copy made by benchmarks/service_overload.py (same weights)"
        changed.pop("version", None)
        changed["extra"].pop("version", None)
        (other / "manifest.json").write_text(json.dumps(changed, indent=2))
        server = Server(args.bundle, 1, free_port(), args.ready_timeout, settings=settings,
                        log_args=("--log-format", "json", "--log-level", "info"), nice=args.service_nice)
        try:
            print(f"serving {manifest['name']} at {server.base}, settings {settings or 'defaults'}", flush=True)
            mark = os.fstat(server.log.fileno()).st_size  # the service's log so far: start-up
            lag_before = loop_lag_buckets(server.base)
            loaded = overload(server.base, image, plans, args.clients, args.seconds, args.client_processes)
            loaded["server_side"] = server_side(server.log, mark)
            loaded["event_loop_lag"] = loop_lag(lag_before, loop_lag_buckets(server.base))
            swapped = swap(server.base, manifest["name"], image, plans[0], args.swap_clients, other)
        finally:
            server.stop()
    checks = {"accepted_p99_ms": loaded["accepted_p99_ms"] is not None and loaded["accepted_p99_ms"] <= 500.0,
              "refused_p99_ms": loaded["refused_p99_ms"] is None or loaded["refused_p99_ms"] <= 20.0,
              "readyz_p99_ms": loaded["readyz_p99_ms"] <= 50.0, "no_other_errors": loaded["other_errors"] == 0,
              "swap_failed_requests": swapped["failed_requests"] == 0,
              "swap_new_version_s": swapped["new_version_after_s"] is not None
              and swapped["new_version_after_s"] <= 10.0}
    result = {"bundle": str(args.bundle), "T": args.T, "settings": settings, "service_nice": args.service_nice,
              "client_processes": args.client_processes, "overload": loaded, "swap": swapped,
              "targets": TARGETS, "checks": checks, "machine": {"python": platform.python_version(),
                                                                "cpus": os.cpu_count()},
              "command": "python benchmarks/service_overload.py " + " ".join(sys.argv[1:])}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    o = loaded
    print("\n| measure | value | target |\n|---|---|---|")
    print(f"| accepted (200) | {o['accepted']} · p50 {o['accepted_p50_ms']:.0f} ms · p99 {o['accepted_p99_ms']:.0f} ms | p99 ≤ 500 ms |")
    if o["refused"]:
        print(f"| refused (503 overloaded) | {o['refused']} · p50 {o['refused_p50_ms']:.1f} ms · p99 "
              f"{o['refused_p99_ms']:.1f} ms · without Retry-After {o['refused_without_retry_after']} | p99 ≤ 20 ms |")
    print(f"| other errors | {o['other_errors']} | 0 |")
    print(f"| /readyz | p50 {o['readyz_p50_ms']:.1f} ms · p99 {o['readyz_p99_ms']:.1f} ms | p99 ≤ 50 ms |")
    print(f"| plans/s | {o['plans_per_s']:.0f} | |")
    for key, v in o["server_side"].items():
        print(f"| service side: {key} | {v['requests']} · p50 {v['p50_ms']:.1f} ms · p99 {v['p99_ms']:.1f} ms | |")
    lag = o["event_loop_lag"]
    print(f"| service side: event loop lag ({lag['probes']} probes of 50 ms) | p50 ≤ {lag['p50_at_most_ms']:g} ms · "
          f"p99 ≤ {lag['p99_at_most_ms']:g} ms · {lag['over_100_ms']} over 100 ms | |")
    s = swapped
    print(f"| swap: failed requests | {s['failed_requests']} of {s['requests']} | 0 |")
    print(f"| swap: load call / new version answering | {s['load_s']:.2f} s / "
          f"{s['new_version_after_s'] if s['new_version_after_s'] is None else round(s['new_version_after_s'], 2)} s | ≤ 10 s |")
    print(f"\nchecks: {checks}\nwrote {args.out}")


if __name__ == "__main__":
    main()
