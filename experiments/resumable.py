"""Long simulation experiments that survive a crash: jobs on a spawn pool, each record appended as it ends.

Every simulation-heavy experiment here runs the same way -- read the records an earlier, possibly
interrupted run left in a JSONL file, run only the missing jobs in worker processes (``spawn``: no
forked GL contexts), and append each record and flush it the moment it arrives, so a crash loses at
most the jobs in flight. :func:`append_as_done` is that loop, once.
"""

from __future__ import annotations

import json
import multiprocessing as mp
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

__all__ = ["append_as_done"]


def append_as_done(records: Path, run: Callable[[Any], dict], jobs: Sequence[Any], *, done: dict[Hashable, dict],
                   key: Callable[[dict], Hashable], workers: int, initializer: Callable[..., None],
                   initargs: tuple = (), desc: str, unit: str = "it", already: int = 0) -> None:
    """Run ``run(job)`` for every job in ``min(workers, len(jobs))`` spawned processes (each set up by
    ``initializer(*initargs)``), appending each record to ``records`` as it ends and filing it in ``done``
    under ``key(record)``. ``already``: jobs an earlier run finished, shown as done in the progress bar."""
    if not jobs:
        return
    records.parent.mkdir(parents=True, exist_ok=True)
    with mp.get_context("spawn").Pool(max(1, min(workers, len(jobs))), initializer, initargs) as pool, \
            records.open("a") as sink, \
            tqdm(total=already + len(jobs), initial=already, desc=desc, unit=unit) as bar:
        for record in pool.imap_unordered(run, jobs):
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            done[key(record)] = record
            bar.update(1)
