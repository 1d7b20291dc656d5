"""Training one model (FIRP or a baseline) on cached features: the loop every tool shares.

Follows the paper's learning algorithm: Adam, gradient clipping, the future-prediction terms
switched on from epoch ``e_start_f``, the image-feature projection (e_t) frozen after epoch
``e_stop_e``, early stopping on validation balanced accuracy of the *inference path* (scores from
the initial image only). Seeded: batch order and sampling noise are drawn from generators seeded
by (seed, epoch), so a resumed run continues exactly as an uninterrupted one. Checkpoints are
safetensors (weights) + a JSON state; the optimizer state is loaded with ``weights_only=True``.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from firp.data import SequenceData
from firp.losses import classification_loss, firp_loss, loss_weights
from firp.metrics import balanced_accuracy
from firp.model.baselines import build_model
from firp.model.config import FIRPConfig
from firp.model.rssm import sample_overshooting_distances

FUTURE_TERMS = ("ce_open_loop", "kl", "re", "kl_overshoot", "re_overshoot")


#: Loss weights older configs kept here; they live in ``model.loss`` (LossConfig) alone.
_MOVED_TO_LOSS = {"overshooting": "overshooting", "alpha": "alpha", "beta": "beta"}


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``lr``, ``grad_clip``, ``e_start_f`` and ``e_stop_e`` are four of the paper's
    seven tuned parameters; the other three (lambda, alpha, beta) are loss weights, so they are
    ``model.loss.overshooting``, ``.alpha`` and ``.beta``, like every other weight of the objective."""

    lr: float = 1e-3
    grad_clip: float = 10.0
    e_start_f: int = 0  # epoch at which the future-prediction losses start
    e_stop_e: int = 20  # epoch after which the projection producing e_t is frozen
    kind: str = "firp"
    epochs: int = 40
    batch_size: int = 32
    patience: int = 10  # epochs without a better validation balanced accuracy
    # no early stop before this many epochs: FIRP's open-loop head sits at chance for its first
    # ~15-40 epochs (fewer optimizer steps per epoch on smaller sets), and a patience counted from
    # epoch 0 ended replacement trials at 0.50 (measured: trial 0 of firp-replacement-prod)
    min_epochs: int = 0
    seed: int = 0
    overshooting_n: int = 2  # sampled distances per batch (besides the open loop)
    overshooting_max_tau: int = 60
    overshooting_stride: int = 4
    threads: int = 2
    model: FIRPConfig = field(default_factory=FIRPConfig)

    def fit_to_plans(self, horizon: int) -> "TrainConfig":
        """This recipe for plans of ``horizon`` steps: the flattening baselines (A-MLP, A-MLP + image)
        widen to the dataset's T when it exceeds their ``max_T`` (pick & place's T = 200 against the
        default 120), since a recipe's flags name no horizon; nothing else depends on T."""
        baseline = self.model.baseline
        if horizon <= baseline.max_T:
            return self
        return replace(self, model=replace(self.model, baseline=replace(baseline, max_T=horizon)))

    def fit_to_data(self, data: SequenceData) -> "TrainConfig":
        """This recipe for a dataset: :meth:`fit_to_plans` for its plans' length, and the arm's kinematics from
        the dataset's attributes where the recipe reads the plan's events and names no chain of its own."""
        cfg = self.fit_to_plans(int(data.actions.shape[1]))
        events = cfg.model.events
        if events.enabled and events.kinematics is None:
            if "kinematics" not in data.attrs:
                raise ValueError("events: the recipe reads the plan's events through the arm's kinematics, and the "
                                 "dataset carries none (collect it with --framed or --view-size, which record them)")
            events = replace(events, kinematics=data.attrs["kinematics"])
            cfg = replace(cfg, model=replace(cfg.model, events=events))
        return cfg

    def to_dict(self) -> dict:
        d = asdict(self)
        d["model"] = self.model.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """Inverse of :meth:`to_dict`; a config written when the loss weights were also fields here
        reads back with them in ``model.loss``, where they were applied all along."""
        d = dict(d)
        moved = {loss_key: d.pop(key) for key, loss_key in _MOVED_TO_LOSS.items() if key in d}
        model = dict(d["model"])
        if moved:
            model["loss"] = {**model.get("loss", {}), **moved}
        d["model"] = FIRPConfig.from_dict(model)
        return cls(**d)


