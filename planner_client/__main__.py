"""``python -m planner_client run --trials 50``: the product's main job.

Today it runs the TAMP-style planner against the embedded simulator and reports TAMP alone and the
oracle line; FIRP scoring and replanning are added when the scoring service lands (see README).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from firp.cli import int_in_range


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m planner_client", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run planning trials end to end")
    run.add_argument("--trials", type=int_in_range("--trials", 1, 100_000), default=50)
    run.add_argument("--task", choices=("stacking", "replacement"), default="stacking")
    run.add_argument("--seed", type=int, default=100_000, help="trial i uses scene seed SEED + i")
    run.add_argument("--max-iterations", type=int_in_range("--max-iterations", 1, 6), default=6,
                     help="block orders tried per trial at most (the replanning budget)")
    run.add_argument("--no-oracle", action="store_true", help="skip the oracle line (faster)")
    run.add_argument("--out", type=Path, default=None,
                     help="JSONL of trial records (default: a new runs/<task>-<time>.jsonl)")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    run.add_argument("--sim", default=os.environ.get("FIRP_PLANNER_SIM_URL") or None, metavar="URL",
                     help="sim worker to execute on (env FIRP_PLANNER_SIM_URL); default: the embedded simulator")
    run.add_argument("--service", default=os.environ.get("FIRP_PLANNER_SERVICE_URL") or None, metavar="URL",
                     help="scoring service (env FIRP_PLANNER_SERVICE_URL); checked for readiness only until "
                          "FIRP scoring joins the loop")
    run.add_argument("--ready-timeout", type=int_in_range("--ready-timeout", 1, 3600), default=120,
                     help="seconds to wait for --sim / --service to be ready")
    return parser


def open_backends(args: argparse.Namespace):
    """The simulator backend (remote if ``--sim``, else embedded), after checking that the services
    the run was pointed at are ready -- a wrong URL fails here, naming it, not mid-run."""
    from planner_client.clients import ScoreClient, SimClient
    from planner_client.embedded import EmbeddedSim

    if args.service:
        with ScoreClient(args.service) as scorer:
            scorer.wait_ready(args.ready_timeout)
    if not args.sim:
        return EmbeddedSim()
    sim = SimClient(args.sim)
    try:
        sim.wait_ready(args.ready_timeout)
    except BaseException:
        sim.close()
        raise
    return sim


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.resume and args.out is None:
        parser.error("--resume needs --out: the run file to continue")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from tqdm import tqdm

    from planner_client.loop import RunConfig, read_records, run_trials, summarise
    from planner_client.tamp import TampPlanner
    from planner_client.transport import ServiceError

    out = args.out or Path(f"runs/{args.task}-{time.strftime('%Y%m%d-%H%M%S')}.jsonl")
    config = RunConfig(task=args.task, trials=args.trials, seed=args.seed, max_iterations=args.max_iterations,
                       oracle=not args.no_oracle, out=out, resume=args.resume)
    try:
        sim = open_backends(args)
    except ServiceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    try:
        done = len(read_records(out)) if args.resume else 0
        planner = TampPlanner()
        bar = tqdm(total=args.trials, initial=min(done, args.trials), desc=f"{args.task} trials", unit="trial")
        for record in run_trials(config, sim, planner):
            bar.update(1)
            bar.set_postfix(tamp="ok" if record["tamp_success"] else "fail")
        bar.close()
    except FileExistsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ServiceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    finally:
        sim.close()
    summary = summarise([r for r in read_records(out) if r["trial"] < args.trials])
    print(f"\n{args.task}: {summary['trials']} trials")
    print(f"  TAMP alone          success rate {summary['tamp_success_rate']:.3f}")
    if "oracle_success_rate" in summary:
        print(f"  oracle (any of {args.max_iterations} orders, checked in simulation) {summary['oracle_success_rate']:.3f}")
    print("  TAMP + FIRP         not available yet: the scoring service is not built (see README)")
    print(json.dumps(summary))
    print(f"trial records: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
