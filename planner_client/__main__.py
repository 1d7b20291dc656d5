"""``python -m planner_client run --trials 50`` (the product's main job) and ``... collect`` (datasets).

**run** -- per trial: a new episode; the TAMP planner's plan is scored by the FIRP scoring service
and the planner replans with the next block order while the score is below the threshold, up to
--max-iterations plans; the accepted (or last) plan is executed in the simulator. TAMP alone (the
first plan, unscored) and the oracle line (the first block order that succeeds in simulation) run
on the same episodes. At the end: the success-rate tables, also written beside --out as
<out>.summary.md / .summary.json / .summary.png. With no --sim / --service (nor
FIRP_PLANNER_SIM_URL / FIRP_PLANNER_SERVICE_URL), both services are launched on loopback for the
run (logs in <out dir>/logs/); the service loads --bundle or the task's shipped bundle.

**collect** -- labelled episodes for training: per episode a seeded scene and block order, the
planner's plan, its execution with one frame per step, the label; written crash-safe into a
robomimic-style HDF5 file, resumable, in worker processes.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

from firp.core.cli_types import int_in_range, non_negative_float, open_unit_float
from firp.core.decisions import DECISION_RULES
from firp.core.contract import DEFAULT_T, T_MAX, T_MIN

EXIT_USAGE, EXIT_SERVICE, EXIT_INTERRUPTED = 2, 3, 130
#: the tasks of our MuJoCo world (sim_worker.tasks.TASK_NAMES; not imported here, which would load MuJoCo)
TASKS = ("stacking", "replacement")
#: the robosuite world's tasks (robosuite_worker.tasks.TASKS; not imported here, which would need robosuite)
ROBOSUITE_TASKS = ("stack_three", "nut_assembly", "nut_assembly_round", "pick_place")
WORLDS = ("mujoco", "robosuite")


def build_parser(prog: str = "python -m planner_client") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    add_run_parser(sub)
    add_collect_parser(sub)
    return parser


def add_run_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``run`` subcommand's flags (defaults of the service URLs etc. from :class:`PlannerSettings`)."""
    from planner_client.settings import PlannerSettings

    settings = PlannerSettings()
    run = sub.add_parser("run", help="run planning trials end to end (the main job)")
    run.add_argument("--trials", type=int_in_range("--trials", 1, 100_000), default=50)
    run.add_argument("--world", choices=WORLDS, default="mujoco",
                     help="mujoco: our world; robosuite: robosuite's tasks, the run continuing in the robosuite "
                          "environment (.venv-robosuite) with the scoring service in this one")
    run.add_argument("--task", choices=TASKS + ROBOSUITE_TASKS, default=None,
                     help="default: stacking (mujoco), stack_three (robosuite)")
    run.add_argument("--seed", type=int, default=100_000, help="trial i uses scene seed SEED + i")
    run.add_argument("--max-iterations", type=int_in_range("--max-iterations", 1, 6), default=6,
                     help="plans scored per trial at most, one per candidate: block order in our world, the "
                          "planner's choice in robosuite's (the replanning budget; also the oracle's)")
    run.add_argument("--threshold", type=non_negative_float("--threshold"), default=None,
                     help="accept a plan when its score is >= this (default: the service's threshold)")
    run.add_argument("--rule", choices=DECISION_RULES, default="threshold",
                     help="which plan TAMP + FIRP executes: threshold (the paper's: the first whose score reaches the "
                          "threshold, else the last scored), rank (plan every candidate, score them in one call, "
                          "execute the highest), conformal (the paper's rule at the threshold that bounds the rate of "
                          "accepted failures at --alpha, from the bundle's validation failures)")
    run.add_argument("--alpha", type=open_unit_float("--alpha"), default=0.1,
                     help="the conformal rule's false-accept rate (default 0.1)")
    run.add_argument("--explore", type=int_in_range("--explore", 0, 6), default=0, metavar="K",
                     help="also execute up to K more candidates, those the ensemble is least sure of first (score "
                          "nearest the threshold): labels where the model is weakest, for --record (default 0)")
    run.add_argument("--no-compare-rules", action="store_true",
                     help="skip scoring every candidate for the summary's side-by-side table of the rules")
    run.add_argument("--replan-on-uninformative", action="store_true",
                     help="replan on the scores even when the bundle is not shown better than chance (its validation "
                          "interval reaches 0.5); by default TAMP's first plan is executed then")
    run.add_argument("--horizon", type=int_in_range("--horizon", T_MIN, T_MAX), default=None,
                     help=f"plan length T in steps at 4 FPS (our world; default {DEFAULT_T}); must be in the bundle's "
                          "T range. robosuite's tasks have their own T")
    run.add_argument("--no-oracle", action="store_true", help="skip the oracle line (faster)")
    run.add_argument("--no-score", action="store_true",
                     help="debugging: TAMP alone and the oracle line only, no scoring service")
    run.add_argument("--out", type=Path, default=None,
                     help="JSONL of trial records (default: a new runs/<task>-<time>.jsonl)")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run in --out (same settings)")
    run.add_argument("--record", type=Path, default=None, metavar="DIR",
                     help="record every executed plan (frames, plan, label, scene id, the score and the bundle "
                          "version) as episodes training reads: DIR/executions.h5 (resumable)")
    run.add_argument("--sim", default=settings.sim_url, metavar="URL[,URL...]",
                     help="running sim worker(s) (env FIRP_PLANNER_SIM_URL); several, comma-separated, run one "
                          "trial each at a time; default: launch --parallel of them for the run")
    run.add_argument("--parallel", type=int_in_range("--parallel", 1, 64), default=None, metavar="K",
                     help="trials run at once, one per sim worker (launched: K of them; given: one per --sim URL); "
                          "one scoring service serves them all; records equal a sequential run's (default 1)")
    run.add_argument("--ray", default=None, metavar="local|auto|ADDRESS",
                     help="run the trials on --parallel Ray actors, each with our world in its own process (no sim "
                          "worker): local starts a private cluster for the run, auto joins this machine's (ray "
                          "start) or RAY_ADDRESS's, else a cluster address (then give --service, reachable from its "
                          "nodes); records equal a sequential run's")
    run.add_argument("--service", default=settings.service_url, metavar="URL",
                     help="running scoring service (env FIRP_PLANNER_SERVICE_URL); default: launch one for the run")
    run.add_argument("--bundle", type=Path, default=None,
                     help="bundle the launched service loads (default: the shipped bundle, models/<task>)")
    run.add_argument("--api-key", default=settings.api_key.get_secret_value() if settings.api_key else None,
                     help="X-API-Key for the scoring service (env FIRP_PLANNER_API_KEY)")
    run.add_argument("--ready-timeout", type=int_in_range("--ready-timeout", 1, 3600), default=settings.ready_timeout,
                     help="seconds to wait for the services to be ready (env FIRP_PLANNER_READY_TIMEOUT)")
    return run