@dataclass
class TrainResult:
    model: torch.nn.Module
    best_epoch: int
    best_val_balanced_accuracy: float
    history: list[dict]
    seconds: float


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA where torch sees a GPU, else the CPU), ``cpu`` or ``cuda``; a CUDA request on a machine
    without one is an error that says so, not a silent fall back."""
    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"--device: {name!r} is none of auto, cpu, cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: torch sees no CUDA device here (this torch build: "
                         f"{torch.__version__}); use --device cpu or auto")
    return torch.device("cuda" if name == "cuda" or (name == "auto" and torch.cuda.is_available()) else "cpu")


def _model_device(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


@torch.inference_mode()
def predict(model: torch.nn.Module, data: SequenceData, batch_size: int = 128) -> np.ndarray:
    """Success probabilities (N,) through the inference path (the Oracle reads all frames), on the model's device."""
    model.eval()
    device = _model_device(model)
    probs = []
    for start in range(0, len(data), batch_size):
        sl = slice(start, start + batch_size)
        feats = data.features[sl] if getattr(model, "requires_future_frames", False) else data.features[sl, 0]
        probs.append(torch.sigmoid(model.score(feats.to(device), data.actions[sl].to(device)).logits).cpu())
    return torch.cat(probs).numpy()


def _loss(model: torch.nn.Module, cfg: TrainConfig, feats: torch.Tensor, actions: torch.Tensor, labels: torch.Tensor,
          epoch: int, gen: torch.Generator, framed: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The batch's training loss and its terms (for the log). ``framed`` (B,) bool: which episodes kept every
    frame; the others kept only their initial frame (see :func:`_firp_terms`)."""
    if cfg.kind != "firp":
        out = model.forward_train(feats, actions)
        loss = classification_loss(out["logits"], labels)
        return loss, {"ce": float(loss.detach())}
    total, terms = _firp_terms(model, cfg, feats, actions, labels, epoch, gen, framed)
    return total, {k: float(v.detach()) for k, v in terms.items()}


def _firp_terms(model: torch.nn.Module, cfg: TrainConfig, feats: torch.Tensor, actions: torch.Tensor,
                labels: torch.Tensor, epoch: int, gen: torch.Generator, framed: torch.Tensor | None
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """FIRP's objective (eq. 9 + TCR). Episodes that kept only their initial frame classify the open loop from it
    (:meth:`FIRP.forward_initial`) and add nothing else: the prediction terms and TCR average over the framed
    episodes, the open loop's classification over all. Before ``e_start_f`` (no future terms, no open loop) they
    add nothing at all."""
    future = epoch >= cfg.e_start_f
    weights = loss_weights(model.cfg.loss)
    initial = None if framed is None or bool(framed.all()) else ~framed
    n = int(labels.shape[0])
    n_initial = int(initial.sum()) if initial is not None else 0
    terms: dict[str, torch.Tensor] = {}
    total = labels.new_zeros(())
    if n_initial < n:
        rows = slice(None) if initial is None else ~initial
        f_feats, f_actions, f_labels = feats[rows], actions[rows], labels[rows]
        transitions = -(-actions.shape[1] // model.cfg.action_chunk)  # RSSM steps: ceil(T / k)
        taus = sample_overshooting_distances(transitions, cfg.overshooting_n, cfg.overshooting_max_tau, gen) \
            if future and model.cfg.loss.overshooting > 0 else []
        out = model.forward_train(f_feats, f_actions, overshooting_distances=taus,
                                  overshooting_stride=cfg.overshooting_stride)
        terms = firp_loss(out, f_actions, f_labels, model.cfg.loss)
        total = terms["total"]
        if not future:  # before E_start^f: classification from real features + TCR only
            total = total - sum(weights[k] * terms[k] for k in FUTURE_TERMS)
    if n_initial and future:
        ce_initial = classification_loss(model.forward_initial(feats[initial, 0], actions[initial]), labels[initial],
                                         model.cfg.loss.pos_weight)
        ce_framed = terms.get("ce_open_loop", ce_initial.new_zeros(()))
        ce_all = ((n - n_initial) * ce_framed + n_initial * ce_initial) / n
        total = total + weights["ce_open_loop"] * (ce_all - ce_framed)
        terms["ce_open_loop"] = ce_all
    terms["total"] = total
    return total, terms


def _set_projection_trainable(model: torch.nn.Module, trainable: bool) -> None:
    projection = getattr(model, "projection", None)
    if projection is not None:
        for p in projection.parameters():
            p.requires_grad_(trainable)


def train_model(cfg: TrainConfig, train: SequenceData, valid: SequenceData, checkpoint_dir: str | os.PathLike | None = None,
                progress: bool = True, initial_state: dict[str, torch.Tensor] | None = None,
                device: str = "cpu") -> TrainResult:
    """Train ``cfg.kind`` on ``train``; select the epoch by validation balanced accuracy; resumable.

    ``initial_state`` warm-starts from a trained model of the same config (a bundle member being refreshed):
    its weights *and* its normalisation statistics, which the weights were trained against. ``device``
    (:func:`resolve_device`): where the model and each batch live; the data stays in RAM and the returned
    model is on the CPU (what bundles and the service load)."""
    where = resolve_device(device)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.kind, cfg.model)
    if getattr(model, "requires_future_frames", False) and not (bool(train.framed.all()) and bool(valid.framed.all())):
        raise ValueError(f"{cfg.kind} reads every executed frame: train and validate it on framed episodes only")
    if hasattr(model, "action_norm"):
        model.action_norm.fit(train.actions)  # training-set statistics, saved with the weights
    if getattr(model, "geometry", None) is not None:
        model.geometry.fit(train.actions)  # likewise for the grasp-frame description
    if initial_state is not None:
        model.load_state_dict(initial_state)
    model.to(where)
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    ckpt = Path(checkpoint_dir) if checkpoint_dir else None
    history: list[dict] = []
    best = (-math.inf, -1)
    best_state: dict[str, torch.Tensor] | None = None
    start_epoch = 0
    started = time.perf_counter()
    if ckpt and (ckpt / "state.json").exists():
        state = json.loads((ckpt / "state.json").read_text())
        # through from_dict, so a checkpoint written before a config field existed (default value) resumes
        if TrainConfig.from_dict(state["config"]).to_dict() != cfg.to_dict():
            raise ValueError(f"checkpoint {ckpt} was written by a different training config; use another directory")
        model.load_state_dict(load_file(ckpt / "last.safetensors"))
        optim.load_state_dict(torch.load(ckpt / "optim.pt", weights_only=True, map_location=where))
        best_state = load_file(ckpt / "best.safetensors")
        history, best, start_epoch = state["history"], tuple(state["best"]), state["epoch"] + 1
        if state.get("finished"):
            model.load_state_dict(best_state)
            return TrainResult(model.cpu().eval(), best[1], best[0], history, state["seconds"])
    n = len(train)
    bar = tqdm(range(start_epoch, cfg.epochs), desc=f"train {cfg.kind}", unit="epoch", disable=not progress)
    for epoch in bar:
        model.train()
        _set_projection_trainable(model, epoch <= cfg.e_stop_e)
        gen = torch.Generator().manual_seed(cfg.seed * 100_003 + epoch)
        torch.manual_seed(cfg.seed * 100_003 + epoch)  # reparametrisation noise
        order = torch.randperm(n, generator=gen)
        sums: dict[str, float] = {}
        batches = 0
        for start in range(0, n, cfg.batch_size):
            idx = order[start:start + cfg.batch_size]
            loss, terms = _loss(model, cfg, train.features[idx].to(where), train.actions[idx].to(where),
                                train.labels[idx].to(where), epoch, gen, train.framed[idx].to(where))
            if not loss.requires_grad:  # only initial-frame episodes before e_start_f: nothing to learn from
                continue
            if not torch.isfinite(loss):
                raise FloatingPointError(f"non-finite loss at epoch {epoch}: {terms}")
            optim.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optim.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v
            batches += 1
        probs = predict(model, valid)
        val_ba = balanced_accuracy(valid.labels.numpy() > 0.5, probs >= 0.5)
        record = {"epoch": epoch, "val_balanced_accuracy": val_ba, **{k: v / max(batches, 1) for k, v in sums.items()}}
        history.append(record)
        if val_ba > best[0]:
            best = (val_ba, epoch)
            best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
        bar.set_postfix(loss=f"{record.get('total', record.get('ce')):.3f}", val_ba=f"{val_ba:.3f}", best=f"{best[0]:.3f}")
        stop = epoch - best[1] >= cfg.patience and epoch + 1 >= cfg.min_epochs
        if ckpt:
            _save_checkpoint(ckpt, model, optim, best_state, cfg, history, best, epoch, time.perf_counter() - started, stop
                             or epoch == cfg.epochs - 1)
        if stop:
            break
    bar.close()
    assert best_state is not None
    model.cpu().load_state_dict(best_state)
    return TrainResult(model.eval(), best[1], best[0], history, time.perf_counter() - started)


def _save_checkpoint(ckpt: Path, model, optim, best_state, cfg: TrainConfig, history, best, epoch: int, seconds: float,
                     finished: bool) -> None:
    """Write weights and state to temp names, then replace, so a crash leaves the previous checkpoint."""
    ckpt.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, ckpt / "last.safetensors.tmp")
    save_file({k: v.contiguous() for k, v in best_state.items()}, ckpt / "best.safetensors.tmp")
    torch.save(optim.state_dict(), ckpt / "optim.pt.tmp")
    (ckpt / "state.json.tmp").write_text(json.dumps({
        "config": cfg.to_dict(), "history": history, "best": list(best), "epoch": epoch, "seconds": seconds,
        "finished": finished}))
    for name in ("last.safetensors", "best.safetensors", "optim.pt", "state.json"):
        os.replace(ckpt / f"{name}.tmp", ckpt / name)
