"""Long simulation experiments that survive a crash: jobs on a spawn pool, each record appended as it ends.

Every simulation-heavy experiment here runs the same way -- read the records an earlier, possibly
interrupted run left in a JSONL file, run only the missing jobs in worker processes (``spawn``: no
forked GL contexts), and append each record and flush it the moment it arrives, so a crash loses at
most the jobs in flight. :func:`append_as_done` is that loop, once; :func:`run_seeds` is it for the common
case of one job per scene seed.
"""

from __future__ import annotations

import json
import multiprocessing as mp
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

__all__ = ["append_as_done", "append_record", "drop_torn_tail", "run_seeds"]


def drop_torn_tail(records: Path) -> None:
    """Cut a last line a crash left half-written: appending after it would glue the next record onto it, and
    the reader, which stops at the first unreadable line, would never see anything written after."""
    if not records.exists():
        return
    data = records.read_bytes()
    if data and not data.endswith(b"\n"):
        with records.open("r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)


def append_record(records: Path, record: dict) -> None:
    """Append one record to ``records`` (after cutting a torn last line) and flush it: for experiments that
    run their jobs in this process, one after another."""
    records.parent.mkdir(parents=True, exist_ok=True)
    drop_torn_tail(records)
    with records.open("a") as sink:
        sink.write(json.dumps(record) + "\n")
        sink.flush()


def append_as_done(records: Path, run: Callable[[Any], dict], jobs: Sequence[Any], *, done: dict[Hashable, dict],
                   key: Callable[[dict], Hashable], workers: int, initializer: Callable[..., None],
                   initargs: tuple = (), desc: str, unit: str = "it", already: int = 0) -> None:
    """Run ``run(job)`` for every job in ``min(workers, len(jobs))`` spawned processes (each set up by
    ``initializer(*initargs)``), appending each record to ``records`` as it ends and filing it in ``done``
    under ``key(record)``. ``already``: jobs an earlier run finished, shown as done in the progress bar."""
    if not jobs:
        return
    records.parent.mkdir(parents=True, exist_ok=True)
    drop_torn_tail(records)
    with mp.get_context("spawn").Pool(max(1, min(workers, len(jobs))), initializer, initargs) as pool, \
            records.open("a") as sink, \
            tqdm(total=already + len(jobs), initial=already, desc=desc, unit=unit) as bar:
        for record in pool.imap_unordered(run, jobs):
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            done[key(record)] = record
            bar.update(1)


def run_seeds(records: Path, run: Callable[[int], dict], seeds: Sequence[int], *, workers: int,
              initializer: Callable[..., None], initargs: tuple = (), desc: str) -> dict[int, dict]:
    """Every seed's record (``run(seed)``, keyed by its ``"seed"``): the ones ``records`` already holds, the
    others run now and appended to it. Simulates nothing when every seed is there."""
    from planner_client.loop import read_records

    done: dict[Hashable, dict] = {int(r["seed"]): r for r in read_records(records)}
    todo = [seed for seed in seeds if seed not in done]
    append_as_done(records, run, todo, done=done, key=lambda record: int(record["seed"]), workers=workers,
                   initializer=initializer, initargs=initargs, desc=desc, already=len(seeds) - len(todo))
    return done  # type: ignore[return-value]
