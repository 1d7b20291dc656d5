"""The compose smoke run's last step: compare the trials run in containers with the same trials run
without them (and on three sim worker replicas), the episodes a Ray cluster of containers collected
with the same collection without containers, and write what the run measured (report.json, report.md).

The comparison is strict on everything discrete (seeds, the bundle, every plan picked and every
outcome) and allows the scores a tolerance of 1e-6: the images install the same pinned wheels, so
any larger difference is a real defect (another torch, another renderer, another image pipeline).
Exit 1 when the runs differ or a record is missing, naming the trial and the field.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

SCORE_TOLERANCE = 1e-6
# Every discrete field of a trial record the two runs must agree on.
EXACT_FIELDS = ("seed", "task", "firp_rule", "firp_success", "firp_accepted", "firp_iterations", "firp_order",
                "tamp_success", "oracle_success", "oracle_order", "rules")


def read_records(path: Path) -> list[dict]:
    if not path.is_file():
        raise SystemExit(f"compare: {path} does not exist")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def compare(container: list[dict], host: list[dict], trials: int) -> tuple[list[str], float]:
    """The differences (empty when the runs agree) and the largest score difference."""
    problems: list[str] = []
    if len(container) != trials or len(host) != trials:
        problems.append(f"expected {trials} trial records, the container run has {len(container)}, "
                        f"the run without containers {len(host)}")
    largest = 0.0
    for c, h in zip(container, host):
        trial = c.get("trial")
        if c["run"]["model"] != h["run"]["model"]:
            problems.append(f"trial {trial}: bundle {c['run']['model']} != {h['run']['model']}")
        for field in EXACT_FIELDS:
            if c.get(field) != h.get(field):
                problems.append(f"trial {trial}: {field} {c.get(field)!r} != {h.get(field)!r}")
        c_scores, h_scores = c.get("candidate_scores") or {}, h.get("candidate_scores") or {}
        if not c_scores or set(c_scores) != set(h_scores):
            problems.append(f"trial {trial}: candidate_scores name other plans: {sorted(c_scores)} vs {sorted(h_scores)}")
            continue
        for plan, score in c_scores.items():
            difference = abs(score - h_scores[plan])
            largest = max(largest, difference)
            if difference > SCORE_TOLERANCE:
                problems.append(f"trial {trial}: score of {plan} {score!r} != {h_scores[plan]!r}")
    return problems, largest


def compare_datasets(ray: Path, host: Path) -> tuple[list[str], dict]:
    """The differences between two collections of the same episodes (empty: bit-identical content), and
    what the Ray one holds."""
    from firp.core.episodes import EpisodeDataset

    for path in (ray, host):
        if not path.is_file():
            return [f"no dataset at {path}"], {}
    with EpisodeDataset(ray) as a, EpisodeDataset(host) as b:
        facts = {"episodes": len(a), "successes": int(a.success_labels().sum()), "content_hash": a.content_hash()}
        problems = []
        if len(a) != len(b):
            problems.append(f"the Ray collection has {len(a)} episodes, the one without containers {len(b)}")
        elif a.content_hash() != b.content_hash():
            problems.append(f"the Ray collection's content {a.content_hash()[:12]} differs from the one without "
                            f"containers {b.content_hash()[:12]}")
    return problems, facts


def parse_pairs(items: list[str]) -> dict[str, list[str]]:
    """``name=a:b:c`` items as {name: [a, b, c]}."""
    return {item.split("=", 1)[0]: item.split("=", 1)[1].split(":") for item in items}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--container", type=Path, required=True, help="trial records of the container run")
    parser.add_argument("--host", type=Path, required=True, help="trial records of the run without containers")
    parser.add_argument("--trials", type=int, required=True)
    parser.add_argument("--engine", required=True)
    parser.add_argument("--base", required=True, help="the base image the images were built on")
    parser.add_argument("--images", nargs="+", default=[], help="name=size_mb:build_s")
    parser.add_argument("--servers", nargs="+", default=[], help="name=ready_s:stop_s:exit_code")
    parser.add_argument("--planner-seconds", type=int, required=True, help="the planner container's run, start to exit")
    parser.add_argument("--replicas", type=Path, help="trial records of the same trials on three sim worker replicas")
    parser.add_argument("--replicas-seconds", type=int, help="the replicas' planner run, start to exit")
    parser.add_argument("--ray-dataset", type=Path, help="the episodes the Ray profile collected")
    parser.add_argument("--host-dataset", type=Path, help="the same episodes collected without containers")
    parser.add_argument("--ray-seconds", type=int, help="the Ray profile's run, up to exit")
    parser.add_argument("--seconds", type=int, required=True, help="the smoke run's wall time so far")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    summary = args.container.with_name(args.container.stem + ".summary.json")
    if not summary.is_file() or not json.loads(summary.read_text()).get("trials"):
        print(f"compare: the container run wrote no summary ({summary})", file=sys.stderr)
        return 1
    container, host = read_records(args.container), read_records(args.host)
    problems, largest = compare(container, host, args.trials)
    if args.replicas is not None:  # one trial per worker at a time: every record as the one worker's
        replica_problems, replica_largest = compare(read_records(args.replicas), container, args.trials)
        problems += [f"replicas: {p}" for p in replica_problems]
        largest = max(largest, replica_largest)
    ray = {}
    if args.ray_dataset is not None:
        ray_problems, ray = compare_datasets(args.ray_dataset, args.host_dataset)
        problems += [f"ray: {p}" for p in ray_problems]
        ray["seconds"] = args.ray_seconds

    images = {name: {"size_mb": int(v[0]), "build_s": int(v[1])} for name, v in parse_pairs(args.images).items()}
    servers = {name: {"ready_s": float(v[0]), "stop_s": int(v[1]), "exit_code": int(v[2])}
               for name, v in parse_pairs(args.servers).items()}
    report = {
        "engine": args.engine, "base_image": args.base, "trials": args.trials, "planner_run_s": args.planner_seconds,
        "seconds": args.seconds,
        "images": images, "servers": servers,
        "scores_compared": sum(len(r.get("candidate_scores") or {}) for r in container),
        "largest_score_difference": largest, "score_tolerance": SCORE_TOLERANCE,
        "firp_successes": [r["firp_success"] for r in container], "equal": not problems, "differences": problems,
        "replicas": None if args.replicas is None else {"workers": 3, "planner_run_s": args.replicas_seconds},
        "ray": ray or None,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = [f"# Compose smoke run ({args.engine}, base {args.base})", "",
             "| image | size (MB) | build (s) | ready after `up` (s) | `stop` (s) | exit code |", "|---|---|---|---|---|---|"]
    for name, image in images.items():
        server = servers.get(name, {})
        lines.append(f"| {name} | {image['size_mb']} | {image['build_s']} | {server.get('ready_s', '–')} | "
                     f"{server.get('stop_s', '–')} | {server.get('exit_code', '–')} |")
    lines += ["", f"`compose run --rm planner run --trials {args.trials}`: {args.planner_seconds} s, start to exit.",
              "", f"{args.trials} trials, {report['scores_compared']} plan scores compared with the same trials run "
              f"without containers: largest difference {largest:.3g} (tolerance {SCORE_TOLERANCE:g}); "
              f"{'equal' if not problems else 'DIFFERENT'}. Wall time {args.seconds} s."]
    if args.replicas is not None:
        lines += ["", f"The same {args.trials} trials on three sim worker replicas (`--profile replicas`, "
                  f"`planner_replicas`): {args.replicas_seconds} s, every record compared with the one-worker run's."]
    if ray:
        lines += ["", f"`--profile ray` (a head and two workers, one actor each): {ray.get('episodes')} episodes "
                  f"({ray.get('successes')} successes) in {ray['seconds']} s, content {ray.get('content_hash', '')[:12]}, "
                  "compared with the same collection without containers."]
    lines += [f"- {problem}" for problem in problems]
    (args.out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
