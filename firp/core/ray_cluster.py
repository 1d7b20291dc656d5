"""Joining or starting a Ray cluster for one job, the same way for every command that takes ``--ray``.

``local`` starts a private single-node cluster of ``cpus`` CPUs; ``auto`` joins the cluster ``ray
start`` made on this machine (or ``RAY_ADDRESS``'s); any other value is a cluster's address
(``HOST:PORT`` or ``ray://HOST:PORT``). A process already connected keeps its connection. Ray is
imported only here, when a job asks for it (the ``ray`` extra).
"""

from __future__ import annotations

from collections import deque
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator

__all__ = ["IN_FLIGHT_PER_ACTOR", "as_completed_on_actors", "ray_session"]

#: calls queued on each actor: one running, one waiting, so an actor never idles between calls
IN_FLIGHT_PER_ACTOR = 2


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


def as_completed_on_actors(ray: Any, actors: list, items: Iterable, call: Callable[[Any, Any], Any]) -> Iterator[Any]:
    """``call(actor, item)`` (a remote call: an object ref) for every item, fed to ``actors`` so that
    each has :data:`IN_FLIGHT_PER_ACTOR` calls queued; yields each call's result as it completes (in
    completion order), the finished actor's next call submitted first."""
    waiting = deque(items)
    in_flight: dict = {}

    def submit(actor: Any) -> None:
        if waiting:
            in_flight[call(actor, waiting.popleft())] = actor

    for actor in actors:
        for _ in range(IN_FLIGHT_PER_ACTOR):
            submit(actor)
    while in_flight:
        (ref,), _ = ray.wait(list(in_flight), num_returns=1)
        actor = in_flight.pop(ref)
        result = ray.get(ref)
        submit(actor)
        yield result
