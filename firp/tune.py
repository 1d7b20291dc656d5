"""Optuna tuning of FIRP's seven parameters, and the top-five ensemble built from the best trials.

Search space: the paper's Table (learning rate, gradient clipping, lambda, alpha, beta,
E_start^f, E_stop^e) with two adaptations, recorded in each study's user attributes:
the learning rates include 3e-4 and 1e-3 (our RSSM is small and trains for tens of epochs, not
300 with a ResNet50), and the epoch parameters are the paper's fractions of its 300 epochs
applied to ``--epochs``. Storage is persistent (SQLite file by default; PostgreSQL for several
processes and machines on one study) and studies resume: finished trials are kept, and a trial
whose worker died is retried under its own seed, its training resuming from its checkpoint when
the retrying worker sees it. Every trial trains on the same train/validation split.

    python -m firp.tune --data data/stacking.h5 --trials 20
    python -m firp.tune --data data/stacking.h5 --trials 40 --storage postgresql://user@db/firp   # on each worker
    python -m firp.tune --data data/stacking.h5 --export models/stacking
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
import warnings
from dataclasses import replace
from datetime import datetime
from pathlib import Path

import numpy as np
import optuna
import torch
from safetensors.torch import load_file

from firp.bundle import BundleMember, export_bundle
from firp.core.cli_types import int_in_range
from firp.core.decisions import decision_evidence
from firp.flags import add_model_flags, add_training_flags, check_data_flag, recipe_from
from firp.presets import preset
from firp.core.contract import PlanLimits
from firp.data import SequenceData, load_sequences, stratified_split
from firp.metrics import balanced_accuracy, choose_threshold, expected_calibration_error, reliability_diagram
from firp.model.baselines import build_model

from firp.train import TrainConfig, predict, train_model

LEARNING_RATES = (1e-5, 1e-4, 3e-4, 1e-3)
GRAD_CLIPS = (1e-1, 1e0, 1e1, 1e5)
LOSS_WEIGHTS = (1e-3, 1e-2, 1e-1, 0.0)
E_START_FRACTIONS = (1 / 300, 50 / 300, 100 / 300, 150 / 300)
E_STOP_FRACTIONS = (50 / 300, 100 / 300, 150 / 300, 200 / 300)
TOP_K = 5

#: Search spaces: ``paper`` is the paper's grid (above); ``product`` narrows it to the values that
#: train at all with this product's small RSSM on a 2-core CPU (measured: learning rates 1e-5/1e-4/3e-3
#: and E_start^f late left every stacking trial at validation balanced accuracy 0.50-0.56 in 30
#: epochs), so a short study spends its trials on the loss weights. It also tunes the weight of the
#: one-step prediction terms L_KL^1 + L_re^1 (fixed at 1 in the paper): measured on stacking (400
#: steps, chunk 4), with weight 1 the open-loop head stayed at validation AUC ~0.5, without them it
#: reached 0.78 -- reconstructing e_t pulls the predicted features towards the average future.
SPACES: dict[str, dict[str, tuple]] = {
    "paper": {"lr": LEARNING_RATES, "grad_clip": GRAD_CLIPS, "lambda": LOSS_WEIGHTS, "alpha": LOSS_WEIGHTS,
              "beta": LOSS_WEIGHTS, "e_start_f_fraction": E_START_FRACTIONS, "e_stop_e_fraction": E_STOP_FRACTIONS},
    "product": {"lr": (1e-3,), "grad_clip": (1e1, 1e5), "lambda": (0.0, 1e-3), "alpha": (0.0, 1e-3, 1e-2),
                "beta": (0.0, 1e-3, 1e-2), "e_start_f_fraction": (1 / 300,), "e_stop_e_fraction": (200 / 300,),
                "prediction": (0.0, 1e-2)},
}


def suggest_config(trial: optuna.Trial, base: TrainConfig, space: str = "paper") -> TrainConfig:
    """A training config from a grid of :data:`SPACES` (categorical, so every value is a grid point)."""
    e = base.epochs
    grid = SPACES[space]
    lr = trial.suggest_categorical("lr", grid["lr"])
    grad_clip = trial.suggest_categorical("grad_clip", grid["grad_clip"])
    weights = {"overshooting": trial.suggest_categorical("lambda", grid["lambda"]),
               "alpha": trial.suggest_categorical("alpha", grid["alpha"]),
               "beta": trial.suggest_categorical("beta", grid["beta"])}
    e_start_f = int(round(trial.suggest_categorical("e_start_f_fraction", grid["e_start_f_fraction"]) * e))
    e_stop_e = int(round(trial.suggest_categorical("e_stop_e_fraction", grid["e_stop_e_fraction"]) * e))
    if "prediction" in grid:
        weights["prediction"] = trial.suggest_categorical("prediction", grid["prediction"])
    return replace(base, lr=lr, grad_clip=grad_clip, e_start_f=e_start_f, e_stop_e=e_stop_e, seed=trial.number,
                   model=replace(base.model, loss=replace(base.model.loss, **weights)))


VALID_FRACTION = 0.2
SPLIT_SEED = 0


def tuning_split(labels: np.ndarray, seed: int = SPLIT_SEED) -> tuple[np.ndarray, np.ndarray]:
    """(train, valid) indices of every trial of a study: 20% of the episodes for validation, stratified."""
    return stratified_split(np.asarray(labels), VALID_FRACTION, seed=seed)


#: Liveness of a trial's worker, kept in the storage: a RUNNING trial whose heartbeat is older than
#: the grace period is failed by the next worker that starts a trial, and retried (at most MAX_RETRY
#: times) under its original number's seed and checkpoint directory.
HEARTBEAT_S = 30
GRACE_S = 120
MAX_RETRY = 2
SCHEMA_ATTEMPTS = 5


def open_storage(url: str) -> optuna.storages.RDBStorage:
    """Optuna's RDB storage at ``url`` with heartbeats and retries of trials whose worker died.

    ``postgresql://`` (or ``postgres://``) is served by psycopg 3 (``postgresql+psycopg://``), the
    driver the ``train`` extra installs; any other SQLAlchemy URL is passed on as it is."""
    scheme, sep, rest = url.partition("://")
    if sep and scheme in ("postgresql", "postgres"):
        try:
            import psycopg  # noqa: F401
        except ImportError as error:
            raise SystemExit(f"--storage {url}: PostgreSQL needs psycopg (pip install -e \".[train]\")") from error
        url = f"postgresql+psycopg://{rest}"
    import sqlalchemy.exc

    with warnings.catch_warnings():  # heartbeats are "experimental" in Optuna since 2.8; we rely on them
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        retry = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)
        for attempt in range(SCHEMA_ATTEMPTS):
            try:
                return optuna.storages.RDBStorage(url, heartbeat_interval=HEARTBEAT_S, grace_period=GRACE_S,
                                                  heartbeat_stale_trial_callback=retry)
            except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
                # workers started together on an empty database race to create Optuna's tables (one
                # gets "already exists"): the next attempt finds them made
                if attempt == SCHEMA_ATTEMPTS - 1:
                    raise
                time.sleep(0.5 * (attempt + 1))
    raise AssertionError("unreachable")


def _worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _died_here(trial: optuna.trial.FrozenTrial) -> bool:
    """The RUNNING trial's worker ran on this host and its process is gone. Such a trial is retried at
    once; one of another host waits for its heartbeat to go stale. A trial without a worker id was
    just created by a worker that has not recorded itself yet, or predates worker ids: dead only once
    it is older than the heartbeat's grace period."""
    worker = trial.user_attrs.get("worker")
    if worker is None:
        started = trial.datetime_start
        return started is not None and (datetime.now() - started).total_seconds() > GRACE_S
    host, _, pid = worker.rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def _origin(trial: optuna.trial.FrozenTrial) -> int:
    """The number of the trial a retry repeats (its seed and checkpoint directory), else its own: a
    retry of a dead local worker's trial says so in ``retry_of``, Optuna's retry of a stale one in its
    system attributes."""
    if "retry_of" in trial.user_attrs:
        return int(trial.user_attrs["retry_of"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        retried = optuna.storages.RetryHeartbeatStaleTrialCallback.retried_trial_number(trial)
    return trial.number if retried is None else retried


def run_study(data: SequenceData, base: TrainConfig, storage: str, study_name: str, trials: int, run_dir: Path,
              progress: bool = True, space: str = "paper", recipe: dict | None = None,
              device: str = "cpu") -> optuna.Study:
    """Run trials until the study holds ``trials`` finished ones (a resumed study counts its old ones),
    together with every other worker on the same study: each stops once the study has ``trials``.

    ``recipe`` (``{"preset": name, "overrides": {...}}``) is kept with the study, so that the bundle it
    exports can say what it was made from. On a SQLite file (one machine, usually one worker) the
    sampler is seeded, so a study repeats; on a shared database each worker samples from its own seed,
    with running trials counted as if they had scored (constant liar), so two workers starting together
    do not propose the same trials."""
    shared = not storage.startswith("sqlite")
    sampler = (optuna.samplers.TPESampler(seed=None, constant_liar=True) if shared
               else optuna.samplers.TPESampler(seed=0))
    study = optuna.create_study(study_name=study_name, storage=open_storage(storage), direction="maximize",
                                load_if_exists=True, sampler=sampler)
    study.set_user_attr("dataset_hash", data.dataset_hash)
    if recipe is not None:
        study.set_user_attr("recipe", recipe)
    study.set_user_attr("search_space", space)
    study.set_user_attr("search_space_note", "paper grid; lr adds 3e-4, 1e-3; epochs as fractions of --epochs"
                        if space == "paper" else f"product grid {SPACES[space]}")
    train_idx, valid_idx = tuning_split(data.labels.numpy())
    train, valid = data.subset(train_idx), data.subset(valid_idx)

    def objective(trial: optuna.Trial) -> float:
        trial.set_user_attr("worker", _worker_id())  # first: who runs it, for a crash's retry
        frozen = next(t for t in trial.study.get_trials(deepcopy=False) if t.number == trial.number)
        origin = _origin(frozen)  # a retry trains as the trial it repeats: same seed, same checkpoints
        cfg = replace(suggest_config(trial, base, space), seed=origin)
        ckpt = run_dir / f"trial_{origin:04d}"
        trial.set_user_attr("checkpoint", str(ckpt.resolve()))  # absolute: any worker's export finds it
        trial.set_user_attr("config", cfg.to_dict())
        result = train_model(cfg, train, valid, checkpoint_dir=ckpt, progress=progress, device=device)
        trial.set_user_attr("best_epoch", result.best_epoch)
        trial.set_user_attr("train_seconds", round(result.seconds, 1))
        return result.best_val_balanced_accuracy

    # a trial left RUNNING by a crash of a worker on this host is retried now (another host's: once its
    # heartbeat is stale, by whichever worker starts a trial next)
    for t in study.trials:
        if t.state == optuna.trial.TrialState.RUNNING and _died_here(t):
            try:
                study.tell(t.number, state=optuna.trial.TrialState.FAIL)
            except (ValueError, optuna.exceptions.UpdateFinishedTrialError):
                continue  # another worker starting now failed it first, and retries it
            study.enqueue_trial(t.params, user_attrs={"retry_of": _origin(t)})
    done = len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))
    if trials > done:
        stop_at_total = optuna.study.MaxTrialsCallback(trials, states=(optuna.trial.TrialState.COMPLETE,))
        study.optimize(objective, n_trials=trials - done, callbacks=[stop_at_total])
    return study


