"""The evaluation protocol: every method on the same splits, balanced accuracy on held-out tests.

Per repeat r: a stratified 80/20 train/test split (seed r), then 20% of train held out for
validation (early stopping and threshold choice). Every method trains on the same episodes and is
tested on the same episodes; results are written per (repeat, method) as they finish, so an
interrupted evaluation resumes without retraining what is done. DVD (the paper's video baseline)
needs its authors' published weights and cannot run here: it is reported as not run.

    firp evaluate --data data/stacking.h5 --repeats 5            # the product preset
    firp evaluate --data data/stacking.h5 --repeats 5 --preset paper
    firp evaluate --data data/stacking.h5 --repeats 5 --ray local   # the runs as Ray tasks
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from firp.core.cli_types import int_in_range
from firp.core.episodes import EpisodeDataset
from firp.core.ray_cluster import ray_session
from firp.flags import add_loss_flags, add_model_flags, add_training_flags, check_data_flag, recipe_flags, recipe_from
from firp.data import SequenceData, load_sequences, stratified_split
from firp.metrics import balanced_accuracy, choose_threshold

from firp.train import TrainConfig, predict, train_model

#: method name -> how it differs from the default training config
METHODS: dict[str, dict] = {
    "a_mlp": {"kind": "a_mlp"},
    "a_mlp_image": {"kind": "a_mlp_image"},
    "gru": {"kind": "gru"},
    "firp": {"kind": "firp", "loss": {"alpha": 0.0, "beta": 0.0}},
    "firp_ttc": {"kind": "firp", "loss": {"beta": 0.0}},
    "firp_atc": {"kind": "firp", "loss": {"alpha": 0.0}},
    "firp_tcr": {"kind": "firp"},
    "oracle": {"kind": "oracle"},
    # an MLP on the plan's grasp-frame description alone (needs --plan-geometry): what the others add to it
    "geometry_mlp": {"kind": "a_mlp", "baseline": {"plan_pooling": "none"}},
}
NEEDS_GEOMETRY = ("geometry_mlp",)
#: kinds that read every executed frame: on a dataset where most episodes kept only their initial frame they
#: train and test on the framed episodes of each split
FRAME_READERS = ("oracle",)
DEFAULT_METHODS = ("a_mlp", "a_mlp_image", "gru", "firp", "firp_ttc", "firp_atc", "firp_tcr", "oracle")
#: the FIRP variants whose test scores the per-repeat ensemble row averages
FIRP_VARIANTS = ("firp", "firp_ttc", "firp_atc", "firp_tcr")
ENSEMBLE = "firp_ensemble"
BASELINES = ("a_mlp", "a_mlp_image", "gru", "geometry_mlp")
NOT_RUN = {"dvd": "needs the DVD authors' published weights, which cannot be downloaded here"}
#: the bar the FIRP ensemble must clear above the best non-oracle baseline, by the dataset's world (its
#: ``env`` attribute): robosuite's tasks are held to the paper's MimicGen lead (~+0.02), our own world to +0.05
TARGET_MARGINS = {"robosuite": 0.02}
DEFAULT_TARGET_MARGIN = 0.05


def target_margin(env: str | None) -> float:
    """The margin over the best non-oracle baseline a dataset of world ``env`` is judged by."""
    return TARGET_MARGINS.get(env or "", DEFAULT_TARGET_MARGIN)


_RUN_NAME = re.compile(r"r(?P<repeat>\d+)-(?P<method>\w+)")


def run_name(repeat: int, method: str) -> str:
    """A (repeat, method) run's name: its row is ``<out>/<name>.json``, its checkpoint ``<out>/<name>/checkpoint``."""
    return f"r{repeat}-{method}"


def parse_run_name(name: str) -> tuple[int, str] | None:
    """``(repeat, method)`` of a name :func:`run_name` made, else None."""
    match = _RUN_NAME.fullmatch(name)
    return (int(match["repeat"]), match["method"]) if match else None