def add_collect_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``collect`` subcommand's flags."""
    c = sub.add_parser("collect", help="simulate labelled episodes into a robomimic-style HDF5 file (resumable)")
    c.add_argument("--world", choices=WORLDS, default="mujoco",
                   help="mujoco: our world (tasks stacking, replacement); robosuite: robosuite's tasks (stack_three, "
                        "nut_assembly, nut_assembly_round, pick_place), run in the robosuite environment (.venv-robosuite)")
    c.add_argument("--task", required=True, choices=TASKS + ROBOSUITE_TASKS)
    c.add_argument("--episodes", required=True, type=int_in_range("--episodes", 1, 1_000_000))
    c.add_argument("--out", required=True, type=Path, help="HDF5 file to write (parts kept beside it until done)")
    c.add_argument("--workers", type=int_in_range("--workers", 1, 256), default=max(1, os.cpu_count() or 1))
    c.add_argument("--seed-offset", type=int_in_range("--seed-offset", 0, 2**31 - 1), default=0,
                   help="episode i uses scene seed seed_offset + i")
    c.add_argument("--horizon", "-T", type=int_in_range("--horizon", T_MIN, T_MAX), default=None,
                   help=f"plan length in steps at 4 FPS (our world; default {DEFAULT_T}); robosuite's tasks have "
                        "their own T (80 stack_three, 100 nut_assembly and nut_assembly_round, 200 pick_place)")
    c.add_argument("--image-size", type=int_in_range("--image-size", 16, 512), default=84)
    c.add_argument("--framed", type=int_in_range("--framed", 0, 1_000_000), default=None,
                   help="our world: only episodes 0..N-1 keep a frame per step, the rest their initial frame alone "
                        "(about a third of the cost; they train what classifies from the initial image, not the "
                        "RSSM's prediction terms). Default: every episode")
    c.add_argument("--view-size", type=int_in_range("--view-size", 0, 1024), default=0,
                   help="our world: > 0 also keeps each episode's initial image at this many pixels square (the "
                        "plan-conditioned view; 256 reads the stacking blocks at about 1.7 mm per pixel), with the "
                        "camera's calibration and the arm's kinematics in the dataset's attributes")
    c.add_argument("--camera", default=None,
                   help="the robosuite world's camera of the images (default agentview; stack_three also has "
                        "workspaceview, a close view of the cubes)")
    c.add_argument("--final-view", action="store_true",
                   help="our world, with --view-size: also keep the settled final scene at that size (what an Oracle "
                        "reads: it shows the outcome)")
    c.add_argument("--pose-error-mm", type=non_negative_float("--pose-error-mm"), default=3.0,
                   help="std of the planner's block position estimate error in the plane (0 = exact)")
    c.add_argument("--pose-error-deg", type=non_negative_float("--pose-error-deg"), default=3.0,
                   help="std of the planner's block yaw estimate error (0 = exact)")
    c.add_argument("--ray", default=None, metavar="local|auto|ADDRESS",
                   help="simulate on Ray actors instead of a process pool: local starts a private cluster with "
                        "--workers CPUs for the run; auto joins the cluster of this machine (ray start) or "
                        "RAY_ADDRESS; else a cluster address. --workers actors, each one world")
    c.add_argument("--no-progress", action="store_true")
    return c


