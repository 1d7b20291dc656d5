"""What exploration's labels are worth: refreshes trained on what a recording would hold with and without
``--explore``, judged on the same new scenes.

A recording run with ``--explore 6`` executed every plannable candidate of every scene. The simulator is
deterministic and every execution starts from the episode's initial state, so a candidate's label does not
depend on which others ran: the recording a run *without* exploration -- or with fewer explored candidates --
would have made is a subset of it, chosen from the run's own records. Policies (per scene):

* ``deployed``: the plan the loop executed under the paper's rule (``firp_order``), the one execution a
  deployment makes and records without exploration;
* ``least-sure-K``: that plan plus the ``K`` other candidates whose score (by the bundle that scored the run)
  lies nearest its threshold -- what ``--explore K`` adds;
* ``random-K``: that plan plus ``K`` other candidates drawn at random -- as many labels, chosen blind, to tell
  the choice of labels from their number;
* ``all``: every executed candidate.

Each policy refreshes the same bundle the same way (``firp refresh``'s recipe: every member warm-started and
trained again on the collected dataset plus the policy's episodes; one validation split of scenes shared by
all policies), and each refreshed ensemble scores every candidate of an evaluation recording made on other,
new seeds (all candidates executed): the candidates' ROC AUC, the balanced accuracy at the ensemble's
threshold, and the loop replayed on those scenes -- the paper's rule (the first candidate in the planner's
order whose score reaches the threshold, else the last) and the ranking rule (the highest) -- each with a
bootstrap interval over scenes of its difference from ``deployed``. The bundle in use, not refreshed, is the
first row.

    MUJOCO_GL=egl python -m experiments.exploration_value --bundle models/stacking --data data/stacking.h5 \\
        --recording runs/rounds-stacking/round-0 --evaluation runs/rounds-stacking/final \\
        --out runs/exploration-stacking --report docs/results/exploration_value_stacking
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from firp.bundle import load_bundle
from firp.core.decisions import first_accepted, highest
from firp.core.episodes import EpisodeDataset
from firp.features import DEFAULT_CACHE_DIR
from firp.metrics import balanced_accuracy, choose_threshold
from firp.refresh import load_pool, scene_split
from firp.train import TrainConfig, predict, train_model
from planner_client.loop import read_records

__all__ = ["Candidate", "chosen_by_policy", "difference_cell", "main", "policies", "replay"]

Candidate = tuple[str, tuple]  # (scene id, the candidate's description as a tuple)


def _as_tuple(value) -> tuple:
    return tuple(value) if isinstance(value, (list, tuple)) else (value,)


def _recorded_candidate(attrs: dict) -> Candidate:
    """A recorded episode's (scene, candidate): the recorder writes the candidate as ``str(description)``."""
    text = attrs["candidate"]
    try:
        described = ast.literal_eval(text)
    except (ValueError, SyntaxError):  # a robosuite choice's label is a plain string
        described = text
    return attrs["scene_id"], _as_tuple(described)


def _scene_of(record: dict) -> str:
    return f"{record['task']}/{record['seed']}"


def policies(ks: list[int]) -> list[str]:
    """The policies compared, ``deployed`` first (the reference of every difference)."""
    return ["deployed", *[f"{kind}-{k}" for k in ks for kind in ("least-sure", "random")], "all"]


def chosen_by_policy(records: list[dict], policy: str, seed: int = 0) -> set[Candidate]:
    """The (scene, candidate) pairs ``policy`` would have executed and recorded (see the module docstring)."""
    rng = np.random.default_rng(seed)
    chosen: set[Candidate] = set()
    for r in records:
        scene = _scene_of(r)
        executed = {_as_tuple(json.loads(key)): key for key in (r.get("candidate_outcomes") or {})}
        deployed = _as_tuple(r["firp_order"])
        if policy == "all":
            chosen |= {(scene, c) for c in executed}
            continue
        chosen.add((scene, deployed))
        if policy == "deployed":
            continue
        kind, k = policy.rsplit("-", 1)
        others = [c for c in executed if c != deployed]
        if kind == "least-sure":
            threshold = float(r["service_threshold"])
            others.sort(key=lambda c: abs(r["candidate_scores"][executed[c]] - threshold))
        elif kind == "random":
            others = [others[i] for i in rng.permutation(len(others))]
        else:
            raise ValueError(f"unknown policy {policy!r}")
        chosen |= {(scene, c) for c in others[: int(k)]}
    return chosen


