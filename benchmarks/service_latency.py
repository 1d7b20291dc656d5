"""Scoring service latency and throughput over HTTP on loopback, as a planner sees it.

Starts ``python -m service`` (uvicorn) as a subprocess on 127.0.0.1 with the given bundle, waits
until ``/readyz`` says ready, then measures with keep-alive HTTP clients:

* single ``POST /v1/score`` (T steps, one plan), the same scene image every time (the planner's
  case: its backbone features are cached after the first call) and a new image every time (cache
  miss: PNG decode + backbone on every call) -- p50 / p99 per run, medians over runs;
* ``POST /v1/score/batch`` with ``--batch`` plans -- plans per second;
* ``--clients`` concurrent clients for ``--seconds`` -- errors, throughput, p50 / p99;
* single V2 inference (``POST /v2/models/{name}/infer``, same image and plan) in the JSON form and
  with the binary tensor extension as Triton's clients send it (image as UINT8 pixels, plan as
  FP32 bytes, binary outputs);
* with ``--compare-no-micro-batch``: the concurrent run again on a server with micro-batching off;
  with ``--compare-threads N``: single and batch again on a server with N torch threads;
* the ratio of executing a T=120 plan in the simulator (``docs/results/sim_throughput.json``, not
  re-measured: this script does not import mujoco) to scoring it.

Targets (issue 4; for T = 120 and five members): single p50 <= 15 ms, p99 <= 40 ms; batch of 32
>= 200 plans/s; concurrent: zero errors.

    python benchmarks/service_latency.py --bundle models/stacking --compare-no-micro-batch --compare-threads 2
    python benchmarks/service_latency.py --bundle /tmp/tiny --T 16 --seconds 5 --repeats 50 --out /tmp/smoke.json

The client process imports neither torch nor mujoco; the server runs with ``--threads`` torch
threads and ``OMP_NUM_THREADS`` set to the same.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import threading
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image

from firp.core.contract import JOINT_LOWER, JOINT_UPPER, make_plan

ROOT = Path(__file__).resolve().parents[1]
SIM_RESULTS = ROOT / "docs" / "results" / "sim_throughput.json"
TARGETS = {"single_p50_ms": 15.0, "single_p99_ms": 40.0, "batch32_plans_per_s": 200.0, "concurrent_errors": 0}


def fail(message: str) -> None:
    print(f"service_latency: error: {message}", file=sys.stderr)
    sys.exit(2)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def png_b64(image: np.ndarray) -> str:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def random_plans(n: int, t: int, seed: int) -> list[list[list[float]]]:
    rng = np.random.default_rng(seed)
    return [make_plan(rng.integers(0, 7, t), rng.uniform(JOINT_LOWER, JOINT_UPPER, (t, 9))).tolist()
            for _ in range(n)]


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


class Server:
    """``python -m service`` in a subprocess; stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(self, bundle: Path, threads: int, port: int, ready_timeout: float, micro_batch: bool = True,
                 settings: dict[str, str] | None = None, log_args: tuple[str, ...] = ("--no-access-log", "--log-level",
                                                                                        "warning"), nice: int = 0):
        self.base = f"http://127.0.0.1:{port}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("FIRP_SERVICE_")}
        env.update(OMP_NUM_THREADS=str(threads), PYTHONPATH=str(ROOT), FIRP_SERVICE_MICRO_BATCH=str(micro_batch).lower())
        env.update({f"FIRP_SERVICE_{k.upper()}": v for k, v in (settings or {}).items()})
        self.log = open(Path(os.environ.get("TMPDIR", "/tmp")) / f"service_latency_{port}.log", "w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", str(port), "--bundle", str(bundle),
             "--threads", str(threads), *log_args],
            cwd=ROOT, env=env, stdout=self.log, stderr=subprocess.STDOUT,
            preexec_fn=(lambda: os.nice(nice)) if nice else None)  # lower priority than the clients timing it
        deadline = time.monotonic() + ready_timeout
        while True:
            if self.proc.poll() is not None:
                self.log.seek(0)
                fail(f"the service exited with status {self.proc.returncode} before it was ready:\n{self.log.read()}")
            try:
                r = httpx.get(f"{self.base}/readyz", timeout=2)
                if r.status_code == 200:
                    self.ready = r.json()
                    return
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                self.stop()
                fail(f"the service was not ready within {ready_timeout:.0f} s")
            time.sleep(0.2)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def timed_post(client: httpx.Client, url: str, body: dict[str, Any]) -> tuple[float, dict[str, Any]]:
    start = time.perf_counter()
    r = client.post(url, json=body)
    elapsed = time.perf_counter() - start
    if r.status_code != 200:
        fail(f"{url} answered {r.status_code}: {r.text[:500]}")
    return elapsed, r.json()


