"""A server that does nothing but refuse: the floor of what the overload benchmark's clients can measure.

``benchmarks/service_overload.py --floor`` runs its clients against this instead of the scoring service.
Every ``POST /v1/score/batch`` is answered at once with the service's own refusal (503, rule
``overloaded``, ``Retry-After``) without its body being read, as the service's admission does;
``GET /readyz`` answers 200. It runs under uvicorn as the service does, at the same niceness, while
``--busy`` processes keep as many cores busy as the service's inference does. What its clients measure
is then what the clients, the loopback copies of their ~450 kB bodies and the scheduler cost on this
machine -- with no service logic at all. A refusal p99 at the clients above the target here means no
service can meet that target at the clients on this machine.

    python benchmarks/refusing_server.py --port 8123
"""

from __future__ import annotations

import argparse
import json

REFUSAL = json.dumps({"error": {"code": 503, "field": None, "rule": "overloaded",
                                "message": "refused by benchmarks/refusing_server.py (the clients' floor)"}}).encode()
READY = json.dumps({"status": "ready"}).encode()


async def app(scope, receive, send) -> None:
    """Raw ASGI: no framework, no body read; uvicorn drains what the client sends."""
    if scope["type"] == "lifespan":
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                await send({"type": "lifespan.shutdown.complete"})
                return
    if scope["type"] != "http":
        return
    if scope["path"] == "/readyz":
        status, body, headers = 200, READY, []
    else:
        status, body, headers = 503, REFUSAL, [(b"retry-after", b"1")]
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), *headers]})
    await send({"type": "http.response.body", "body": body})


def main() -> None:
    import uvicorn

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, required=True)
    args = ap.parse_args()
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning", access_log=False)


if __name__ == "__main__":
    main()