def split_indices(labels: np.ndarray, repeat: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, valid, test) index arrays for repeat ``repeat``: 80/20, then 20% of train to valid."""
    rest, test = stratified_split(labels, 0.2, seed=repeat)
    inner_train, inner_valid = stratified_split(labels[rest], 0.2, seed=10_000 + repeat)
    return rest[inner_train], rest[inner_valid], test


def held_out_metrics(y_valid: np.ndarray, p_valid: np.ndarray, y_test: np.ndarray, p_test: np.ndarray) -> dict:
    """Test balanced accuracy at 0.5 and at the threshold that maximises it on the validation episodes."""
    threshold, _ = choose_threshold(y_valid, p_valid)
    return {"test_balanced_accuracy": balanced_accuracy(y_test, p_test >= 0.5),
            "test_balanced_accuracy_valid_threshold": balanced_accuracy(y_test, p_test >= threshold),
            "valid_threshold": threshold}


def method_config(name: str, base: TrainConfig) -> TrainConfig:
    """``base`` as method ``name`` of :data:`METHODS` trains: its kind, loss weights and baseline settings."""
    overrides = dict(METHODS[name])
    baseline, loss = overrides.pop("baseline", None), overrides.pop("loss", None)
    cfg = replace(base, **overrides)
    if baseline:
        cfg = replace(cfg, model=replace(cfg.model, baseline=replace(cfg.model.baseline, **baseline)))
    if loss:
        cfg = replace(cfg, model=replace(cfg.model, loss=replace(cfg.model.loss, **loss)))
    return cfg


def evaluate_method(name: str, base: TrainConfig, data: SequenceData, repeat: int, run_dir: Path,
                    progress: bool, device: str = "cpu") -> dict:
    train_idx, valid_idx, test_idx = split_indices(data.labels.numpy(), repeat)
    cfg = method_config(name, replace(base, seed=repeat))
    if cfg.kind in FRAME_READERS:  # it reads every executed frame: the episodes that kept them
        framed = data.framed.numpy()
        train_idx, valid_idx, test_idx = (i[framed[i]] for i in (train_idx, valid_idx, test_idx))
    started = time.perf_counter()
    result = train_model(cfg, data.subset(train_idx), data.subset(valid_idx), checkpoint_dir=run_dir / "checkpoint",
                         progress=progress, device=device)
    valid, test = data.subset(valid_idx), data.subset(test_idx)
    p_valid, p_test = predict(result.model, valid), predict(result.model, test)
    return {
        "method": name, "repeat": repeat, "config": cfg.to_dict(),
        **held_out_metrics(valid.labels.numpy() > 0.5, p_valid, test.labels.numpy() > 0.5, p_test),
        "valid_balanced_accuracy": result.best_val_balanced_accuracy,
        "best_epoch": result.best_epoch, "epochs_run": len(result.history),
        "train_seconds": round(time.perf_counter() - started, 1),
        "n_train": len(train_idx), "n_valid": len(valid_idx), "n_test": len(test_idx),
        # per-episode scores (same order as the indices) so ensembles and figures need no retraining
        "valid_index": valid_idx.tolist(), "test_index": test_idx.tolist(),
        "valid_scores": [round(float(p), 6) for p in p_valid], "test_scores": [round(float(p), 6) for p in p_test],
    }


def _evaluate_task(name: str, base: TrainConfig, data: SequenceData, repeat: int, run_dir: Path,
                   threads: int, device: str = "cpu") -> dict:
    """One (repeat, method) run inside a Ray worker, with the driver's thread count and device."""
    torch.set_num_threads(threads)
    return evaluate_method(name, base, data, repeat, run_dir, progress=False, device=device)


def evaluate_on_ray(address: str, runs: list[tuple[int, str]], base: TrainConfig, data: SequenceData, out: Path,
                    threads: int, device: str = "cpu"):
    """Train ``runs`` as Ray tasks of ``threads`` CPUs each and yield ``((repeat, method), row)`` as they finish.

    The sequences go into Ray's object store once and every task reads them from there; each task seeds
    its training as the sequential loop does, so its row equals the sequential run's (but for
    ``train_seconds``). A worker that dies is retried by Ray (``max_retries``); checkpoints stay on
    the node that trained (under ``out`` there). ``local`` starts a private cluster of this machine's
    CPUs for the run (:mod:`firp.core.ray_cluster`)."""
    if not runs:
        return
    with ray_session(address, os.cpu_count() or 1) as ray:
        task = ray.remote(num_cpus=threads, max_retries=3)(_evaluate_task)
        shared = ray.put(data)
        pending = {task.remote(name, base, shared, repeat, out.resolve() / run_name(repeat, name), threads, device):
                   (repeat, name) for repeat, name in runs}
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            yield pending.pop(ref), ray.get(ref)


