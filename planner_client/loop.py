"""The trial loop: per trial a new episode, the planner's first plan, execution, and the oracle line.

Scoring with FIRP (and replanning while the score is below the threshold) joins this loop when the
scoring service exists; until then each trial records the TAMP-alone outcome and the oracle: the
first block order, in the replanning loop's order, whose plan succeeds when executed in the
simulator (the ceiling of any replanning over block orders). Records are appended to a JSONL file
as each trial ends, so an interrupted run resumes without repeating or losing trials.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from planner_client.backend import SimBackend
from planner_client.tamp import TampPlanner, block_orders


@dataclass(frozen=True)
class RunConfig:
    task: str = "stacking"
    trials: int = 50
    seed: int = 100_000  # trial i uses scene seed seed + i (apart from the dataset seeds 0..)
    max_iterations: int = 6
    oracle: bool = True
    out: Path = Path("runs/run.jsonl")
    resume: bool = False


def read_records(path: Path) -> list[dict]:
    """Completed trial records; a torn last line (killed mid-write) is ignored."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return records


def run_trials(config: RunConfig, sim: SimBackend[Any], planner: TampPlanner) -> Iterator[dict]:
    """Run the pending trials, appending one JSON line per finished trial; yields each record."""
    config.out.parent.mkdir(parents=True, exist_ok=True)
    if config.out.exists() and not config.resume:
        raise FileExistsError(f"--out: {config.out} exists; pass --resume to continue it or choose another file")
    records = read_records(config.out)
    done = {r["trial"] for r in records}
    # rewrite without a torn tail so appends start on a clean line
    config.out.write_text("".join(json.dumps(r) + "\n" for r in records))
    orders = block_orders()[: config.max_iterations]
    with config.out.open("a") as sink:
        for trial in range(config.trials):
            if trial in done:
                continue
            started = time.perf_counter()
            seed = config.seed + trial
            episode = sim.start(config.task, seed)
            first = planner.plan(config.task, episode.observation, orders[0])
            outcome = sim.execute(episode, first.actions)
            record = {"trial": trial, "seed": seed, "task": config.task,
                      "tamp_success": outcome.success, "tamp_reason": outcome.reason}
            if config.oracle:
                oracle_order = list(orders[0]) if outcome.success else None
                tried = 1
                for order in orders[1:]:
                    if oracle_order is not None:
                        break
                    tried += 1
                    if sim.execute(episode, planner.plan(config.task, episode.observation, order).actions).success:
                        oracle_order = list(order)
                record.update(oracle_success=oracle_order is not None, oracle_order=oracle_order,
                              oracle_executions=tried)
            record["seconds"] = round(time.perf_counter() - started, 3)
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            yield record


def summarise(records: list[dict]) -> dict:
    n = len(records)
    out = {"trials": n, "tamp_success_rate": sum(r["tamp_success"] for r in records) / n if n else float("nan")}
    with_oracle = [r for r in records if "oracle_success" in r]
    if with_oracle:
        out["oracle_success_rate"] = sum(r["oracle_success"] for r in with_oracle) / len(with_oracle)
    return out