def collect_command(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: list[str]) -> int:
    if args.ray is not None and not args.ray.strip():
        parser.error("--ray: give local, auto or a cluster address (HOST:PORT or ray://HOST:PORT)")
    world_tasks = ROBOSUITE_TASKS if args.world == "robosuite" else TASKS
    if args.task not in world_tasks:
        parser.error(f"--task: {args.task!r} is not a task of the {args.world} world; one of {', '.join(world_tasks)}")
    if args.camera is not None and args.world != "robosuite":
        parser.error("--camera: our world's camera is fixed per task (sim_worker.scene); --camera is the robosuite "
                     "world's")
    if args.world == "robosuite" and (args.framed is not None or args.view_size or args.final_view):
        parser.error("--framed/--view-size/--final-view: our world's collection only, so far")
    if args.final_view and not args.view_size:
        parser.error("--final-view: the final scene is kept at the view's size; give --view-size too")
    if args.world == "robosuite":
        balance = _collect_robosuite(args, parser, argv)
    else:
        from planner_client.collect import CollectConfig, collect
        from sim_worker.perception import PoseErrorConfig

        error = PoseErrorConfig.from_mm_deg(args.pose_error_mm, args.pose_error_deg)
        config = CollectConfig(task=args.task, episodes=args.episodes, out=args.out, workers=args.workers,
                               seed_offset=args.seed_offset, horizon=args.horizon or DEFAULT_T,
                               image_size=args.image_size, pose_error=error, framed=args.framed,
                               view_size=args.view_size, final_view=args.final_view)
        balance = collect(config, progress=not args.no_progress, ray=args.ray)
    print(f"{args.out}: {balance['total']} episodes, {balance['success']} success / {balance['failure']} failure "
          f"(success rate {balance['success_rate']:.3f}); {balance['new_episodes']} new in {balance['seconds']} s")
    print(json.dumps(balance))
    return 0


def _collect_robosuite(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: list[str]) -> dict:
    """The robosuite collection, here if robosuite imports, else in the robosuite environment (exec)."""
    if args.horizon is not None:
        parser.error("--horizon: the robosuite world's tasks have a fixed T (80 stack_three, 100 nut_assembly "
                     "and nut_assembly_round, 200 pick_place)")
    _continue_in_robosuite_env(args, parser, argv)
    from planner_client.collect_robosuite import RobosuiteCollectConfig, collect_robosuite
    from robosuite_worker.world import UnknownCamera

    config = RobosuiteCollectConfig(task=args.task, episodes=args.episodes, out=args.out, workers=args.workers,
                                    seed_offset=args.seed_offset, image_size=args.image_size,
                                    camera=args.camera or RobosuiteCollectConfig.camera,
                                    pose_error_mm=args.pose_error_mm, pose_error_deg=args.pose_error_deg)
    try:
        return collect_robosuite(config, progress=not args.no_progress, ray=args.ray)
    except UnknownCamera as exc:
        parser.error(f"--{exc}")