def ensemble_rows(rows: list[dict], labels: np.ndarray, min_members: int = 2) -> list[dict]:
    """Per repeat, the mean score of every FIRP variant trained in it: an ensemble of models that differ in
    their TCR weights, like the tuned top five (whose members differ in alpha, beta, lambda), at no extra
    training cost. Its threshold is chosen on the validation scores, as for single models. Repeats with
    fewer than ``min_members`` variants get no row (the protocol's table lists a lone variant on its own)."""
    out = []
    for repeat in sorted({r["repeat"] for r in rows}):
        members = [r for r in rows if r["repeat"] == repeat and r["method"] in FIRP_VARIANTS and "test_scores" in r]
        if len(members) < min_members:
            continue
        p_valid = np.mean([m["valid_scores"] for m in members], axis=0)
        p_test = np.mean([m["test_scores"] for m in members], axis=0)
        y_valid, y_test = labels[members[0]["valid_index"]] > 0.5, labels[members[0]["test_index"]] > 0.5
        out.append({
            "method": ENSEMBLE, "repeat": repeat, "members": [m["method"] for m in members],
            **held_out_metrics(y_valid, p_valid, y_test, p_test),
            "valid_balanced_accuracy": balanced_accuracy(y_valid, p_valid >= 0.5),
            "train_seconds": round(sum(m["train_seconds"] for m in members), 1),
        })
    return out


def _mean_accuracy(rows: list[dict], name: str) -> float | None:
    vals = [r["test_balanced_accuracy"] for r in rows if r["method"] == name]
    return statistics.mean(vals) if vals else None


def best_baseline(rows: list[dict]) -> tuple[str, float] | None:
    """The non-oracle baseline with the highest mean test balanced accuracy in ``rows``, and that mean."""
    base = {name: _mean_accuracy(rows, name) for name in BASELINES if _mean_accuracy(rows, name) is not None}
    if not base:
        return None
    best = max(base, key=base.get)
    return best, base[best]


def target_line(rows: list[dict], margin: float = DEFAULT_TARGET_MARGIN) -> str:
    """The FIRP ensemble against the best non-oracle baseline of the same repeats, judged by ``margin``."""
    best = best_baseline(rows)
    who = ENSEMBLE if _mean_accuracy(rows, ENSEMBLE) is not None else "firp_tcr"
    ours = _mean_accuracy(rows, who)
    if best is None or ours is None:
        return ""
    name, base = best
    return (f"{who} − best non-oracle baseline ({name}) = {ours - base:+.3f} "
            f"(target ≥ +{margin:.2f}: {'met' if ours - base >= margin else 'not met'})")


def mean_std(values: list[float]) -> str:
    """``mean ± sample std`` to three decimals, as the protocol's tables write it."""
    return f"{statistics.mean(values):.3f} ± {statistics.stdev(values) if len(values) > 1 else 0.0:.3f}"