def single_runs(base: str, images: list[str], plan: list[list[float]], runs: int, repeats: int) -> dict[str, Any]:
    """Sequential /v1/score calls; ``images`` cycles (one image: all cache hits after the first)."""
    per_run = []
    with httpx.Client(base_url=base, timeout=60) as client:
        for _ in range(5):  # connection + first-call effects out of the measurement
            timed_post(client, "/v1/score", {"image": images[0], "plan": plan})
        k = 0
        for _ in range(runs):
            lat, server = [], []
            for _ in range(repeats):
                k += 1
                t, body = timed_post(client, "/v1/score", {"image": images[k % len(images)], "plan": plan})
                lat.append(t * 1000.0)
                server.append(body["elapsed_ms"])
            per_run.append({"p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99), "mean_ms": statistics.fmean(lat),
                            "server_p50_ms": pct(server, 50)})
    return {key: statistics.median(r[key] for r in per_run) for key in per_run[0]} | {"runs": per_run}


def v2_bodies(image: np.ndarray, plan: list[list[float]]) -> dict[str, tuple[bytes, dict[str, str]]]:
    """The same V2 request as JSON and with the binary tensor extension (what ``tritonclient.http``
    sends by default: no Content-Type, ``Inference-Header-Content-Length``, binary outputs)."""
    arr = np.asarray(plan, dtype=np.float32)
    image_spec = {"name": "image", "shape": list(image.shape), "datatype": "UINT8"}
    plan_spec = {"name": "plan", "shape": list(arr.shape), "datatype": "FP32"}
    as_json = json.dumps({"inputs": [{**image_spec, "data": image.ravel().tolist()},
                                     {**plan_spec, "data": arr.ravel().tolist()}]}).encode()
    header = json.dumps({"inputs": [{**image_spec, "parameters": {"binary_data_size": image.nbytes}},
                                    {**plan_spec, "parameters": {"binary_data_size": arr.nbytes}}],
                         "parameters": {"binary_data_output": True}}).encode()
    return {"json": (as_json, {"Content-Type": "application/json"}),
            "binary": (header + image.tobytes() + arr.tobytes(), {"Inference-Header-Content-Length": str(len(header))})}


