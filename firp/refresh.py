"""``firp refresh``: a new ensemble from the collected data plus the loop's recorded executions, promoted
only if it is not worse than the bundle in use on the same held-out recorded scenes.

Why: the loop executes several candidates of the same scene and the sim worker labels each one
(``firp run --record``) -- the data a scorer that must rank a scene's candidates learns from best. A
refresh must never make the product worse, so:

1. **Held out first.** A fraction of the scenes of the newest recording (the last ``--data`` file with
   recorded executions; all their candidates: a scene's candidates share an image and its physics) is set
   aside before anything trains; both bundles are judged on it. Neither has seen those scenes: an
   earlier recording may have trained the bundle in use.
2. **Train** every member of the current bundle again (its kind and model config) on everything else,
   warm-started from its weights by default; early stopping and the new ensemble's threshold use a
   validation split of scenes from the training pool, as an export does.
3. **Compare, paired**: both ensembles score the held-out episodes; the difference of their balanced
   accuracies (each at its own threshold) gets a bootstrap interval over held-out scenes
   (:func:`firp.core.decisions.paired_comparison`). **Promoted** when the new one is not worse on the point
   estimate and the interval's lower end is above ``-margin``; otherwise the current bundle stays, and the
   report says which condition failed.
4. The new bundle is written to ``--out`` either way (its manifest's ``refresh`` section says whether it was
   promoted and why, with its decision evidence); ``--swap URL`` loads it into a running scoring service
   (the model repository's hot swap) only when it is promoted.

Exit codes: 0 promoted, 3 kept the current bundle, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from firp.bundle import BundleError, BundleMember, export_bundle, load_bundle
from firp.core.bundle_format import bundle_version
from firp.core.cli_types import int_in_range, non_negative_float, open_unit_float
from firp.core.contract import PlanLimits
from firp.core.decisions import decision_evidence, paired_comparison
from firp.core.episodes import EpisodeDataset
from firp.data import FrameFeatures, SequenceData, load_sequences
from firp.features import DEFAULT_CACHE_DIR
from firp.metrics import balanced_accuracy, choose_threshold, expected_calibration_error
from firp.train import TrainConfig, predict, train_model

__all__ = ["EXIT_KEPT", "Pool", "held_out_scenes", "load_pool", "main", "refresh", "scene_split", "swap_into"]

EXIT_KEPT = 3  # the refresh ran and the current bundle stays


@dataclass
class Pool:
    """Every episode of the ``--data`` files, one after another, with the scene each belongs to."""

    data: SequenceData
    scenes: list[str]  # a recorded episode's scene_id; a collected episode is a scene of its own
    recorded: np.ndarray  # (N,) bool: from the loop's recordings (firp run --record)
    sources: list[dict]  # per file: path, content hash, episodes, recorded or not
    source: np.ndarray  # (N,) int: which --data file each episode came from


def load_pool(paths: list[Path], bundle, cache_dir: Path, progress: bool) -> Pool:
    """The datasets' features through the bundle's own backbone, concatenated; plans must fit the bundle."""
    parts, scenes, recorded, sources, source = [], [], [], [], []
    for k, path in enumerate(paths):
        data = load_sequences(path, bundle.encoder_config, cache_dir, progress=progress)
        T = int(data.actions.shape[1])
        if not bundle.t_range.t_min <= T <= bundle.t_range.t_max:
            raise ValueError(f"--data {path}: plans of T={T} steps are outside the bundle's T range "
                             f"[{bundle.t_range.t_min}, {bundle.t_range.t_max}]")
        if parts and T != parts[0].actions.shape[1]:
            raise ValueError(f"--data {path}: plans of T={T} steps, the first file's have {parts[0].actions.shape[1]}; "
                             "refresh on datasets of one task and horizon")
        with EpisodeDataset(path) as ds:
            attrs = [ds.demo_attrs(name) for name in data.demo_names]
        ids = [a.get("scene_id") for a in attrs]
        from_loop = [i is not None for i in ids]
        scenes += [i if i is not None else f"{path.name}:{name}" for i, name in zip(ids, data.demo_names)]
        recorded += from_loop
        source += [k] * len(from_loop)
        parts.append(replace(data, demo_names=[f"{path.name}:{n}" for n in data.demo_names]))
        sources.append({"path": os.fspath(path), "sha256": data.dataset_hash, "episodes": len(data),
                        "recorded_episodes": int(sum(from_loop))})
    joined = SequenceData(FrameFeatures.concat([p.features for p in parts]), torch.cat([p.actions for p in parts]),
                          torch.cat([p.labels for p in parts]), "+".join(p.dataset_hash[:12] for p in parts),
                          [n for p in parts for n in p.demo_names], parts[0].attrs)
    return Pool(joined, scenes, np.asarray(recorded, dtype=bool), sources, np.asarray(source, dtype=int))


def scene_split(scenes: list[str], candidates: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """Indices (among ``candidates``) of whole scenes drawn at random until ``fraction`` of the candidate
    episodes is reached: a scene's episodes never straddle the split."""
    rng = np.random.default_rng(seed)
    names = sorted({scenes[i] for i in candidates})
    order = rng.permutation(len(names))
    chosen: set[str] = set()
    target = fraction * len(candidates)
    count = 0
    sizes = {name: 0 for name in names}
    for i in candidates:
        sizes[scenes[i]] += 1
    for k in order:
        if count >= target:
            break
        chosen.add(names[k])
        count += sizes[names[k]]
    return np.array([i for i in candidates if scenes[i] in chosen], dtype=int)


