"""Learning from deployment, measured: rounds of trials -> record -> refresh -> live swap, on new seeds.

One scoring service runs for the whole experiment. Round ``k`` (scene seeds ``seed + k * trials`` on,
never used for a dataset or an earlier round):

1. ``firp run --record`` against the running service with the bundle in use (``--explore K`` executes the
   candidates the ensemble is least sure of besides the rules' picks, so every round's labels land where
   it is weakest and the candidates' AUC is measured on every candidate);
2. ``firp refresh`` on the collected dataset plus every round's recorded executions so far, judged against
   the bundle in use on held-out recorded scenes;
3. a promoted bundle is hot-swapped into the running service (``--swap``) and scores the next round.

After the last refresh a final run on new seeds measures the bundle the rounds ended with. Per run: the
loop's success with the paper's rule, the ranking rule's, TAMP alone's and the oracle's on the same
scenes; the candidates' ROC AUC (every executed candidate's score against its label); the model version
and whether its evidence let the loop replan. A table (JSON, Markdown), a plot, and the commands each
step ran. Every step resumes: a round whose files exist is not run again.

    MUJOCO_GL=egl python -m experiments.learning_rounds --task stacking --bundle models/stacking \\
        --data data/stacking.h5 --rounds 3 --trials 100 --seed 300000 --out runs/rounds-stacking \\
        --report docs/results/learning_rounds_stacking
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from planner_client.launcher import Launcher
from planner_client.loop import read_records

EXIT_KEPT = 3  # firp refresh: the bundle in use stays
EXIT_REFUSED = 2  # firp refresh: the data cannot judge a refresh (said on its last line)


def _candidate_pairs(records: list[dict]) -> list[tuple[list[float], list[bool]]]:
    """Per trial (one scene), the executed candidates' scores and labels."""
    pairs = []
    for r in records:
        scored = r.get("candidate_scores", {})
        outcomes = {k: bool(v) for k, v in (r.get("candidate_outcomes") or {}).items() if k in scored}
        pairs.append(([scored[k] for k in outcomes], list(outcomes.values())))
    return pairs


def candidate_auc(records: list[dict]) -> float | None:
    """ROC AUC of the candidates' scores against their labels, pooled over the run's trials (every
    candidate executed; ``--explore`` makes that all of a scene's plannable ones)."""
    from sklearn.metrics import roc_auc_score

    pairs = _candidate_pairs(records)
    scores = [s for ss, _ in pairs for s in ss]
    labels = [y for _, ys in pairs for y in ys]
    if len(set(labels)) < 2:
        return None
    return float(roc_auc_score(labels, scores))


def candidate_auc_interval(records: list[dict], resamples: int = 1000, level: float = 0.95,
                           seed: int = 0) -> list[float] | None:
    """Percentile bootstrap interval of :func:`candidate_auc` over scenes (a scene's candidates share an
    image and its physics, so whole trials are drawn): how far two runs' AUCs on different seeds may lie
    apart by the draw of scenes alone."""
    from sklearn.metrics import roc_auc_score

    pairs = _candidate_pairs(records)
    if candidate_auc(records) is None:
        return None
    rng = np.random.default_rng(seed)
    values: list[float] = []
    for _ in range(50 * resamples):  # bounded: a draw of one class only is drawn again
        if len(values) == resamples:
            break
        draw = [pairs[i] for i in rng.integers(0, len(pairs), len(pairs))]
        labels = [y for _, ys in draw for y in ys]
        if len(set(labels)) == 2:
            values.append(float(roc_auc_score(labels, [s for ss, _ in draw for s in ss])))
    tail = (1.0 - level) / 2.0
    return [float(np.quantile(values, tail)), float(np.quantile(values, 1.0 - tail))]