def summary_table(rows: list[dict], methods: list[str]) -> str:
    lines = ["| method | test balanced accuracy (mean ± std) | repeats | train s / model (median) |", "|---|---|---|---|"]
    for name in [*methods, ENSEMBLE]:
        vals = [r["test_balanced_accuracy"] for r in rows if r["method"] == name]
        secs = [r["train_seconds"] for r in rows if r["method"] == name]
        if not vals:
            continue
        lines.append(f"| {name} | {mean_std(vals)} | {len(vals)} | {statistics.median(secs):.0f} |")
    for name, why in NOT_RUN.items():
        lines.append(f"| {name} | not run: {why} | 0 | — |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="firp evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_flags(parser)
    parser.add_argument("--repeats", type=int_in_range("--repeats", 1, 100), default=5)
    parser.add_argument("--methods", nargs="+", choices=sorted(METHODS), default=list(DEFAULT_METHODS))
    parser.add_argument("--only-repeats", nargs="+", type=int_in_range("--only-repeats", 0, 99), default=None,
                        help="train only these repeat indices (e.g. one process per core or machine, same --out); "
                             "the summary still covers every finished (repeat, method) of the first --repeats")
    parser.add_argument("--out", type=Path, default=None, help="results directory (default runs/eval-<data stem>)")
    parser.add_argument("--ray", default=None, metavar="local|auto|ADDRESS",
                        help="train the (repeat, method) runs as Ray tasks of --threads CPUs each: local starts a "
                             "private cluster of this machine's CPUs for the run, auto joins this machine's "
                             "(ray start) or RAY_ADDRESS's, else a cluster address; results equal the sequential run's")
    add_model_flags(parser)
    add_loss_flags(parser)
    args = parser.parse_args(argv)
    check_data_flag(parser, args)
    base, overrides = recipe_from(args, parser)
    if not (base.model.geometry.enabled or base.model.events.enabled) and any(m in NEEDS_GEOMETRY for m in args.methods):
        parser.error(f"--methods: {', '.join(m for m in args.methods if m in NEEDS_GEOMETRY)} reads the plan's "
                     "description or events, which this recipe leaves out: drop --no-plan-geometry or add "
                     "--plan-events")
    if args.only_repeats is not None and max(args.only_repeats) >= args.repeats:
        parser.error(f"--only-repeats: every index must be < --repeats ({args.repeats}), got {args.only_repeats}")
    out = args.out or Path("runs") / f"eval-{args.data.stem}"
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    data = load_sequences(args.data, base.model.encoder, args.cache_dir, progress=not args.no_progress)
    base = base.fit_to_data(data)
    runs = [(repeat, name) for repeat in range(args.repeats) for name in args.methods]
    done = {run: json.loads(path.read_text()) for run in runs if (path := out / f"{run_name(*run)}.json").exists()}
    todo = [run for run in runs if run not in done and (args.only_repeats is None or run[0] in args.only_repeats)]
    if args.ray is not None:
        finished = evaluate_on_ray(args.ray, todo, base, data, out, args.threads, args.device)
    else:
        finished = ((run, evaluate_method(run[1], base, data, run[0], out / run_name(*run), not args.no_progress,
                                          args.device)) for run in todo)
    for (repeat, name), row in finished:
        (out / f"{run_name(repeat, name)}.json").write_text(json.dumps(row, indent=1))
        done[(repeat, name)] = row
        print(f"repeat {repeat} {name}: test balanced accuracy {row['test_balanced_accuracy']:.3f} "
              f"(valid {row['valid_balanced_accuracy']:.3f}, {row['train_seconds']} s)", flush=True)
    # runs another process (--only-repeats) finished while this one trained count too
    done.update({run: json.loads(path.read_text()) for run in runs
                 if run not in done and (path := out / f"{run_name(*run)}.json").exists()})
    rows = [done[run] for run in runs if run in done]  # in protocol order, however they finished
    rows = [r for r in rows if r["method"] != ENSEMBLE] + ensemble_rows(rows, data.labels.numpy())
    table = summary_table(rows, args.methods)
    with EpisodeDataset(args.data) as dataset:  # the world decides the bar (one header read)
        env = dataset.attrs.get("env")
    bar = target_line(rows, target_margin(env))
    table = f"{table}\n\n{ENSEMBLE}: mean score of the FIRP variants of each repeat ({', '.join(FIRP_VARIANTS)}).\n" \
            f"{bar}" if any(r["method"] == ENSEMBLE for r in rows) else f"{table}\n\n{bar}"
    print(table)
    covered = sorted({repeat for repeat, _ in done})
    only = f" --only-repeats {' '.join(map(str, covered))}" if len(covered) < args.repeats else ""
    command = f"firp evaluate --data {args.data} --repeats {args.repeats}{only} --methods {' '.join(args.methods)} " \
              f"{recipe_flags(args.preset, overrides)} --threads {args.threads}"  # reproduces the table's repeats
    (out / "results.json").write_text(json.dumps({
        "command": command, "preset": args.preset, "overrides": overrides, "dataset": str(args.data), "env": env,
        "dataset_hash": data.dataset_hash,
        "machine": {"python": platform.python_version(), "torch": torch.__version__, "threads": args.threads},
        "rows": rows, "not_run": NOT_RUN}, indent=1))
    (out / "results.md").write_text(f"# Evaluation on {args.data}\n\n`{command}`\n\n{table}\n")
    print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