def top_trials(study: optuna.Study, k: int = TOP_K) -> list[optuna.trial.FrozenTrial]:
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    return sorted(complete, key=lambda t: (-t.value, t.number))[:k]


def load_trial_model(trial: optuna.trial.FrozenTrial) -> tuple[TrainConfig, torch.nn.Module]:
    cfg = TrainConfig.from_dict(trial.user_attrs["config"])
    model = build_model(cfg.kind, cfg.model)
    model.load_state_dict(load_file(Path(trial.user_attrs["checkpoint"]) / "best.safetensors"))
    return cfg, model.eval()


def export_top_ensemble(study: optuna.Study, data: SequenceData, dataset_path: Path, out_dir: Path, task: str,
                        k: int = TOP_K, reliability_png: Path | None = None) -> dict:
    """Bundle the ``k`` best trials: threshold and calibration chosen on the validation episodes.

    The reliability diagram goes to ``reliability_png`` (default ``runs/<study>_reliability.png``),
    not into the bundle's folder: a package's data directory is no place for reports."""
    chosen = top_trials(study, k)
    if not chosen:
        raise ValueError("the study has no finished trial to export")
    _, valid_idx = tuning_split(data.labels.numpy())
    valid = data.subset(valid_idx)
    members, probs = [], []
    for trial in chosen:
        cfg, model = load_trial_model(trial)
        p = predict(model, valid)
        probs.append(p)
        members.append(BundleMember(cfg.kind, model.cfg, model, {"valid_balanced_accuracy": float(trial.value),
                                                                   "trial": trial.number}))
    ensemble = np.mean(probs, axis=0)
    labels = valid.labels.numpy() > 0.5
    threshold, ba_at_threshold = choose_threshold(labels, ensemble)
    ece = expected_calibration_error(labels, ensemble)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    export_bundle(
        out_dir, members, name=f"firp-{task}", task=task, threshold=threshold,
        calibration={"ece": ece, "n_val": int(len(labels)), "n_bins": 10},
        metrics={"valid_balanced_accuracy_at_0.5": balanced_accuracy(labels, ensemble >= 0.5),
                 "valid_balanced_accuracy_at_threshold": ba_at_threshold},
        training_data_hash=data.dataset_hash, training_data_path=str(dataset_path),
        t_range=PlanLimits(data.actions.shape[1], data.actions.shape[1]), overwrite=True,
        evidence=decision_evidence(labels, ensemble, threshold),
        extra={"study": study.study_name, "trials": [t.number for t in chosen],
               "recipe": study.user_attrs.get("recipe"),
               # the episodes the threshold, the metrics and the ECE above were computed on
               "validation_split": {"fraction": VALID_FRACTION, "seed": SPLIT_SEED,
                                    "episodes": [data.demo_names[i] for i in valid_idx.tolist()]}},
    )
    png = reliability_png or Path("runs") / f"{study.study_name}_reliability.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    reliability_diagram(labels, ensemble, png,
                        f"{task}: top-{len(chosen)} ensemble on validation data (ECE {ece:.3f})")
    return {"threshold": threshold, "ece": ece, "members": [t.number for t in chosen], "reliability_png": str(png)}