def success_interval(successes: int, n: int, level: float = 0.95) -> list[float]:
    """Wilson score interval of a success rate (the rows' rates are over 100 scenes or so)."""
    from statistics import NormalDist

    if n == 0:
        return [float("nan"), float("nan")]
    z = NormalDist().inv_cdf(0.5 + level / 2.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [max(0.0, float(centre - half)), min(1.0, float(centre + half))]


def run_row(name: str, records: list[dict]) -> dict:
    """What one run measured."""
    def rate(values: list[bool]) -> float:
        return float(np.mean(values)) if values else float("nan")

    model = records[0]["run"].get("model") or {}
    rules = [r.get("firp_rule") for r in records]
    return {"run": name, "trials": len(records), "seeds": [records[0]["seed"], records[-1]["seed"]],
            "model_version": model.get("version"),
            "replans": rules.count("tamp_first") == 0,  # an uninformative bundle executes TAMP's first plan
            "loop_success": rate([r["firp_success"] for r in records]),
            "rank_success": rate([r["rules"]["rank"]["success"] for r in records if "rules" in r]),
            "tamp_success": rate([r["tamp_success"] for r in records]),
            "oracle_success": rate([r["oracle_success"] for r in records if "oracle_success" in r]),
            "loop_success_interval": success_interval(sum(r["firp_success"] for r in records), len(records)),
            "candidate_auc": candidate_auc(records), "candidate_auc_interval": candidate_auc_interval(records),
            "candidates_executed": int(sum(len(r.get("candidate_outcomes") or {}) for r in records))}


def _step(command: list[str], log: Path, ok: tuple[int, ...] = (0,)) -> int:
    """Run one step's command (printed, logged), returning its exit code; raise on any other."""
    print("$ " + " ".join(command), flush=True)
    with log.open("a") as sink:
        code = subprocess.run(command, stdout=sink, stderr=subprocess.STDOUT).returncode
    if code not in ok:
        raise RuntimeError(f"{' '.join(command[2:4])} exited {code}; its output: {log}")
    return code


def plot(rows: list[dict], path: Path, task: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(rows))
    fig, left = plt.subplots(figsize=(7, 4))
    for key, label, style in [("oracle_success", "oracle", "k:"), ("rank_success", "TAMP + FIRP, ranking", "g--"),
                              ("loop_success", "TAMP + FIRP, paper's rule", "b-o"), ("tamp_success", "TAMP alone", "r-")]:
        left.plot(x, [100 * r[key] for r in rows], style, label=label)
    left.set_ylabel("success (%)")
    left.set_xticks(x, [r["run"] for r in rows])
    right = left.twinx()
    auc = np.array([r["candidate_auc"] if r["candidate_auc"] is not None else np.nan for r in rows])
    bands = np.array([r.get("candidate_auc_interval") or [np.nan, np.nan] for r in rows])
    right.errorbar(x, auc, yerr=[auc - bands[:, 0], bands[:, 1] - auc], fmt="m-s", capsize=3,
                   label="candidates' ROC AUC (95% over scenes)")
    right.set_ylabel("candidates' ROC AUC")
    lines = left.get_legend_handles_labels()[0] + right.get_legend_handles_labels()[0]
    labels = left.get_legend_handles_labels()[1] + right.get_legend_handles_labels()[1]
    left.legend(lines, labels, loc="lower right", fontsize=8)
    left.set_title(f"{task}: learning from deployment, each run on new seeds")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(rows: list[dict], refreshes: list[dict], commands: list[str]) -> str:
    def pct(v: float) -> str:
        return "—" if v != v else f"{100 * v:.0f}%"

    def interval(v: list[float] | None, fmt) -> str:
        return "" if not v else f" [{fmt(v[0])}, {fmt(v[1])}]"

    lines = ["| run | seeds | bundle version | replans | TAMP + FIRP (paper's rule) [95%] | ranking | TAMP alone | oracle "
             "| candidates' AUC [95%] | candidates executed |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        auc = ("—" if r["candidate_auc"] is None else
               f"{r['candidate_auc']:.3f}{interval(r.get('candidate_auc_interval'), lambda v: f'{v:.3f}')}")
        loop = pct(r["loop_success"]) + interval(r.get("loop_success_interval"), pct)
        lines.append(f"| {r['run']} | {r['seeds'][0]}–{r['seeds'][1]} | {r['model_version']} | "
                     f"{'yes' if r['replans'] else 'no (uninformative: TAMP first)'} | {loop} | "
                     f"{pct(r['rank_success'])} | {pct(r['tamp_success'])} | {pct(r['oracle_success'])} | {auc} | "
                     f"{r['candidates_executed']} |")
    lines += ["", "| refresh | held-out episodes (scenes) | current | refreshed | difference [95% interval] | verdict |",
              "|---|---|---|---|---|---|"]
    for k, f in enumerate(refreshes):
        c = f["paired"]
        if c is None:
            lines.append(f"| after round {k} | — | — | — | — | kept: {f['why']} |")
            continue
        lines.append(f"| after round {k} | {c['n_episodes']} ({c['n_scenes']}) | {c['current_balanced_accuracy']:.3f} | "
                     f"{c['new_balanced_accuracy']:.3f} | {c['difference']:+.3f} [{c['interval'][0]:+.3f}, "
                     f"{c['interval'][1]:+.3f}] | {'promoted' if f['promoted'] else 'kept'}: {f['why']} |")
    return "\n".join(lines + ["", "Commands, in order:", "", "```bash", *commands, "```", ""])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="stacking")
    parser.add_argument("--bundle", type=Path, required=True, help="the bundle the first round starts with")
    parser.add_argument("--data", type=Path, required=True, help="the collected dataset every refresh trains on")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--trials", type=int, default=100, help="trials per run")
    parser.add_argument("--seed", type=int, default=300_000)
    parser.add_argument("--explore", type=int, default=6)
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=20, help="refresh epochs per member")
    parser.add_argument("--horizon", type=int, default=None, help="plan length T (default: the task's)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--report", type=Path, required=True, help="path stem of the .json, .md and .png written")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    python = sys.executable
    state_path = args.out / "rounds.json"
    state = json.loads(state_path.read_text()) if state_path.exists() else {"bundle": str(args.bundle)}
    rows, refreshes, commands = [], [], []
    started = time.perf_counter()
    with Launcher(args.out / "service", bundle=Path(state["bundle"]), sim=False, ready_timeout=300) as services:
        url = services.service_server.url
        recorded: list[Path] = []
        ran = False  # whether this call ran any step (else it only reads the files back)
        in_use = str(args.bundle)  # the bundle each round ran with: the last promoted refresh before it
        for k in range(args.rounds + 1):
            final = k == args.rounds
            run_dir = args.out / ("final" if final else f"round-{k}")
            run_dir.mkdir(exist_ok=True)
            trials = run_dir / "trials.jsonl"
            run = [python, "-m", "planner_client", "run", "--task", args.task, "--trials", str(args.trials),
                   "--seed", str(args.seed + k * args.trials), "--service", url, "--parallel", str(args.parallel),
                   "--explore", str(args.explore), "--out", str(trials), "--record", str(run_dir),
                   *(["--horizon", str(args.horizon)] if args.horizon else [])]
            if not (run_dir / "done").exists():
                _step(run + (["--resume"] if trials.exists() else []), run_dir / "run.log")
                ran = True
                (run_dir / "done").touch()
            commands.append(" ".join(["firp", *run[3:]]).replace(url, "$SERVICE"))
            records = read_records(trials)
            rows.append(run_row("after the rounds" if final else f"round {k}", records))
            print(json.dumps(rows[-1]), flush=True)
            if final:
                break
            recorded.append(run_dir / "executions.h5")
            report = run_dir / "refresh.json"
            refresh = [python, "-m", "firp.refresh", "--bundle", in_use, "--data", str(args.data),
                       *[a for p in recorded for a in ("--data", str(p))], "--out", str(run_dir / "bundle"),
                       "--report", str(report), "--epochs", str(args.epochs), "--threads", str(args.threads),
                       "--seed", str(k), "--swap", url, "--no-progress"]
            if not report.exists():
                code = _step(refresh, run_dir / "refresh.log", ok=(0, EXIT_KEPT, EXIT_REFUSED))
                ran = True
                if code == EXIT_REFUSED:  # e.g. held-out scenes of one class: nothing to judge on, keep
                    why = (run_dir / "refresh.log").read_text().strip().splitlines()[-1]
                    report.write_text(json.dumps({"promoted": False, "why": f"refresh refused: {why}", "paired": None}))
            commands.append(" ".join(["firp refresh", *refresh[3:]]).replace(url, "$SERVICE"))
            outcome = json.loads(report.read_text())
            refreshes.append(outcome)
            if outcome["promoted"]:
                in_use = str(run_dir / "bundle")
                following = args.out / ("final" if k + 1 == args.rounds else f"round-{k + 1}")
                if state["bundle"] != in_use and not (following / "done").exists():
                    state["bundle"] = in_use  # what the service serves when a later call resumes here
                    state_path.write_text(json.dumps(state))
    seconds = round(time.perf_counter() - started)
    previous = args.report.with_suffix(".json")
    if not ran and previous.exists():  # a report written again from the files keeps the experiment's own time
        seconds = json.loads(previous.read_text()).get("seconds", seconds)
    result = {"task": args.task, "rows": rows, "refreshes": [{k: v for k, v in f.items() if k != "split"}
                                                              for f in refreshes],
              "commands": commands, "seconds": seconds,
              "command": "python -m experiments.learning_rounds " + " ".join(argv or sys.argv[1:])}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.with_suffix(".json").write_text(json.dumps(result, indent=1))
    args.report.with_suffix(".md").write_text(markdown(rows, refreshes, commands))
    plot(rows, args.report.with_suffix(".png"), args.task)
    print(markdown(rows, refreshes, commands))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