def _postfix(records: list[dict]) -> dict[str, str]:
    """Running success rates for the progress bar."""
    n = len(records)
    post = {"tamp": f"{sum(r['tamp_success'] for r in records) / n:.2f}"}
    scored = [r for r in records if "firp_success" in r]
    if scored:
        post["firp"] = f"{sum(r['firp_success'] for r in scored) / len(scored):.2f}"
        post["accepted"] = f"{sum(r['firp_accepted'] for r in scored)}/{len(scored)}"
    with_oracle = [r for r in records if "oracle_success" in r]
    if with_oracle:
        post["oracle"] = f"{sum(r['oracle_success'] for r in with_oracle) / len(with_oracle):.2f}"
    return post


def main(argv: list[str] | None = None, prog: str = "python -m planner_client") -> int:
    parser = build_parser(prog)
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.command == "collect":
        return collect_command(args, parser, argv)
    from firp.core.tracing import TracingConfigError, configure_tracing
    from planner_client.transport import TRACING_SERVICE_NAME

    try:  # a bad OTEL_* variable is a usage error, named before any trial runs
        configure_tracing(TRACING_SERVICE_NAME)
    except TracingConfigError as exc:
        parser.error(str(exc))
    return run_command(args, parser, argv)


def _world_planner(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: list[str]):
    """The world's planner; for robosuite's world the run continues in its environment (exec) if need be."""
    world_tasks = ROBOSUITE_TASKS if args.world == "robosuite" else TASKS
    args.task = args.task or world_tasks[0]
    if args.task not in world_tasks:
        parser.error(f"--task: {args.task!r} is not a task of the {args.world} world; one of {', '.join(world_tasks)}")
    if args.world == "mujoco":
        from planner_client.tamp import PlannerConfig, TampPlanner

        return TampPlanner(PlannerConfig(horizon=args.horizon or DEFAULT_T))
    if args.horizon is not None:
        parser.error("--horizon: the robosuite world's tasks have a fixed T (80 stack_three, 100 nut_assembly "
                     "and nut_assembly_round, 200 pick_place)")
    _continue_in_robosuite_env(args, parser, argv)
    from planner_client.robosuite_tamp import RobosuiteTampPlanner

    return RobosuiteTampPlanner()