def study_table(study: optuna.Study) -> str:
    """Markdown table of the finished trials, best first (what a report or an issue note quotes)."""
    done = sorted((t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE),
                  key=lambda t: t.value, reverse=True)
    keys = sorted({k for t in done for k in t.params})
    lines = ["| trial | validation balanced accuracy | best epoch | train s | " + " | ".join(keys) + " |",
             "|---" * (4 + len(keys)) + "|"]
    for t in done:
        lines.append(f"| {t.number} | {t.value:.3f} | {t.user_attrs.get('best_epoch', '')} | "
                     f"{t.user_attrs.get('train_seconds', '')} | " + " | ".join(f"{t.params.get(k, '')}" for k in keys) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="firp tune", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_flags(parser)
    parser.add_argument("--trials", type=int_in_range("--trials", 0, 10_000), default=20)
    parser.add_argument("--storage", default=None,
                        help="Optuna storage URL (default: sqlite:///runs/tune-<data>.db); postgresql://user@host/db "
                             "lets several workers, on one machine or many, share the study")
    parser.add_argument("--study", default=None, help="study name (default: firp-<data stem>)")
    parser.add_argument("--export", type=Path, default=None, help="write the top-five bundle to this directory")
    parser.add_argument("--task", default=None, help="task name for the bundle (default: the dataset's)")
    parser.add_argument("--report", type=Path, default=None, help="also write the study's trials as a Markdown table")
    parser.add_argument("--reliability", type=Path, default=None,
                        help="with --export: the reliability diagram PNG (default runs/<study>_reliability.png)")
    parser.add_argument("--space", choices=sorted(SPACES), default=None,
                        help="search space: the paper's grid or the narrowed product grid (default: the preset's)")
    add_model_flags(parser)
    args = parser.parse_args(argv)
    check_data_flag(parser, args)
    base, overrides = recipe_from(args, parser)
    space = args.space or preset(args.preset).space
    runs = Path("runs")
    runs.mkdir(exist_ok=True)
    storage = args.storage or f"sqlite:///{runs / ('tune-' + args.data.stem + '.db')}"
    study_name = args.study or f"firp-{args.data.stem}"
    torch.set_num_threads(args.threads)
    data = load_sequences(args.data, base.model.encoder, args.cache_dir, progress=not args.no_progress)
    base = base.fit_to_data(data)
    started = time.perf_counter()
    study = run_study(data, base, storage, study_name, args.trials, runs / f"tune-{study_name}",
                      progress=not args.no_progress, space=space, recipe={"preset": args.preset, "overrides": overrides},
                      device=args.device)
    best = top_trials(study)
    print(f"{len(study.trials)} trials in {storage} ({time.perf_counter() - started:.0f} s this call); best:")
    for t in best:
        print(f"  trial {t.number}: validation balanced accuracy {t.value:.3f}  {json.dumps(t.params)}")
    if args.report:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        command = "firp tune " + " ".join(argv if argv is not None else sys.argv[1:])
        args.report.write_text(f"# Optuna study `{study_name}` on {args.data}\n\n`{command}`\n\n"
                               f"Search space `{space}`: {SPACES[space]}\n\n{study_table(study)}\n")
        print(f"wrote {args.report}")
    if args.export:
        from firp.core.episodes import EpisodeDataset

        with EpisodeDataset(args.data) as ds:
            task = args.task or str(ds.attrs.get("task", args.data.stem))
        info = export_top_ensemble(study, data, args.data, args.export, task, reliability_png=args.reliability)
        print(f"wrote bundle {args.export}: threshold {info['threshold']:.3f}, ECE {info['ece']:.3f}, "
              f"trials {info['members']}; reliability diagram {info['reliability_png']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