@dataclass
class Evaluation:
    """Every candidate of the evaluation recording, in the planner's order within each scene."""

    scenes: list[str]  # per episode
    order: np.ndarray  # (N,) candidate_index: the planner's order
    labels: np.ndarray  # (N,) bool


def replay(evaluation: Evaluation, scores: np.ndarray, threshold: float) -> dict[str, np.ndarray]:
    """Per scene (sorted names), the label of the plan each rule executes on these scores."""
    out: dict[str, list[bool]] = {"threshold": [], "rank": []}
    names = sorted(set(evaluation.scenes))
    scene_of = np.asarray(evaluation.scenes)
    for name in names:
        idx = np.flatnonzero(scene_of == name)
        idx = idx[np.argsort(evaluation.order[idx], kind="stable")]
        out["threshold"].append(bool(evaluation.labels[idx[first_accepted(scores[idx], threshold)[0]]]))
        out["rank"].append(bool(evaluation.labels[idx[highest(scores[idx])]]))
    return {rule: np.asarray(v) for rule, v in out.items()}


def _auc(labels: np.ndarray, scores: np.ndarray) -> float:
    from sklearn.metrics import roc_auc_score

    return float(roc_auc_score(labels, scores))


def _interval(values: list[float], level: float = 0.95) -> list[float]:
    tail = (1.0 - level) / 2.0
    return [float(np.quantile(values, tail)), float(np.quantile(values, 1.0 - tail))]


def measure(evaluation: Evaluation, scores: np.ndarray, threshold: float, reference: dict | None,
            resamples: int, seed: int, key: str = "versus_deployed") -> dict:
    """A scorer's figures on the evaluation recording; with ``reference`` (another scorer's scores and
    threshold), paired bootstrap intervals over scenes of the differences from it, under ``key``."""
    y = evaluation.labels
    rules = replay(evaluation, scores, threshold)
    row = {"candidate_auc": _auc(y, scores), "balanced_accuracy": balanced_accuracy(y, scores >= threshold),
           "threshold": float(threshold), "loop_success": float(rules["threshold"].mean()),
           "rank_success": float(rules["rank"].mean())}
    if reference is None:
        return row
    ref_rules = replay(evaluation, reference["scores"], reference["threshold"])
    names = sorted(set(evaluation.scenes))
    scene_of = np.asarray(evaluation.scenes)
    members = [np.flatnonzero(scene_of == n) for n in names]
    rng = np.random.default_rng(seed)
    auc, loop, rank = [], [], []
    while len(auc) < resamples:
        draw = rng.integers(0, len(names), len(names))
        pick = np.concatenate([members[g] for g in draw])
        if y[pick].all() or not y[pick].any():
            continue
        auc.append(_auc(y[pick], scores[pick]) - _auc(y[pick], reference["scores"][pick]))
        loop.append(float(rules["threshold"][draw].mean() - ref_rules["threshold"][draw].mean()))
        rank.append(float(rules["rank"][draw].mean() - ref_rules["rank"][draw].mean()))
    row[key] = {
        "candidate_auc": [row["candidate_auc"] - _auc(y, reference["scores"]), _interval(auc)],
        "loop_success": [row["loop_success"] - float(ref_rules["threshold"].mean()), _interval(loop)],
        "rank_success": [row["rank_success"] - float(ref_rules["rank"].mean()), _interval(rank)],
        "method": f"paired percentile bootstrap over the {len(names)} evaluation scenes, {resamples} resamples"}
    return row


def _episode_attrs(path: Path, names: list[str]) -> list[dict]:
    """Each episode's attributes, in the order of ``names`` (a pool's ``file:demo`` names)."""
    with EpisodeDataset(path) as ds:
        return [ds.demo_attrs(name.rsplit(":", 1)[-1]) for name in names]