def v2_runs(base: str, model: str, body: bytes, headers: dict[str, str], runs: int, repeats: int) -> dict[str, Any]:
    """Sequential V2 infer calls with a prepared body (the same image every time: cached features)."""
    url = f"/v2/models/{model}/infer"

    def call(client: httpx.Client) -> float:
        start = time.perf_counter()
        r = client.post(url, content=body, headers=headers)
        if r.status_code != 200:
            fail(f"{url} answered {r.status_code}: {r.text[:500]}")
        return (time.perf_counter() - start) * 1000.0

    per_run = []
    with httpx.Client(base_url=base, timeout=60) as client:
        for _ in range(5):
            call(client)
        for _ in range(runs):
            lat = [call(client) for _ in range(repeats)]
            per_run.append({"p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99), "mean_ms": statistics.fmean(lat)})
    return {key: statistics.median(r[key] for r in per_run) for key in per_run[0]} | {"runs": per_run}


def batch_runs(base: str, image: str, plans: list[list[list[float]]], runs: int, repeats: int) -> dict[str, Any]:
    per_run = []
    with httpx.Client(base_url=base, timeout=120) as client:
        timed_post(client, "/v1/score/batch", {"image": image, "plans": plans})
        for _ in range(runs):
            lat = [timed_post(client, "/v1/score/batch", {"image": image, "plans": plans})[0] for _ in range(repeats)]
            per_run.append({"p50_ms": pct(lat, 50) * 1000.0, "plans_per_s": len(plans) * len(lat) / sum(lat)})
    return {key: statistics.median(r[key] for r in per_run) for key in per_run[0]} | {"runs": per_run}


def concurrent_run(base: str, image: str, plan: list[list[float]], clients: int, seconds: float) -> dict[str, Any]:
    """``clients`` threads, each a keep-alive client sending /v1/score back to back for ``seconds``."""
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors: list[list[str]] = [[] for _ in range(clients)]
    stop_at = time.monotonic() + seconds
    barrier = threading.Barrier(clients)

    def worker(i: int) -> None:
        with httpx.Client(base_url=base, timeout=60) as client:
            barrier.wait()
            while time.monotonic() < stop_at:
                start = time.perf_counter()
                try:
                    r = client.post("/v1/score", json={"image": image, "plan": plan, "request_id": f"c{i}"})
                    if r.status_code != 200:
                        errors[i].append(f"{r.status_code}: {r.text[:200]}")
                except httpx.HTTPError as exc:
                    errors[i].append(repr(exc))
                latencies[i].append((time.perf_counter() - start) * 1000.0)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(clients)]
    start = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - start
    lat = [x for per in latencies for x in per]
    errs = [e for per in errors for e in per]
    return {"clients": clients, "seconds": wall, "requests": len(lat), "errors": len(errs),
            "first_errors": errs[:5], "requests_per_s": len(lat) / wall, "p50_ms": pct(lat, 50),
            "p99_ms": pct(lat, 99)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=ROOT / "models" / "stacking",
                    help="bundle directory to serve (default: the shipped stacking bundle)")
    ap.add_argument("--T", type=int, default=120, help="plan length (must lie in the bundle's T range)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the server")
    ap.add_argument("--runs", type=int, default=3, help="repeated runs; the results are their medians")
    ap.add_argument("--repeats", type=int, default=200, help="requests per run of the single-plan measurement")
    ap.add_argument("--batch", type=int, default=32, help="plans per /v1/score/batch call")
    ap.add_argument("--clients", type=int, default=8, help="concurrent clients")
    ap.add_argument("--seconds", type=float, default=60.0, help="duration of the concurrent measurement")
    ap.add_argument("--image-size", type=int, default=84, help="side of the PNG sent (the camera's frames: 84)")
    ap.add_argument("--ready-timeout", type=float, default=300.0)
    ap.add_argument("--no-micro-batch", dest="micro_batch", action="store_false",
                    help="measure a server with micro-batching off (FIRP_SERVICE_MICRO_BATCH=false)")
    ap.add_argument("--compare-no-micro-batch", action="store_true",
                    help="also run the concurrent measurement on a second server with micro-batching off")
    ap.add_argument("--compare-threads", type=int, default=None, metavar="N",
                    help="also measure single and batch on a second server with N torch threads")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "service_latency.json")
    args = ap.parse_args()

    manifest_path = args.bundle / "manifest.json"
    if not manifest_path.is_file():
        fail(f"no bundle at {args.bundle} (no {manifest_path.name}). Export one (python -m firp.tune ... "
             "--export DIR) and pass --bundle DIR.")
    manifest = json.loads(manifest_path.read_text())
    t_min, t_max = manifest["t_range"]["t_min"], manifest["t_range"]["t_max"]
    if not t_min <= args.T <= t_max:
        fail(f"--T {args.T} is outside the bundle's T range [{t_min}, {t_max}]; pass --T in that range")
    members = len(manifest["members"])

    rng = np.random.default_rng(0)
    base_image = rng.integers(0, 256, (args.image_size, args.image_size, 3), dtype=np.uint8)
    same = [png_b64(base_image)]
    distinct = []
    for i in range(min(args.repeats, 512)):
        img = base_image.copy()
        img[0, 0] = (i % 256, i // 256, 7)
        distinct.append(png_b64(img))
    plan = random_plans(1, args.T, seed=1)[0]
    plans = random_plans(args.batch, args.T, seed=2)

    bodies = v2_bodies(base_image, plan)
    server = Server(args.bundle, args.threads, free_port(), args.ready_timeout, args.micro_batch)
    try:
        print(f"serving {manifest['name']} ({members} members, T={args.T}, micro-batching "
              f"{'on' if args.micro_batch else 'off'}) at {server.base}; "
              f"warm-up {server.ready.get('warmup_ms', 0):.0f} ms", flush=True)
        cached = single_runs(server.base, same, plan, args.runs, args.repeats)
        uncached = single_runs(server.base, distinct, plan, args.runs, args.repeats)
        v2 = {form: v2_runs(server.base, manifest["name"], body, headers, args.runs, args.repeats)
              for form, (body, headers) in bodies.items()}
        batch = batch_runs(server.base, same[0], plans, args.runs, max(args.repeats // 10, 5))
        concurrent = concurrent_run(server.base, same[0], plan, args.clients, args.seconds)
    finally:
        server.stop()
    compare: dict[str, Any] = {}
    if args.compare_no_micro_batch:
        other = Server(args.bundle, args.threads, free_port(), args.ready_timeout, micro_batch=not args.micro_batch)
        try:
            print(f"comparison: micro-batching {'off' if args.micro_batch else 'on'}", flush=True)
            compare["micro_batch_" + ("off" if args.micro_batch else "on")] = {
                "concurrent": concurrent_run(other.base, same[0], plan, args.clients, args.seconds)}
        finally:
            other.stop()
    if args.compare_threads is not None:
        other = Server(args.bundle, args.compare_threads, free_port(), args.ready_timeout, args.micro_batch)
        try:
            print(f"comparison: {args.compare_threads} torch threads", flush=True)
            compare[f"threads_{args.compare_threads}"] = {
                "single_same_image": single_runs(other.base, same, plan, args.runs, args.repeats),
                "batch": batch_runs(other.base, same[0], plans, args.runs, max(args.repeats // 10, 5))}
        finally:
            other.stop()

    sim = json.loads(SIM_RESULTS.read_text()) if SIM_RESULTS.is_file() else None
    sim_task = manifest["task"] if sim and manifest["task"] in sim["results"]["tasks"] else "stacking"
    sim_s = sim["results"]["tasks"][sim_task]["execute_with_frames_s"] if sim else None
    ratio = {
        "sim_task": sim_task,
        "sim_execute_T120_with_frames_s": sim_s,
        "score_p50_new_image_ms": uncached["p50_ms"],
        "execute_over_score": None if sim_s is None else sim_s / (uncached["p50_ms"] / 1000.0),
    }
    applicable = args.T == 120 and members == 5
    met = {
        "single_p50": cached["p50_ms"] <= TARGETS["single_p50_ms"],
        "single_p99": cached["p99_ms"] <= TARGETS["single_p99_ms"],
        "batch32_throughput": args.batch == 32 and batch["plans_per_s"] >= TARGETS["batch32_plans_per_s"],
        "concurrent_no_errors": concurrent["errors"] == 0,
    }
    rows = [
        ("single /v1/score, same image: p50 / p99 ms", f"{cached['p50_ms']:.1f} / {cached['p99_ms']:.1f}"),
        ("  of which in the service (p50 ms)", f"{cached['server_p50_ms']:.1f}"),
        ("single /v1/score, new image: p50 / p99 ms", f"{uncached['p50_ms']:.1f} / {uncached['p99_ms']:.1f}"),
        (f"batch of {args.batch}: p50 ms per call", f"{batch['p50_ms']:.1f}"),
        (f"batch of {args.batch}: plans/s", f"{batch['plans_per_s']:.0f}"),
        (f"{args.clients} clients x {concurrent['seconds']:.0f} s: requests/s", f"{concurrent['requests_per_s']:.1f}"),
        (f"{args.clients} clients: p50 / p99 ms", f"{concurrent['p50_ms']:.1f} / {concurrent['p99_ms']:.1f}"),
        (f"{args.clients} clients: errors / requests", f"{concurrent['errors']} / {concurrent['requests']}"),
        ("V2 infer JSON, same image: p50 / p99 ms", f"{v2['json']['p50_ms']:.1f} / {v2['json']['p99_ms']:.1f}"),
        ("V2 infer binary, same image: p50 / p99 ms", f"{v2['binary']['p50_ms']:.1f} / {v2['binary']['p99_ms']:.1f}"),
    ]
    for name, res in compare.items():
        if "concurrent" in res:
            c = res["concurrent"]
            rows.append((f"[{name}] {args.clients} clients: req/s, p99 ms, errors",
                         f"{c['requests_per_s']:.1f}, {c['p99_ms']:.0f}, {c['errors']}"))
        if "single_same_image" in res:
            rows.append((f"[{name}] single same image: p50 / p99 ms",
                         f"{res['single_same_image']['p50_ms']:.1f} / {res['single_same_image']['p99_ms']:.1f}"))
            rows.append((f"[{name}] batch of {args.batch}: plans/s", f"{res['batch']['plans_per_s']:.0f}"))
    if ratio["execute_over_score"] is not None:
        rows.append((f"simulating ({sim_task}, T=120, frames) / scoring (new image)",
                     f"{ratio['execute_over_score']:.0f}x"))
    width = max(len(r[0]) for r in rows) + 2
    table = "\n".join(f"{name:<{width}}{value:>16}" for name, value in rows)
    print(table)
    verdict = ", ".join(f"{k}: {'met' if v else 'NOT met'}" for k, v in met.items())
    print(f"targets (T=120, 5 members{'' if applicable else '; NOT this configuration'}): {verdict}")

    def version(pkg: str) -> str | None:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return None

    result = {
        "command": "python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": version("torch"),
                    "load_avg_1min": os.getloadavg()[0]},
        "bundle": {"path": str(args.bundle), "name": manifest["name"], "version": server.ready["model"]["version"],
                   "task": manifest["task"], "members": members, "kinds": [m["kind"] for m in manifest["members"]],
                   "image_size": manifest["image_size"], "backbone": manifest["backbone"]["name"],
                   "t_range": [t_min, t_max]},
        "settings": {"T": args.T, "threads": args.threads, "runs": args.runs, "repeats": args.repeats,
                     "batch": args.batch, "clients": args.clients, "seconds": args.seconds,
                     "image_size_sent": args.image_size, "micro_batch": args.micro_batch},
        "results": {"single_same_image": cached, "single_new_image": uncached, "batch": batch,
                    "concurrent": concurrent, "v2_single_same_image": v2, "sim_ratio": ratio},
        "comparisons": compare,
        "targets": TARGETS,
        "targets_applicable": applicable,
        "targets_met": met,
        "table": table,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
