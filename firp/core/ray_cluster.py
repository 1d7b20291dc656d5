"""Joining or starting a Ray cluster for one job, the same way for every command that takes ``--ray``.

``local`` starts a private single-node cluster of ``cpus`` CPUs; ``auto`` joins the cluster ``ray
start`` made on this machine (or ``RAY_ADDRESS``'s); any other value is a cluster's address
(``HOST:PORT`` or ``ray://HOST:PORT``). A process already connected keeps its connection. Ray is
imported only here, when a job asks for it (the ``ray`` extra).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

__all__ = ["ray_session"]


@contextmanager
def ray_session(address: str, cpus: int) -> Iterator:
    """The ``ray`` module, connected to ``address`` for the block. On leaving, the driver disconnects if it
    connected here: that stops a private ``local`` cluster and leaves a joined one running."""
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - the dev and robosuite extras install it
        raise RuntimeError("--ray: Ray is not installed in this environment (pip install 'firp[ray]')") from exc
    connected_here = not ray.is_initialized()
    if connected_here:
        options = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if address == "local":
            ray.init(num_cpus=cpus, **options)
        else:
            ray.init(address=address, **options)
    try:
        yield ray
    finally:
        if connected_here:
            ray.shutdown()