def held_out_scenes(pool: Pool, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(training pool, held out): ``fraction`` of the scenes of the *last* ``--data`` file that holds
    recorded executions, whole, held out. Only the newest recording: the bundle in use may have been
    trained on an earlier round's scenes, and a comparison on them would favour it."""
    if not pool.recorded.any():
        raise ValueError("--data: none of the datasets holds recorded executions (firp run --record DIR gives "
                         "DIR/executions.h5); the refresh is judged on held-out recorded scenes")
    newest = pool.source[pool.recorded].max()
    recorded = np.flatnonzero(pool.recorded & (pool.source == newest))
    held = scene_split(pool.scenes, recorded, fraction, seed)
    labels = pool.data.labels.numpy()[held] > 0.5
    if labels.all() or not labels.any():
        raise ValueError(f"--held-out-fraction {fraction}: the {len(held)} held-out recorded episodes are all "
                         f"{'successes' if labels.all() else 'failures'}; record more trials or hold out more")
    rest = np.setdiff1d(np.arange(len(pool.data)), held)
    return rest, held


def _ensemble(models: list[torch.nn.Module], data: SequenceData) -> np.ndarray:
    return np.mean([predict(m, data) for m in models], axis=0)


def refresh(bundle_dir: Path, datasets: list[Path], out: Path, *, held_out_fraction: float = 0.3,
            valid_fraction: float = 0.2, epochs: int = 20, lr: float = 3e-4, warm_start: bool = True,
            margin: float = 0.02, resamples: int = 2000, seed: int = 0, threads: int = 2,
            cache_dir: Path = DEFAULT_CACHE_DIR, progress: bool = True) -> dict:
    """Train, compare and write; returns the report (``promoted`` and ``why`` among its keys)."""
    started = time.perf_counter()
    torch.set_num_threads(threads)
    current = load_bundle(bundle_dir)
    pool = load_pool(datasets, current, cache_dir, progress)
    rest, held = held_out_scenes(pool, held_out_fraction, seed)
    valid_idx = rest[np.isin(rest, scene_split(pool.scenes, rest, valid_fraction, seed + 1))]
    train_idx = np.setdiff1d(rest, valid_idx)
    train, valid, test = (pool.data.subset(i) for i in (train_idx, valid_idx, held))
    y_valid, y_test = valid.labels.numpy() > 0.5, test.labels.numpy() > 0.5
    if y_valid.all() or not y_valid.any():
        raise ValueError("the validation split of the training pool has one class only; give more data")
    members, models = [], []
    for k, (kind, config, model) in enumerate(zip(current.kinds, current.configs, current.models)):
        cfg = TrainConfig(kind=kind, model=config, epochs=epochs, lr=lr, seed=seed + k, threads=threads,
                          patience=max(5, epochs // 2))
        initial = {name: t.detach().clone() for name, t in model.state_dict().items()} if warm_start else None
        result = train_model(cfg, train, valid, progress=progress, initial_state=initial)
        models.append(result.model)
        members.append(BundleMember(kind, config, result.model,
                                    {"valid_balanced_accuracy": float(result.best_val_balanced_accuracy),
                                     "best_epoch": int(result.best_epoch)}))
    p_valid = _ensemble(models, valid)
    threshold, ba_at_threshold = choose_threshold(y_valid, p_valid)
    new_test = _ensemble(models, test)
    current_test = _ensemble(list(current.models), test)
    comparison = paired_comparison(y_test, [pool.scenes[i] for i in held], new_scores=new_test,
                                   new_threshold=threshold, current_scores=current_test,
                                   current_threshold=current.threshold, resamples=resamples, seed=seed)
    low = comparison["interval"][0]
    if comparison["difference"] < 0:
        promoted, why = False, (f"worse on the held-out scenes: balanced accuracy {comparison['new_balanced_accuracy']:.3f} "
                                f"against the current {comparison['current_balanced_accuracy']:.3f}")
    elif low < -margin:
        promoted, why = False, (f"not shown to be no worse: the difference's interval reaches {low:+.3f}, below "
                                f"-{margin:g} (more held-out scenes narrow it)")
    else:
        promoted, why = True, (f"not worse: difference {comparison['difference']:+.3f}, interval "
                               f"[{low:+.3f}, {comparison['interval'][1]:+.3f}] above -{margin:g}")
    report = {
        "current": {"path": os.fspath(current.path), "name": current.manifest.get("name"),
                    "version": bundle_version(current.path, current.manifest)},
        "datasets": pool.sources,
        "split": {"train": int(len(train_idx)), "valid": int(len(valid_idx)), "held_out": int(len(held)),
                  "held_out_scenes": sorted({pool.scenes[i] for i in held}), "held_out_fraction": held_out_fraction,
                  "seed": seed},
        "training": {"warm_start": warm_start, "epochs": epochs, "lr": lr,
                     "members": [m.metrics for m in members]},
        "paired": comparison, "margin": margin, "promoted": promoted, "why": why,
    }
    export_bundle(
        out, members, name=str(current.manifest.get("name")), task=str(current.manifest.get("task")),
        threshold=threshold,
        calibration={"ece": expected_calibration_error(y_valid, p_valid), "n_val": int(len(y_valid)), "n_bins": 10},
        metrics={"valid_balanced_accuracy_at_0.5": balanced_accuracy(y_valid, p_valid >= 0.5),
                 "valid_balanced_accuracy_at_threshold": ba_at_threshold},
        training_data_hash=pool.data.dataset_hash, training_data_path=";".join(os.fspath(p) for p in datasets),
        t_range=PlanLimits(current.t_range.t_min, current.t_range.t_max), backbone=current.backbone, overwrite=True,
        evidence=decision_evidence(y_valid, p_valid, threshold, resamples=resamples),
        extra={"refresh": {k: v for k, v in report.items() if k != "datasets"}, "datasets": pool.sources,
               "validation_split": {"episodes": [pool.data.demo_names[i] for i in valid_idx.tolist()]}},
    )
    report["new"] = {"path": os.fspath(out), "version": bundle_version(out, load_bundle(out).manifest)}
    report["seconds"] = round(time.perf_counter() - started, 1)
    return report


def swap_into(service_url: str, bundle_dir: Path, api_key: str | None = None, timeout: float = 120.0) -> dict:
    """Load ``bundle_dir`` into the scoring service at ``service_url`` through the model repository's hot
    swap (``POST /v2/repository/models/{name}/load``; the service verifies and warms it before switching)
    and return the service's ``/v1/model`` afterwards. The bundle's path must be readable by the service."""
    import httpx

    headers = {"X-API-Key": api_key} if api_key else {}
    try:
        with httpx.Client(base_url=service_url.rstrip("/"), headers=headers, timeout=timeout) as http:
            name = http.get("/v1/model").raise_for_status().json()["name"]
            answer = http.post(f"/v2/repository/models/{name}/load", json={"parameters": {"bundle": str(bundle_dir)}})
            if answer.status_code != 200:
                raise RuntimeError(f"{service_url} refused the bundle ({answer.status_code}): {answer.text[:300]}")
            return http.get("/v1/model").raise_for_status().json()
    except httpx.HTTPError as exc:
        raise RuntimeError(f"{service_url}: {exc}") from exc


def table(report: dict) -> str:
    c = report["paired"]
    low, high = c["interval"]
    return "\n".join([
        f"held out: {c['n_episodes']} recorded episodes of {c['n_scenes']} scenes "
        f"({c['n_successes']} successes / {c['n_failures']} failures)",
        "| bundle | version | held-out balanced accuracy |", "|---|---|---|",
        f"| current | {report['current']['version']} | {c['current_balanced_accuracy']:.3f} |",
        f"| refreshed | {report['new']['version']} | {c['new_balanced_accuracy']:.3f} |",
        f"difference {c['difference']:+.3f}, {100 * c['level']:.0f}% interval [{low:+.3f}, {high:+.3f}]",
        ("PROMOTED: " if report["promoted"] else "KEPT the current bundle: ") + report["why"],
    ])


def main(argv: list[str] | None = None, prog: str = "firp refresh") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", type=Path, required=True, help="the bundle in use (its members are refreshed)")
    parser.add_argument("--data", type=Path, action="append", required=True,
                        help="a dataset: collected (firp collect) or recorded (DIR/executions.h5 of firp run "
                             "--record); repeat the flag for several")
    parser.add_argument("--out", type=Path, required=True, help="where the refreshed bundle is written")
    parser.add_argument("--held-out-fraction", type=open_unit_float("--held-out-fraction"), default=0.3,
                        help="share of the newest recording's scenes (the last --data file with recorded "
                             "executions) held out to judge both bundles (default 0.3)")
    parser.add_argument("--epochs", type=int_in_range("--epochs", 1, 1000), default=20)
    parser.add_argument("--lr", type=open_unit_float("--lr"), default=3e-4)
    parser.add_argument("--no-warm-start", action="store_true", help="train the members from scratch")
    parser.add_argument("--margin", type=non_negative_float("--margin"), default=0.02,
                        help="promote when the paired difference is >= 0 and its interval's lower end >= -MARGIN")
    parser.add_argument("--resamples", type=int_in_range("--resamples", 100, 1_000_000), default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int_in_range("--threads", 1, 256), default=2)
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE_DIR)
    parser.add_argument("--report", type=Path, default=None, help="write the report as JSON here")
    parser.add_argument("--swap", default=None, metavar="URL",
                        help="a running scoring service: load the refreshed bundle into it when promoted (hot swap)")
    parser.add_argument("--api-key", default=None, help="X-API-Key for --swap")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    for path in args.data:
        if not path.exists():
            parser.error(f"--data: {path} does not exist")
    if not args.bundle.exists():
        parser.error(f"--bundle: {args.bundle} does not exist")
    try:
        report = refresh(args.bundle, args.data, args.out, held_out_fraction=args.held_out_fraction,
                         epochs=args.epochs, lr=args.lr, warm_start=not args.no_warm_start, margin=args.margin,
                         resamples=args.resamples, seed=args.seed, threads=args.threads, cache_dir=args.cache_dir,
                         progress=not args.no_progress)
    except (BundleError, ValueError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if report["promoted"] and args.swap:
        try:
            report["swapped"] = swap_into(args.swap, args.out.resolve(), args.api_key)
        except RuntimeError as exc:
            print(f"{prog}: --swap: {exc}", file=sys.stderr)
            return 1
    if args.report:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=1))
    print(table(report))
    if "swapped" in report:
        print(f"swapped: {args.swap} serves {report['swapped'].get('version')}")
    return 0 if report["promoted"] else EXIT_KEPT


if __name__ == "__main__":
    raise SystemExit(main())