def _continue_in_robosuite_env(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """Unless robosuite imports here, re-run this command in its environment."""
    from planner_client.robosuite_env import RobosuiteMissing, has_robosuite, robosuite_python

    if has_robosuite():
        return
    try:
        python = robosuite_python()
    except RobosuiteMissing as exc:
        parser.error(str(exc))
    print(f"{args.command} --world robosuite: running in the robosuite environment ({python})", file=sys.stderr)
    os.execv(str(python), [str(python), "-m", "planner_client", *argv])


def _ray_trials(args: argparse.Namespace, parser: argparse.ArgumentParser):
    """``--ray``'s settings, or None; refuses what does not run on Ray actors, naming the flag."""
    if args.ray is None:
        return None
    from planner_client.ray_trials import RayTrials

    if not args.ray.strip():
        parser.error("--ray: give local, auto or a cluster address (HOST:PORT or ray://HOST:PORT)")
    if args.sim:
        parser.error("--ray: the trials run our world inside the Ray actors; drop --sim (or drop --ray to use "
                     "running sim workers)")
    if args.world != "mujoco":
        parser.error("--ray: only our world (--world mujoco) runs inside Ray actors; robosuite's runs in its own "
                     "environment: use --parallel with launched robosuite workers")
    if args.record is not None:
        parser.error("--record writes the executions on this machine's disk; it does not run with --ray")
    if args.ray not in ("local", "auto") and not args.no_score and not args.service:
        parser.error(f"--ray {args.ray}: the actors on the cluster's nodes call the scoring service, so give "
                     "--service with a URL they reach (a launched service listens on this machine's loopback)")
    return RayTrials(address=args.ray, actors=args.parallel or 1)


def run_command(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: list[str]) -> int:
    ray = _ray_trials(args, parser)  # before the world's planner: robosuite's would hand the run to its environment
    planner = _world_planner(args, parser, argv)
    if args.resume and args.out is None:
        parser.error("--resume needs --out: the run file to continue")
    if args.explore and args.no_score:
        parser.error("--explore picks the candidates the ensemble is least sure of: it needs scores, drop --no-score")
    if args.bundle is not None and args.service and not args.no_score:
        parser.error("--bundle is for the scoring service this run launches; with --service the running service "
                     "has loaded its own bundle")
    from tqdm import tqdm

    from firp.core.bundle_format import MissingBundle
    from planner_client.loop import RunConfig, RunSetupError, check_resumable, read_records, run_identity, run_trials
    from planner_client.processes import ServerStartError
    from planner_client.report import markdown, summarise, write_report
    from planner_client.session import ServicePlan, open_services
    from planner_client.transport import ServiceError

    out = args.out or Path(f"runs/{args.task}-{time.strftime('%Y%m%d-%H%M%S')}.jsonl")
    if out.exists() and not args.resume:
        parser.error(f"--out {out} exists; pass --resume to continue it or choose another file")
    config = RunConfig(task=args.task, trials=args.trials, seed=args.seed, max_iterations=args.max_iterations,
                       oracle=not args.no_oracle, out=out, resume=args.resume, threshold=args.threshold,
                       record=args.record, world=args.world, rule=args.rule, alpha=args.alpha,
                       compare_rules=not args.no_compare_rules, explore=args.explore,
                       replan_on_uninformative=args.replan_on_uninformative)
    plan = ServicePlan(task=args.task, out_dir=out.parent, sim_url=args.sim, service_url=args.service,
                       bundle=args.bundle, score=not args.no_score, api_key=args.api_key,
                       ready_timeout=args.ready_timeout, world=args.world, parallel=args.parallel or 1,
                       launch_sims=ray is None)
    if plan.sim_urls and args.parallel is not None and args.parallel != len(plan.sim_urls):
        parser.error(f"--parallel: with --sim one trial runs on each given sim worker at a time; {args.parallel} "
                     f"asked, {len(plan.sim_urls)} URL(s) given: give {args.parallel} URLs or drop --parallel")
    try:
        plan.bundle_to_launch()
    except MissingBundle as exc:
        parser.error(str(exc))
    out.parent.mkdir(parents=True, exist_ok=True)
    records = [r for r in read_records(out) if r["trial"] < args.trials] if args.resume else []
    if records:  # refuse other settings now, not after launching the services (the model is checked later)
        flags = run_identity(config, planner, None, scoring=not args.no_score)
        try:
            check_resumable(read_records(out), flags, out, ignore=("model",))
        except RunSetupError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_USAGE
    try:
        with open_services(plan) as services:
            bar = tqdm(total=args.trials, initial=len(records), desc=f"{args.task} trials", unit="trial")
            try:
                if ray is not None and services.scorer is not None:
                    ray = replace(ray, service_url=services.scorer.base_url, api_key=args.api_key)
                for record in run_trials(config, services.sim, planner, services.scorer, services.sims, ray=ray):
                    records.append(record)
                    bar.set_postfix(_postfix(records), refresh=False)
                    bar.update(1)
            finally:
                bar.close()
            if services.sim_restarts:
                print(f"the sim worker was restarted {services.sim_restarts} time(s); no trial was lost",
                      file=sys.stderr)
            if services.service_restarts:
                print(f"the scoring service was restarted {services.service_restarts} time(s); no trial was lost",
                      file=sys.stderr)
    except (FileExistsError, RunSetupError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (ServiceError, ServerStartError) as exc:
        print(f"error: {exc}\n{len(records)} trial(s) are in {out}; continue with --resume --out {out}",
              file=sys.stderr)
        return EXIT_SERVICE
    except KeyboardInterrupt:
        print(f"\ninterrupted: {len(records)} trial(s) are in {out}; continue with --resume --out {out}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    summary = summarise([r for r in read_records(out) if r["trial"] < args.trials])
    paths = write_report(summary, out)
    print("\n" + markdown(summary))
    print(f"trial records: {out}")
    print("summary: " + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
