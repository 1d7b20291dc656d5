"""Where the rounds' candidates' AUC plateaus: every bundle of the rounds on the same new scenes, paired.

Each round of ``experiments.learning_rounds`` measures the bundle in use on *its own* new seeds, so two
rounds' AUCs differ by the draw of scenes as much as by the bundle (about ±0.03 over 100 scenes). Here
every bundle the rounds made -- the shipped one, each refresh, promoted or kept -- scores every candidate
of one recording that none of them trained on (the final run's, all candidates executed), and each is
compared with the first on the same scenes: the candidates' ROC AUC, the balanced accuracy at its own
threshold, and the loop replayed (paper's rule, ranking), with paired bootstrap intervals over scenes.

    python -m experiments.bundle_generations --rounds runs/rounds-stacking --first models/stacking \\
        --evaluation runs/rounds-stacking/final --report docs/results/bundle_generations_stacking
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from experiments.exploration_value import (
    Evaluation,
    _ensemble_scores,
    difference_cell,
    _episode_attrs,
    measure,
)
from firp.bundle import load_bundle
from firp.core.bundle_format import bundle_version
from firp.features import DEFAULT_CACHE_DIR
from firp.refresh import load_pool

__all__ = ["main"]


def generations(rounds: Path, first: Path) -> list[tuple[str, Path]]:
    """(name, bundle) of the shipped bundle, then each round's refresh in order, with its verdict."""
    out = [("shipped", first)]
    k = 0
    while (rounds / f"round-{k}" / "bundle" / "manifest.json").exists():
        report = rounds / f"round-{k}" / "refresh.json"
        verdict = json.loads(report.read_text()).get("promoted") if report.exists() else None
        out.append((f"refresh after round {k} ({'promoted' if verdict else 'kept'})", rounds / f"round-{k}" / "bundle"))
        k += 1
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=Path, required=True, help="the --out folder of experiments.learning_rounds")
    parser.add_argument("--first", type=Path, required=True, help="the bundle the rounds started with")
    parser.add_argument("--evaluation", type=Path, required=True,
                        help="a run directory recorded with --explore 6 on seeds no bundle trained on")
    parser.add_argument("--resamples", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--report", type=Path, required=True, help="path stem of the .json and .md written")
    args = parser.parse_args(argv)
    if not (args.evaluation / "executions.h5").exists():
        parser.error(f"--evaluation {args.evaluation}: no executions.h5 (firp run --record DIR writes it)")
    torch.set_num_threads(args.threads)
    rows, reference, evaluation = [], None, None
    for name, path in generations(args.rounds, args.first):
        bundle = load_bundle(path)
        pool = load_pool([args.evaluation / "executions.h5"], bundle, DEFAULT_CACHE_DIR, progress=False)
        if evaluation is None:
            attrs = _episode_attrs(args.evaluation / "executions.h5", pool.data.demo_names)
            evaluation = Evaluation([a["scene_id"] for a in attrs], np.asarray([a["candidate_index"] for a in attrs]),
                                    pool.data.labels.numpy() > 0.5)
        scores = _ensemble_scores(list(bundle.models), pool.data)
        row = {"bundle": name, "path": str(path), "version": bundle_version(bundle.path, bundle.manifest),
               **measure(evaluation, scores, bundle.threshold, reference, args.resamples, 0, key="versus_shipped")}
        rows.append(row)
        reference = reference or {"scores": scores, "threshold": bundle.threshold}
        print(json.dumps({k: v for k, v in row.items() if k != "versus_shipped"}), flush=True)
    assert evaluation is not None
    n_scenes = len(set(evaluation.scenes))

    def diff(row: dict, key: str, scale: float = 1.0, digits: int = 3) -> str:
        return difference_cell(row, "versus_shipped", key, scale, digits)

    lines = [f"Every bundle of `{args.rounds}` on every candidate of `{args.evaluation}` ({len(evaluation.labels)} "
             f"candidates, {n_scenes} scenes, none trained on).", "",
             "| bundle | version | candidates' AUC | vs shipped [95%] | balanced accuracy | TAMP + FIRP (paper's rule) "
             "| vs shipped [95%] | ranking | vs shipped [95%] |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['bundle']} | {r['version']} | {r['candidate_auc']:.3f} | {diff(r, 'candidate_auc')} | "
                     f"{r['balanced_accuracy']:.3f} | {r['loop_success']:.0%} | {diff(r, 'loop_success', 100, 0)} | "
                     f"{r['rank_success']:.0%} | {diff(r, 'rank_success', 100, 0)} |")
    text = "\n".join(lines) + "\n"
    result = {"rounds": str(args.rounds), "evaluation": str(args.evaluation), "evaluation_scenes": n_scenes,
              "evaluation_candidates": len(evaluation.labels), "rows": rows,
              "command": "python -m experiments.bundle_generations " + " ".join(argv or sys.argv[1:])}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.with_suffix(".json").write_text(json.dumps(result, indent=1))
    args.report.with_suffix(".md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
