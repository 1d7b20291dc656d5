"""Readiness probe for container health checks: ``python -m firp.core.probe URL``.

Exit 0 when ``URL`` answers 200 within the timeout, else 1 with one line saying why. It exists
because a health check written as ``python -c "<code with spaces>"`` does not survive every engine:
podman's Docker-compatible API re-splits a ``CMD`` health check's arguments at spaces, so the code
arrives as broken words. This probe takes only space-free arguments. ``--port-env NAME`` takes the
port from an environment variable (the image's ``FIRP_*_PORT``), so an image whose port is changed
by the environment keeps probing the right one. Standard library only: every image has it.
"""

from __future__ import annotations

import argparse
import os
import sys
import urllib.error
import urllib.parse
import urllib.request


def probe_url(url: str, port_env: str | None) -> str:
    """``url`` with its port replaced by the value of ``port_env`` when that variable is set."""
    if not port_env or not os.environ.get(port_env):
        return url
    port = os.environ[port_env]
    if not port.isdigit():
        raise ValueError(f"{port_env}={port!r} is not a port number")
    parts = urllib.parse.urlsplit(url)
    return parts._replace(netloc=f"{parts.hostname}:{port}").geturl()


def probe(url: str, timeout: float) -> tuple[bool, str]:
    """(ready, why): ready only on a 200 answer."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as answer:
            return answer.status == 200, f"{url}: {answer.status}"
    except urllib.error.HTTPError as error:  # 503 while loading, warming up or draining
        return False, f"{url}: {error.code}"
    except (urllib.error.URLError, OSError) as error:
        return False, f"{url}: {getattr(error, 'reason', error)}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m firp.core.probe", description=__doc__.splitlines()[0])
    parser.add_argument("url", help="e.g. http://127.0.0.1:8001/readyz")
    parser.add_argument("--port-env", help="environment variable whose value replaces the URL's port, when set")
    parser.add_argument("--timeout", type=float, default=4.0, help="seconds (default 4)")
    args = parser.parse_args(argv)
    try:
        url = probe_url(args.url, args.port_env)
    except ValueError as error:
        parser.error(str(error))
    ready, why = probe(url, args.timeout)
    print(why, file=sys.stdout if ready else sys.stderr)
    return 0 if ready else 1


if __name__ == "__main__":
    sys.exit(main())