def _ensemble_scores(models: list[torch.nn.Module], data) -> np.ndarray:
    return np.mean([predict(m, data) for m in models], axis=0)


def difference_cell(row: dict, versus: str, key: str, scale: float = 1.0, digits: int = 3) -> str:
    """A table cell for a row's paired difference ``row[versus][key]`` and its interval; empty on the
    reference row, which has none."""
    if versus not in row:
        return ""
    d, (lo, hi) = row[versus][key]
    return f"{d * scale:+.{digits}f} [{lo * scale:+.{digits}f}, {hi * scale:+.{digits}f}]"


def markdown(rows: list[dict], recording: str, evaluation: str, n_scenes: int, n_candidates: int) -> str:
    def diff(row: dict, key: str, scale: float = 1.0, digits: int = 3) -> str:
        return difference_cell(row, "versus_deployed", key, scale, digits)

    lines = [f"Refreshes trained on what `{recording}` would have recorded under each policy, judged on every "
             f"candidate of `{evaluation}` ({n_candidates} candidates, {n_scenes} scenes).", "",
             "| policy | recorded episodes | candidates' AUC | vs deployed [95%] | balanced accuracy | "
             "TAMP + FIRP (paper's rule) | vs deployed [95%] | ranking | vs deployed [95%] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['policy']} | {r.get('recorded', '')} | {r['candidate_auc']:.3f} | {diff(r, 'candidate_auc')} "
                     f"| {r['balanced_accuracy']:.3f} | {r['loop_success']:.0%} | {diff(r, 'loop_success', 100, 0)} "
                     f"| {r['rank_success']:.0%} | {diff(r, 'rank_success', 100, 0)} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["policy"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for ax, key, title in ((axes[0], "candidate_auc", "candidates' ROC AUC"),
                           (axes[1], "loop_success", "TAMP + FIRP, paper's rule")):
        values = [r[key] for r in rows]
        ax.bar(range(len(rows)), values, color=["0.6"] + ["C0"] * (len(rows) - 1))
        for i, r in enumerate(rows):
            if "versus_deployed" in r:
                d, (lo, hi) = r["versus_deployed"][key]  # the difference's interval, drawn around the bar
                ax.errorbar(i, r[key], yerr=[[max(0.0, d - lo)], [max(0.0, hi - d)]], color="k", capsize=3)
        ax.set_xticks(range(len(rows)), names, rotation=30, ha="right")
        ax.set_ylim(min(values) - 0.08, min(1.0, max(values) + 0.05))
        ax.set_title(title)
    fig.suptitle("Refreshes from a recording with and without exploration (error bars: 95% interval of the "
                 "difference from 'deployed')", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", type=Path, required=True, help="the bundle that scored the recording run")
    parser.add_argument("--data", type=Path, required=True, help="the collected dataset every refresh trains on")
    parser.add_argument("--recording", type=Path, required=True,
                        help="a run directory of `firp run --record --explore 6` (trials.jsonl, executions.h5)")
    parser.add_argument("--evaluation", type=Path, required=True,
                        help="a run directory recorded the same way on other seeds: every candidate is judged")
    parser.add_argument("--k", type=int, nargs="+", default=[2], help="explored candidates per scene to compare")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resamples", type=int, default=2000)
    parser.add_argument("--out", type=Path, required=True, help="per-policy scores, so a rerun resumes")
    parser.add_argument("--report", type=Path, required=True, help="path stem of the .json, .md and .png written")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    torch.set_num_threads(args.threads)
    progress = not args.no_progress
    for run_dir in (args.recording, args.evaluation):
        for name in ("trials.jsonl", "executions.h5"):
            if not (run_dir / name).exists():
                parser.error(f"{run_dir}: no {name} (a run of `firp run --record DIR --explore 6` writes both)")
    records = read_records(args.recording / "trials.jsonl")
    if not all("candidate_outcomes" in r for r in records):
        parser.error(f"--recording {args.recording}: its trials were not run with --explore (no candidate_outcomes)")
    bundle = load_bundle(args.bundle)
    pool = load_pool([args.data, args.recording / "executions.h5"], bundle, DEFAULT_CACHE_DIR, progress)
    test_pool = load_pool([args.evaluation / "executions.h5"], bundle, DEFAULT_CACHE_DIR, progress)
    attrs = _episode_attrs(args.evaluation / "executions.h5", test_pool.data.demo_names)
    evaluation = Evaluation([a["scene_id"] for a in attrs], np.asarray([a["candidate_index"] for a in attrs]),
                            test_pool.data.labels.numpy() > 0.5)
    collected = np.flatnonzero(pool.source == 0)
    recorded = np.flatnonzero(pool.source == 1)
    recorded_pairs = [_recorded_candidate(a) for a in _episode_attrs(
        args.recording / "executions.h5", [pool.data.demo_names[i] for i in recorded])]
    # one validation split of scenes for every policy: early stopping and thresholds see the same episodes
    valid_scenes = {pool.scenes[i] for i in scene_split(pool.scenes, np.arange(len(pool.data)), 0.2, args.seed + 1)}
    is_valid = np.asarray([s in valid_scenes for s in pool.scenes])
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    current = _ensemble_scores(list(bundle.models), test_pool.data)
    rows.append({"policy": "bundle in use (no refresh)", "recorded": 0,
                 **measure(evaluation, current, bundle.threshold, None, args.resamples, args.seed)})
    reference = None
    for policy in policies(args.k):
        saved = args.out / f"{policy}.json"
        wanted = chosen_by_policy(records, policy, seed=args.seed)
        chosen = recorded[np.asarray([pair in wanted for pair in recorded_pairs], dtype=bool)]
        if saved.exists():
            done = json.loads(saved.read_text())
            scores, threshold = np.asarray(done["scores"]), float(done["threshold"])
        else:
            episodes = np.concatenate([collected, chosen])
            train_idx, valid_idx = episodes[~is_valid[episodes]], episodes[is_valid[episodes]]
            train, valid = pool.data.subset(train_idx), pool.data.subset(valid_idx)
            models = []
            for k, (kind, config, model) in enumerate(zip(bundle.kinds, bundle.configs, bundle.models)):
                cfg = TrainConfig(kind=kind, model=config, epochs=args.epochs, lr=args.lr, seed=args.seed + k,
                                  threads=args.threads, patience=max(5, args.epochs // 2))
                initial = {name: t.detach().clone() for name, t in model.state_dict().items()}
                models.append(train_model(cfg, train, valid, progress=progress, initial_state=initial).model)
            threshold, _ = choose_threshold(valid.labels.numpy() > 0.5, _ensemble_scores(models, valid))
            scores = _ensemble_scores(models, test_pool.data)
            saved.write_text(json.dumps({"policy": policy, "recorded": len(chosen), "train": len(train_idx),
                                         "valid": len(valid_idx), "threshold": float(threshold),
                                         "scores": scores.tolist()}))
        row = {"policy": policy, "recorded": len(chosen),
               **measure(evaluation, scores, threshold, reference, args.resamples, args.seed)}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "versus_deployed"}), flush=True)
        if reference is None:
            reference = {"scores": scores, "threshold": threshold}
    n_scenes = len(set(evaluation.scenes))
    result = {"bundle": str(args.bundle), "recording": str(args.recording), "evaluation": str(args.evaluation),
              "evaluation_scenes": n_scenes, "evaluation_candidates": len(evaluation.labels),
              "epochs": args.epochs, "rows": rows, "seconds": round(time.perf_counter() - started),
              "command": "python -m experiments.exploration_value " + " ".join(argv or sys.argv[1:])}
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.with_suffix(".json").write_text(json.dumps(result, indent=1))
    text = markdown(rows, str(args.recording), str(args.evaluation), n_scenes, len(evaluation.labels))
    args.report.with_suffix(".md").write_text(text)
    plot(rows, args.report.with_suffix(".png"))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
