"""The TCR ablation figures of the paper, from a finished evaluation directory (no retraining).

``python -m firp.evaluate`` leaves, per repeat r and method m, the selected weights in
``<eval-dir>/r{r}-{m}/checkpoint/best.safetensors`` (with ``state.json``: the training config and
whether training finished) and the test episodes in ``<eval-dir>/r{r}-{m}.json`` (``test_index``).
For every finished FIRP variant (firp, firp_ttc, firp_atc, firp_tcr) this tool reloads the weights
(safetensors, no pickle) and, on that repeat's test episodes, compares

* the real features ``e_t``: the model's projection of the cached backbone features of the frame
  each RSSM step observes (``FIRP.forward_train(...)["e"]``, run on means), and
* the open-loop predictions ``ê_t``: the prior rolled from ``e_1`` under the plan, exactly what
  inference classifies (``FIRP.score(...).features`` = ``[e_1, ê_2, ..., ê_T]``).

With action chunks (``action_chunk = k``) one RSSM step covers k plan steps, so ``t`` runs over the
``ceil(T / k)`` steps and step j observes frame ``chunk_frame_index(T, k)[j]``; ``e_T`` is the last
step's feature, the last frame's. Then it writes to ``--out``:

* ``prediction_error.png``: box + violin plots per variant (pooled over repeats; each episode a
  dot coloured by its repeat) of ‖e_T − ê_T‖ (the paper's figure) and the scale-free versions;
* ``prediction_error_by_step.png``: the mean scale-free error at every RSSM step;
* ``tsne.png``: t-SNE of real feature trajectories of a subsample of one repeat's test episodes,
  each point coloured by the plan's action category at that step, one panel per variant;
* ``ablation.json`` (every number, per episode) and ``ablation.md`` (mean ± std over repeats per
  variant, a per-repeat table, the command).

    python -m experiments.tcr_ablation --eval-dir runs/eval-stacking-protocol --data data/stacking.h5 \\
        --out docs/results/stacking_tcr_ablation

Missing or unfinished checkpoints are skipped with a message naming them; an evaluation directory
without a single finished FIRP-variant checkpoint is an error. ``--data`` must be the evaluated
dataset: the tool recomputes every model's test scores and warns when they differ from the ones
the evaluation recorded (wrong dataset, indices or weights).
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from safetensors.torch import load_file
from tqdm import tqdm

from firp.core.cli_types import int_in_range, positive_float
from firp.core.contract import CATEGORIES
from firp.data import SequenceData, load_sequences
from firp.evaluate import FIRP_VARIANTS, parse_run_name, run_name
from firp.features import DEFAULT_CACHE_DIR
from firp.losses import atc, ttc
from firp.model.baselines import build_model
from firp.model.firp import FIRP, chunk_frame_index
from firp.train import TrainConfig

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Display names, as in the paper's figures.
LABELS = {"firp": "FIRP", "firp_ttc": "FIRP + TTC", "firp_atc": "FIRP + ATC", "firp_tcr": "FIRP + TCR"}

#: Per-episode prediction-error metrics: key -> (short label for tables and axes, what it is).
METRICS: dict[str, tuple[str, str]] = {
    "final_l2": ("‖e_T − ê_T‖", "Euclidean distance at the last step (the paper's figure)"),
    "final_rel": ("‖e_T − ê_T‖ / s", "the same divided by s, the model's mean ‖e_t‖ over its test episodes and steps"),
    "final_cos": ("1 − cos(e_T, ê_T)", "cosine distance at the last step (ignores scale entirely)"),
    "final_vs_mean": ("‖e_T − ê_T‖ / ‖e_T − ē_T‖", "final distance over the mean distance of e_T from the test "
                                                   "set's mean e_T: < 1 means the rollout beats a constant guess"),
    "mean_l2": ("mean_t ‖e_t − ê_t‖", "Euclidean distance averaged over the predicted steps t = 2..T"),
    "mean_rel": ("mean_t ‖e_t − ê_t‖ / s", "the same divided by s"),
    "mean_cos": ("mean_t 1 − cos", "cosine distance averaged over the predicted steps t = 2..T"),
}
#: Per-model feature statistics on the real test features.
FEATURE_STATS: dict[str, tuple[str, str]] = {
    "scale": ("s = mean ‖e_t‖", "mean norm of the real features (the scale the scale-free errors divide by)"),
    "spread": ("mean ‖e_T − ē_T‖", "how much the last feature varies over test episodes"),
    "r_ttc": ("R_TTC(e)", "the TTC regulariser (firp.losses.ttc) on the real test features"),
    "r_atc": ("R_ATC(e)", "the ATC regulariser (firp.losses.atc) on the real test features, lower = more consistent"),
    "silhouette": ("silhouette by category", "silhouette score of the real e_t grouped by action category (cosine; "
                                             "higher = features localised by category, what the t-SNE shows)"),
    "test_balanced_accuracy": ("test balanced accuracy", "from the evaluation's r{r}-{m}.json"),
}


#: ``r{repeat}-{method}``: the evaluation's name of a run (its row file's stem and its directory).


@dataclass(frozen=True)
class Checkpoint:
    """One finished FIRP-variant run of the evaluation."""

    repeat: int
    method: str
    weights: Path
    config: TrainConfig
    row: dict  # the evaluation's r{r}-{m}.json


def find_checkpoints(eval_dir: Path, methods: tuple[str, ...], repeats: set[int] | None = None
                     ) -> tuple[list[Checkpoint], list[str]]:
    """Every finished checkpoint of ``methods`` in ``eval_dir``, and a message per skipped one.

    A run counts as finished when its ``state.json`` says so *and* the evaluation wrote its row
    (which holds the test indices): an interrupted evaluation leaves a checkpoint without a row,
    and a row is only written after training returned.
    """
    runs: set[tuple[int, str]] = set()  # (repeat, method) with a row file or a run directory
    for path in eval_dir.iterdir():
        parsed = parse_run_name(path.stem if path.suffix == ".json" else path.name)
        if parsed and parsed[1] in methods:
            runs.add(parsed)
    out, skipped = [], []
    for repeat, method in sorted(runs, key=lambda rm: (rm[0], methods.index(rm[1]))):
        if repeats is not None and repeat not in repeats:
            continue
        name = run_name(repeat, method)
        row_path, ckpt = eval_dir / f"{name}.json", eval_dir / name / "checkpoint"
        state_path, weights = ckpt / "state.json", ckpt / "best.safetensors"
        if not state_path.exists() or not weights.exists():
            skipped.append(f"{name}: skipped, no checkpoint ({state_path.name} and {weights.name} in {ckpt})")
            continue
        state = json.loads(state_path.read_text())
        if not state.get("finished"):
            skipped.append(f"{name}: skipped, training not finished (epoch {state.get('epoch')} in {state_path})")
            continue
        if not row_path.exists():
            skipped.append(f"{name}: skipped, training finished but the evaluation did not write {row_path} yet")
            continue
        cfg = TrainConfig.from_dict(state["config"])
        if cfg.kind != "firp":
            skipped.append(f"{name}: skipped, model kind {cfg.kind!r} is not FIRP")
            continue
        out.append(Checkpoint(repeat, method, weights, cfg, json.loads(row_path.read_text())))
    return out, skipped


def load_model(ckpt: Checkpoint) -> FIRP:
    """The selected weights of ``ckpt`` in a FIRP built from its own config (safetensors, no pickle).

    The loss weights of the config do not change the forward pass, so the model is built from the
    checkpoint's model config as written; ``strict`` loading fails on any architecture mismatch.
    """
    model = build_model(ckpt.config.kind, ckpt.config.model)
    model.load_state_dict(load_file(ckpt.weights), strict=True)
    return model.eval()


@torch.inference_mode()
def feature_trajectories(model: FIRP, data: SequenceData, batch_size: int = 64) -> dict[str, np.ndarray]:
    """Real and open-loop predicted features of every episode of ``data``, through the model's own code.

    Returns ``e`` and ``e_hat`` (N, Tc, E) with ``e_hat[:, 0] = e[:, 0]`` (the rollout starts from
    the real e_1), ``categories`` (N, Tc) the plan's category at each step's frame (what ATC uses),
    ``frame_index`` (Tc,) the frame each RSSM step observes, and ``probs`` (N,) the success
    probabilities inference gives (to check against the evaluation's recorded scores).
    """
    es, hats, cats, probs = [], [], [], []
    for start in range(0, len(data), batch_size):
        feats, actions = data.features[start:start + batch_size], data.actions[start:start + batch_size]
        out = model.forward_train(feats, actions, sample=False)  # e on the chunk frames, no sampling
        score = model.score(feats[:, 0], actions)  # inference: from e_1 only, on means
        es.append(out["e"]), hats.append(score.features), cats.append(out["categories"])
        probs.append(torch.sigmoid(score.logits))
    T, k = data.actions.shape[1], model.cfg.action_chunk
    return {"e": torch.cat(es).numpy(), "e_hat": torch.cat(hats).numpy(), "categories": torch.cat(cats).numpy(),
            "frame_index": np.asarray(chunk_frame_index(T, k)), "probs": torch.cat(probs).numpy()}


def prediction_errors(e: np.ndarray, e_hat: np.ndarray) -> dict[str, np.ndarray]:
    """Per-episode errors of the open-loop prediction (see :data:`METRICS`), plus per-step curves.

    Why scale-free versions: ``e_t`` is the output of a projection each variant trains differently
    (TCR's terms act on it; with ``feature_norm = "none"`` nothing fixes its scale), so a raw
    distance also measures how large the features are: a model with features half as long has
    errors half as large without predicting any better. Dividing by the model's own mean ‖e_t‖
    (``_rel``) compares errors relative to the features' size; the cosine distance ignores length
    altogether (the success head reads the predicted features through cosine attention, so their
    direction is what it uses). Neither catches features that barely differ between episodes,
    which are easy to "predict" by a constant; ``final_vs_mean`` divides by the error of exactly
    that constant (the test set's mean e_T), so it is < 1 only when the rollout knows something
    about this episode. Step 0 is left out of the means over t: ê_1 = e_1 by construction.

    With the default encoder (``feature_norm = "layernorm"``, no affine) every real e_t has norm
    √E, so s is the same for every variant and the raw and divided errors differ by that constant;
    the predicted ê_t are not normalised, which the cosine distance separates from direction.
    """
    diff = np.linalg.norm(e - e_hat, axis=-1)  # (N, Tc)
    norm_e, norm_hat = np.linalg.norm(e, axis=-1), np.linalg.norm(e_hat, axis=-1)
    cos = 1.0 - np.sum(e * e_hat, axis=-1) / np.maximum(norm_e * norm_hat, 1e-12)  # (N, Tc)
    scale = float(norm_e.mean())
    spread = np.linalg.norm(e[:, -1] - e[:, -1].mean(axis=0), axis=-1)  # (N,)
    pred = slice(1, None) if e.shape[1] > 1 else slice(None)
    return {
        "final_l2": diff[:, -1], "final_rel": diff[:, -1] / scale, "final_cos": cos[:, -1],
        "final_vs_mean": diff[:, -1] / max(float(spread.mean()), 1e-12),
        "mean_l2": diff[:, pred].mean(axis=1), "mean_rel": diff[:, pred].mean(axis=1) / scale,
        "mean_cos": cos[:, pred].mean(axis=1),
        "step_rel": diff.mean(axis=0) / scale, "step_cos": cos.mean(axis=0),  # (Tc,) curves
        "scale": np.float64(scale), "spread": np.float64(spread.mean()),
    }


def category_silhouette(e: np.ndarray, categories: np.ndarray) -> float | None:
    """Silhouette of the real features grouped by action category (cosine), or None if undefined."""
    from sklearn.metrics import silhouette_score

    x, y = e.reshape(-1, e.shape[-1]), categories.reshape(-1)
    if not 2 <= len(np.unique(y)) < len(y):
        return None
    return float(silhouette_score(x, y, metric="cosine"))


def _rounded(values: np.ndarray) -> list[float]:
    """A JSON list at 6 decimals: per-episode numbers without float noise bloating the file."""
    return [round(float(v), 6) for v in np.asarray(values).reshape(-1)]


def analyse(model: FIRP, ckpt: Checkpoint, test: SequenceData, traj: dict[str, np.ndarray]) -> dict:
    """All numbers of one checkpoint on its repeat's test episodes ``test`` (``traj``: their
    :func:`feature_trajectories`)."""
    err = prediction_errors(traj["e"], traj["e_hat"])
    e_t = torch.from_numpy(traj["e"])
    recorded = np.asarray(ckpt.row.get("test_scores", []), dtype=np.float64)
    score_diff = float(np.max(np.abs(recorded - traj["probs"]))) if len(recorded) == len(test) else None
    return {
        "repeat": ckpt.repeat, "method": ckpt.method, "weights": str(ckpt.weights), "n_test": len(test),
        "test_index": [int(i) for i in ckpt.row["test_index"]],
        "labels": [int(v) for v in test.labels.numpy()],
        "action_chunk": model.cfg.action_chunk, "frame_index": [int(i) for i in traj["frame_index"]],
        "alpha": ckpt.config.model.loss.alpha, "beta": ckpt.config.model.loss.beta,
        "test_balanced_accuracy": ckpt.row.get("test_balanced_accuracy"),
        "recorded_score_max_abs_diff": score_diff,
        "scale": float(err["scale"]), "spread": float(err["spread"]),
        "r_ttc": float(ttc(e_t)), "r_atc": float(atc(e_t, torch.from_numpy(traj["categories"]),
                                                     alignment=model.cfg.loss.atc_alignment)),
        "silhouette": category_silhouette(traj["e"], traj["categories"]),
        "per_episode": {m: _rounded(err[m]) for m in METRICS},
        "per_step": {"rel": _rounded(err["step_rel"]), "cos": _rounded(err["step_cos"])},
        "mean": {m: float(np.mean(err[m])) for m in METRICS},
    }


def _mean_std(values: list[float]) -> dict:
    return {"mean": statistics.mean(values), "std": statistics.stdev(values) if len(values) > 1 else 0.0,
            "n_repeats": len(values), "per_repeat": values}


def summarise(results: list[dict], methods: tuple[str, ...]) -> dict[str, dict]:
    """Per variant: mean ± std over repeats of each repeat's mean (episodes pooled within a repeat)."""
    out: dict[str, dict] = {}
    for m in methods:
        rows = [r for r in results if r["method"] == m]
        if not rows:
            continue
        summary: dict[str, object] = {"repeats": [r["repeat"] for r in rows],
                                      "n_episodes": sum(r["n_test"] for r in rows)}
        for key in METRICS:
            summary[key] = _mean_std([r["mean"][key] for r in rows])
        for key in FEATURE_STATS:
            vals = [r[key] for r in rows if r.get(key) is not None]
            summary[key] = _mean_std(vals) if vals else None
        out[m] = summary
    return out


def _fmt(s: dict | None, digits: int = 3) -> str:
    """``mean ± std`` over repeats; the mean alone for one repeat (a std of 0 would claim a spread)."""
    if not s:
        return "—"
    return f"{s['mean']:.{digits}f}" if s["n_repeats"] == 1 else f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def markdown(summary: dict[str, dict], results: list[dict], command: str, skipped: list[str], tsne: dict | None,
             seconds: float) -> str:
    """The summary table (mean ± std over repeats), a per-repeat table, what each column means."""
    cols = ["final_l2", "final_rel", "final_cos", "final_vs_mean", "mean_rel"]
    stats = ["scale", "r_ttc", "r_atc", "silhouette", "test_balanced_accuracy"]
    lines = ["# TCR ablation: open-loop prediction errors and feature statistics", "", f"`{command}`", "",
             f"{seconds:.0f} s. Test episodes of every repeat; mean ± std over repeats of the per-repeat means "
             "(the mean alone when there is one repeat).", "",
             "| variant | repeats | episodes | " + " | ".join(METRICS[c][0] for c in cols) + " | "
             + " | ".join(FEATURE_STATS[c][0] for c in stats) + " |",
             "|---|---|---|" + "---|" * (len(cols) + len(stats))]
    for m, s in summary.items():
        lines.append(f"| {LABELS[m]} | {len(s['repeats'])} | {s['n_episodes']} | "
                     + " | ".join(_fmt(s[c]) for c in cols) + " | " + " | ".join(_fmt(s[c]) for c in stats) + " |")
    lines += ["", "Per repeat (means over the repeat's test episodes):", "",
              "| repeat | variant | n | ‖e_T − ê_T‖ | ‖e_T − ê_T‖ / s | 1 − cos at T | vs constant | s | "
              "test BA | recomputed − recorded score (max) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        diff = r["recorded_score_max_abs_diff"]
        ba = r["test_balanced_accuracy"]
        lines.append(f"| {r['repeat']} | {LABELS[r['method']]} | {r['n_test']} | {r['mean']['final_l2']:.3f} | "
                     f"{r['mean']['final_rel']:.3f} | {r['mean']['final_cos']:.3f} | {r['mean']['final_vs_mean']:.3f} | "
                     f"{r['scale']:.3f} | {'—' if ba is None else f'{ba:.3f}'} | "
                     f"{'—' if diff is None else f'{diff:.1e}'} |")
    lines += ["", "Columns:", ""] + [f"- **{lab}**: {why}" for lab, why in METRICS.values()] \
        + [f"- **{lab}**: {why}" for lab, why in FEATURE_STATS.values()]
    lines += ["", "Figures: `prediction_error.png` (box + violin per variant, dots = episodes coloured by repeat), "
              "`prediction_error_by_step.png`, `tsne.png`."]
    if tsne:
        lines.append(f"t-SNE: repeat {tsne['repeat']}, {len(tsne['episodes'])} test episodes "
                     f"(dataset indices {tsne['episodes']}), {tsne['features']} features, perplexity "
                     f"{tsne['perplexity']:g}, seed {tsne['seed']}.")
    if skipped:
        lines += ["", "Skipped:", ""] + [f"- {s}" for s in skipped]
    return "\n".join(lines) + "\n"


# figures ---------------------------------------------------------------------------------------

def _figure(nrows: int, ncols: int, size: tuple[float, float]) -> tuple["Figure", np.ndarray]:
    """A matplotlib Figure on the Agg canvas (no pyplot: no global state, no display)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def plot_errors(results: list[dict], methods: list[str], path: Path) -> None:
    """2 × 2 panels of box + violin plots per variant; every episode a dot coloured by its repeat."""
    from matplotlib import colormaps

    panels = ["final_l2", "final_rel", "final_cos", "mean_rel"]
    fig, axes = _figure(2, 2, (4.2 + 1.3 * len(methods), 8))
    repeats = sorted({r["repeat"] for r in results})
    colours = {rep: colormaps["tab10"](i % 10) for i, rep in enumerate(repeats)}
    jitter = np.random.default_rng(0)
    for ax, key in zip(axes.flat, panels):
        pooled = [np.concatenate([r["per_episode"][key] for r in results if r["method"] == m]) for m in methods]
        pos = np.arange(1, len(methods) + 1)
        if all(len(v) > 1 for v in pooled):
            parts = ax.violinplot(pooled, positions=pos, showextrema=False, widths=0.8)
            for body in parts["bodies"]:
                body.set_facecolor("tab:grey"), body.set_alpha(0.25)
        ax.boxplot(pooled, positions=pos, widths=0.25, showfliers=False, medianprops={"color": "black"})
        for i, m in enumerate(methods):
            for r in results:
                if r["method"] == m:
                    y = np.asarray(r["per_episode"][key])
                    ax.scatter(pos[i] + jitter.uniform(-0.3, 0.3, len(y)), y, s=5, alpha=0.5, color=colours[r["repeat"]],
                               linewidths=0)
        ax.set_xticks(pos, [LABELS[m] for m in methods])
        ax.set_title(METRICS[key][0])
        ax.grid(axis="y", alpha=0.3)
    handles = [axes[0, 0].scatter([], [], s=15, color=colours[rep], label=f"repeat {rep}") for rep in repeats]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(repeats), 8), fontsize="small", frameon=False)
    fig.suptitle("Open-loop prediction error on test episodes (ê from e_1 under the plan)")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, format="png", dpi=110)


def plot_by_step(results: list[dict], methods: list[str], path: Path) -> None:
    """Mean scale-free error at each RSSM step per variant; the band is ± std over repeats."""
    fig, axes = _figure(1, 2, (11, 4))
    for ax, key, title in ((axes[0, 0], "rel", "‖e_t − ê_t‖ / s"), (axes[0, 1], "cos", "1 − cos(e_t, ê_t)")):
        for m in methods:
            rows = [r for r in results if r["method"] == m]
            curves = np.asarray([r["per_step"][key] for r in rows])
            x = np.asarray(rows[0]["frame_index"])
            mean, std = curves.mean(axis=0), curves.std(axis=0)
            ax.plot(x, mean, marker=".", label=f"{LABELS[m]} ({len(rows)} repeat{'' if len(rows) == 1 else 's'})")
            ax.fill_between(x, mean - std, mean + std, alpha=0.15)
        ax.set_xlabel("plan step of the observed frame")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=110)


def tsne_embedding(e: np.ndarray, perplexity: float, seed: int) -> tuple[np.ndarray, float]:
    """2-D t-SNE of ``e`` (n, E); the perplexity is lowered if there are too few points for it."""
    from sklearn.manifold import TSNE

    p = float(min(perplexity, max(1.0, (len(e) - 1) / 3)))
    return TSNE(n_components=2, perplexity=p, init="pca", random_state=seed).fit_transform(e), p


def plot_tsne(panels: list[tuple[str, np.ndarray, np.ndarray]], path: Path, subtitle: str) -> None:
    """One panel per variant: ``(method, xy (n_ep, Tc, 2), categories (n_ep, Tc))``; grey lines join an
    episode's steps, a ring marks its first step."""
    from matplotlib import colormaps

    fig, axes = _figure(1, len(panels), (4.2 * len(panels), 4.6))
    cmap = colormaps["tab10"]
    for ax, (method, xy, cats) in zip(axes.flat, panels):
        for ep in range(xy.shape[0]):
            ax.plot(xy[ep, :, 0], xy[ep, :, 1], color="grey", alpha=0.25, linewidth=0.6)
        ax.scatter(xy[:, 0, 0], xy[:, 0, 1], s=40, facecolors="none", edgecolors="black", linewidths=0.6)
        ax.scatter(xy[..., 0].ravel(), xy[..., 1].ravel(), c=[cmap(int(c)) for c in cats.ravel()], s=9)
        ax.set_title(LABELS[method])
        ax.set_xticks([]), ax.set_yticks([])
    handles = [axes[0, 0].scatter([], [], s=20, color=cmap(i), label=name) for i, name in enumerate(CATEGORIES)]
    fig.legend(handles=handles, loc="lower center", ncol=len(CATEGORIES), fontsize="small", frameon=False)
    fig.suptitle(f"t-SNE of feature trajectories, coloured by action category ({subtitle})")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, format="png", dpi=110)


# command line ----------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m experiments.tcr_ablation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--eval-dir", type=Path, required=True, help="a python -m firp.evaluate output directory")
    parser.add_argument("--data", type=Path, required=True, help="the dataset that was evaluated")
    parser.add_argument("--out", type=Path, default=None,
                        help="output directory (default docs/results/<data stem>_tcr_ablation)")
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE_DIR, help="backbone feature cache")
    parser.add_argument("--methods", nargs="+", choices=FIRP_VARIANTS, default=list(FIRP_VARIANTS))
    parser.add_argument("--repeats", nargs="+", type=int_in_range("--repeats", 0, 999), default=None,
                        help="only these repeats (default: every finished one)")
    parser.add_argument("--tsne-repeat", type=int_in_range("--tsne-repeat", 0, 999), default=None,
                        help="repeat whose test episodes the t-SNE shows (default: the first with the most variants)")
    parser.add_argument("--tsne-episodes", type=int_in_range("--tsne-episodes", 1, 100_000), default=16,
                        help="test episodes in the t-SNE subsample (each gives ceil(T / action_chunk) points)")
    parser.add_argument("--tsne-features", choices=("real", "predicted"), default="real",
                        help="embed the real e_t (the paper's figure) or the open-loop ê_t")
    parser.add_argument("--perplexity", type=positive_float("--perplexity"), default=30.0)
    parser.add_argument("--seed", type=int, default=0, help="t-SNE subsample and embedding seed")
    parser.add_argument("--threads", type=int_in_range("--threads", 1, 64), default=1)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if not args.eval_dir.is_dir():
        parser.error(f"--eval-dir: {args.eval_dir} is not a directory (write one with python -m firp.evaluate)")
    if not args.data.exists():
        parser.error(f"--data: {args.data} does not exist")
    methods = tuple(m for m in FIRP_VARIANTS if m in args.methods)
    checkpoints, skipped = find_checkpoints(args.eval_dir, methods, set(args.repeats) if args.repeats else None)
    for msg in skipped:
        print(msg, flush=True)
    if not checkpoints:
        parser.error(f"--eval-dir: no finished FIRP-variant checkpoint in {args.eval_dir} (looked for "
                     f"r<repeat>-<{'|'.join(methods)}>/checkpoint/ with state.json 'finished' and r<repeat>-<variant>.json)")
    out = args.out or Path("docs/results") / f"{args.data.stem}_tcr_ablation"
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    started = time.perf_counter()

    by_encoder: dict[str, list[Checkpoint]] = {}
    for c in checkpoints:  # one data load per encoder config (normally all checkpoints share one)
        by_encoder.setdefault(json.dumps(asdict(c.config.model.encoder), sort_keys=True), []).append(c)
    results, dataset_hash, warnings = [], None, []
    recorded_hash = None
    if (args.eval_dir / "results.json").exists():
        recorded_hash = json.loads((args.eval_dir / "results.json").read_text()).get("dataset_hash")
    tsne_input: dict[tuple[int, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for group in by_encoder.values():
        data = load_sequences(args.data, group[0].config.model.encoder, args.cache_dir, progress=not args.no_progress)
        dataset_hash = data.dataset_hash
        if recorded_hash and recorded_hash != dataset_hash:
            warnings.append(f"{args.data} (hash {dataset_hash[:12]}) is not the dataset the evaluation recorded "
                            f"({recorded_hash[:12]})")
        for c in tqdm(group, desc="checkpoints", unit="model", disable=args.no_progress):
            if max(c.row["test_index"]) >= len(data):
                parser.error(f"--data: r{c.repeat}-{c.method}.json indexes episode {max(c.row['test_index'])} but "
                             f"{args.data} has {len(data)}: not the evaluated dataset")
            model = load_model(c)
            test = data.subset(np.asarray(c.row["test_index"]))
            traj = feature_trajectories(model, test)
            res = analyse(model, c, test, traj)
            diff = res["recorded_score_max_abs_diff"]
            if diff is None or diff > 1e-3:
                warnings.append(f"r{c.repeat}-{c.method}: recomputed test scores differ from the recorded ones "
                                f"(max |diff| {diff}); check --data and the checkpoint")
            results.append(res)
            tsne_input[(c.repeat, c.method)] = (traj["e" if args.tsne_features == "real" else "e_hat"],
                                                traj["categories"], np.asarray(c.row["test_index"]))
    for w in warnings:
        print(f"warning: {w}", flush=True)
    results.sort(key=lambda r: (r["repeat"], methods.index(r["method"])))
    present = [m for m in methods if any(r["method"] == m for r in results)]
    summary = summarise(results, methods)

    # t-SNE: one repeat (same test episodes for every variant), a seeded subsample of its episodes
    repeats = sorted({r["repeat"] for r in results})
    if args.tsne_repeat is not None and args.tsne_repeat not in repeats:
        parser.error(f"--tsne-repeat: repeat {args.tsne_repeat} has no finished FIRP checkpoint (have {repeats})")
    tsne_repeat = args.tsne_repeat if args.tsne_repeat is not None else \
        max(repeats, key=lambda rep: (sum((rep, m) in tsne_input for m in methods), -rep))
    panels, tsne_info = [], None
    for m in tqdm([m for m in methods if (tsne_repeat, m) in tsne_input], desc="t-SNE", unit="panel",
                  disable=args.no_progress):
        feats, cats, index = tsne_input[(tsne_repeat, m)]
        pick = np.sort(np.random.default_rng(args.seed).choice(len(index), min(args.tsne_episodes, len(index)),
                                                               replace=False))
        x = feats[pick]  # (n_ep, Tc, E)
        xy, perplexity = tsne_embedding(x.reshape(-1, x.shape[-1]), args.perplexity, args.seed)
        panels.append((m, xy.reshape(x.shape[0], x.shape[1], 2), cats[pick]))
        tsne_info = {"repeat": tsne_repeat, "episodes": [int(i) for i in index[pick]], "features": args.tsne_features,
                     "perplexity": perplexity, "seed": args.seed, "methods": [p[0] for p in panels]}

    plot_errors(results, present, out / "prediction_error.png")
    plot_by_step(results, present, out / "prediction_error_by_step.png")
    plot_tsne(panels, out / "tsne.png", f"repeat {tsne_repeat}, {len(tsne_info['episodes'])} test episodes, "
              f"{args.tsne_features} features")
    seconds = time.perf_counter() - started
    command = f"python -m experiments.tcr_ablation {shlex.join(argv)}"
    (out / "ablation.json").write_text(json.dumps({
        "command": command, "eval_dir": str(args.eval_dir), "dataset": str(args.data), "dataset_hash": dataset_hash,
        "seconds": round(seconds, 1),
        "machine": {"python": platform.python_version(), "torch": torch.__version__, "threads": args.threads},
        "metrics": {k: {"label": lab, "meaning": why} for k, (lab, why) in {**METRICS, **FEATURE_STATS}.items()},
        "skipped": skipped, "warnings": warnings, "summary": summary, "tsne": tsne_info, "models": results,
        "categories": list(CATEGORIES)}, indent=1))
    md = markdown(summary, results, command, skipped, tsne_info, seconds)
    (out / "ablation.md").write_text(md)
    print(md)
    print(f"wrote {out}/ablation.json, ablation.md, prediction_error.png, prediction_error_by_step.png, tsne.png "
          f"({seconds:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
