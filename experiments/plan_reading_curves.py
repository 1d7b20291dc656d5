"""Which reading of the plan learns the outcome best, and how it grows with episodes: learning curves.

The question: with no task-specific numbers in it, can a learned reading of the plan reach what the hand-built
descriptions reach, given the episodes that cost little to collect (initial image and plan, no per-step
frames)? Every learner gets the same fixed test episodes (a stratified fifth of the dataset, seed 0) and
nested training sets of growing size drawn from the rest (each with its own stratified fifth for validation:
early stopping and the threshold). Learners, ``INPUT:LEARNER``:

* ``raw:gb`` -- gradient boosting on the raw plan (the joint targets every 4th step): generic, no model;
* ``grasp_frame:gb``, ``grasp_frame:mlp`` -- gradient boosting / a small MLP on the hand-built grasp-frame
  description (:mod:`firp.model.plan_geometry`, written for cubes and a Panda): the bar to beat;
* ``events:gb`` -- gradient boosting on the same generic numbers the relation network reads (each event's
  hand pose, category, time and gripper; every other event's offset, distance and relative rotation in its
  hand frame), flattened: whether the information is there, apart from how a network learns it;
* ``events:net`` -- the product's generic reading (:mod:`firp.model.plan_events`: the plan's events through
  the dataset's kinematics, a relation network) with a linear score, trained end to end;
* ``events_view:net`` -- the same, each event also reading the initial image where its hand is
  (:mod:`firp.model.plan_view`), for datasets that carry a view;
* ``events_final_view:net`` -- an Oracle: the same, reading the settled *final* scene at the plan's events
  (``firp collect --final-view``), which shows the outcome.

Each (learner, size, repeat) is one JSON line of ``--out`` as it finishes, so a run resumes; ``--plot`` draws
the curves (balanced accuracy against training episodes, log-2 axis).

    python -m experiments.plan_reading_curves --data data/stacking_8000.h5 --sizes 640 1280 2560 5120 \\
        --learners raw:gb grasp_frame:gb grasp_frame:mlp events:net --out runs/plan_reading.jsonl \\
        --plot docs/results/plan_reading/stacking.png
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from experiments.resumable import append_record
from firp.core.episodes import EpisodeDataset
from firp.data import stratified_split
from firp.metrics import balanced_accuracy, choose_threshold
from planner_client.loop import read_records

LEARNERS = ("raw:gb", "grasp_frame:gb", "grasp_frame:mlp", "events:gb", "events:net", "events_view:net",
            "events_final_view:net")


def split_pool(labels: np.ndarray, sizes: list[int], repeat: int) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The fixed test set (a stratified fifth, seed 0) and, per size, the training episodes of ``repeat``:
    nested prefixes of one shuffle of the rest (seed ``repeat``)."""
    rest, test = stratified_split(labels, 0.2, seed=0)
    order = np.random.default_rng(1000 + repeat).permutation(rest)
    too_big = [n for n in sizes if n > len(order)]
    if too_big:
        raise SystemExit(f"--sizes: {too_big} exceed the {len(order)} episodes outside the test set")
    return test, {n: np.sort(order[:n]) for n in sizes}


def inner_split(labels: np.ndarray, train: np.ndarray, repeat: int) -> tuple[np.ndarray, np.ndarray]:
    """A training set's own (fit, validation) split: a stratified fifth for early stopping and the threshold."""
    fit, valid = stratified_split(labels[train], 0.2, seed=2000 + repeat)
    return train[fit], train[valid]


def scores(y_valid: np.ndarray, p_valid: np.ndarray, y_test: np.ndarray, p_test: np.ndarray) -> dict:
    from sklearn.metrics import roc_auc_score

    threshold, _ = choose_threshold(y_valid, p_valid)
    return {"test_balanced_accuracy": balanced_accuracy(y_test, p_test >= 0.5),
            "test_balanced_accuracy_valid_threshold": balanced_accuracy(y_test, p_test >= threshold),
            "test_auc": float(roc_auc_score(y_test, p_test)), "valid_threshold": float(threshold)}


# -- inputs ---------------------------------------------------------------------------------------


def raw_plan(actions: np.ndarray) -> np.ndarray:
    """The joint and gripper targets every 4th step, flattened: the plan with nothing computed from it."""
    return actions[:, ::4, 7:].reshape(len(actions), -1)


def grasp_frame(actions: np.ndarray) -> np.ndarray:
    from firp.model.plan_geometry import plan_geometry

    with torch.no_grad():
        return np.concatenate([plan_geometry(torch.from_numpy(actions[i:i + 512]).double()).numpy()
                               for i in range(0, len(actions), 512)])


# -- learners -------------------------------------------------------------------------------------


def fit_gb(X: np.ndarray, y: np.ndarray, fit: np.ndarray, valid: np.ndarray, test: np.ndarray) -> dict:
    from sklearn.ensemble import HistGradientBoostingClassifier

    model = HistGradientBoostingClassifier(max_iter=400, learning_rate=0.05, random_state=0,
                                           early_stopping=True, validation_fraction=0.15)
    model.fit(X[fit], y[fit])
    return scores(y[valid], model.predict_proba(X[valid])[:, 1], y[test], model.predict_proba(X[test])[:, 1])


def fit_small_mlp(X: np.ndarray, y: np.ndarray, fit: np.ndarray, valid: np.ndarray, test: np.ndarray) -> dict:
    from experiments.grasp_clearance import fit_mlp

    best = None
    for seed in range(3):
        model = fit_mlp(X[fit], y[fit], seed)
        p_valid = model.predict_proba(X[valid])[:, 1]
        valid_score = choose_threshold(y[valid], p_valid)[1]
        if best is None or valid_score > best[0]:
            best = (valid_score, scores(y[valid], p_valid, y[test], model.predict_proba(X[test])[:, 1]))
    return best[1]


class EventClassifier(torch.nn.Module):
    """The plan's events (and, with a view, what the image shows at them) -> a success logit."""

    def __init__(self, events: torch.nn.Module):
        super().__init__()
        self.events = events
        self.out = torch.nn.Sequential(torch.nn.ReLU(), torch.nn.Linear(events.dim, 1))

    def forward(self, actions: torch.Tensor, train: bool = False, **view) -> torch.Tensor:
        return self.out(self.events(actions, augment=train and bool(view), **view)).squeeze(-1)


def fit_net(build, inputs: dict[str, torch.Tensor], y: np.ndarray, fit: np.ndarray, valid: np.ndarray,
            test: np.ndarray, seed: int, epochs: int = 300, patience: int = 15, batch: int = 64,
            min_steps: int = 1500) -> dict:
    """Adam on the binary cross-entropy, the epoch kept by validation balanced accuracy (at its best threshold).

    The relation network sits near chance for its first few hundred optimizer steps, so early stopping starts
    counting only after ``min_steps`` steps (many epochs on a small set, few on a large one)."""
    min_epochs = -(-min_steps // -(-len(fit) // batch))
    torch.manual_seed(seed)
    model = build()
    model.events.fit(inputs["actions"][torch.from_numpy(fit)])
    optim = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-4)
    labels = torch.from_numpy(y.astype(np.float32))
    gen = torch.Generator().manual_seed(seed)

    def predict(index: np.ndarray) -> np.ndarray:
        model.eval()
        out = []
        with torch.no_grad():
            for i in range(0, len(index), 256):
                sl = torch.from_numpy(index[i:i + 256])
                out.append(torch.sigmoid(model(**{k: v[sl] for k, v in inputs.items()})))
        return torch.cat(out).numpy()

    best, best_state, since = -1.0, None, 0
    for epoch in range(epochs):
        model.train()
        order = torch.from_numpy(fit)[torch.randperm(len(fit), generator=gen)]
        for i in range(0, len(order), batch):
            sl = order[i:i + batch]
            loss = torch.nn.functional.binary_cross_entropy_with_logits(
                model(train=True, **{k: v[sl] for k, v in inputs.items()}), labels[sl])
            optim.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            optim.step()
        valid_score = choose_threshold(y[valid], predict(valid))[1]
        if valid_score > best:
            best, since = valid_score, 0
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        else:
            since += 1
            if since >= patience and epoch + 1 >= min_epochs:
                break
    model.load_state_dict(best_state)
    return {**scores(y[valid], predict(valid), y[test], predict(test)), "epochs_run": epoch + 1}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.plan_reading_curves", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--sizes", type=int, nargs="+", required=True)
    parser.add_argument("--learners", nargs="+", default=list(LEARNERS[:4]), choices=LEARNERS)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--view-window", type=float, default=None,
                        help="the view's crops span this many metres (default: the preset's, 0.08)")
    parser.add_argument("--view-crop", type=int, default=None, help="... at this many pixels (default 48)")
    parser.add_argument("--min-steps", type=int, default=1500,
                        help="the networks' optimizer steps before early stopping may end their training")
    parser.add_argument("--out", type=Path, required=True, help="JSON lines, one per (learner, size, repeat)")
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--report", type=Path, default=None, help="also write the summary table (Markdown) here")
    args = parser.parse_args(argv)
    if any(n < 20 for n in args.sizes):
        parser.error("--sizes: each training set needs at least 20 episodes (a fifth of them validate)")
    torch.set_num_threads(args.threads)
    with EpisodeDataset(args.data) as ds:
        names = ds.demo_names
        actions = np.stack([ds.actions(n) for n in names]).astype(np.float32)
        y = ds.success_labels()
        attrs = ds.attrs
    command = shlex.join(["python", "-m", "experiments.plan_reading_curves", *(argv if argv is not None else sys.argv[1:])])
    done = {(r["learner"], r["size"], r["repeat"]) for r in read_records(args.out)}
    suffix = f"@{args.view_window}m" if args.view_window else ""  # a learner with a view records its window
    view = {k: v for k, v in (("view_window", args.view_window), ("view_crop", args.view_crop)) if v is not None}
    cache: dict[str, object] = {}
    for repeat in range(args.repeats):
        test, trains = split_pool(y, args.sizes, repeat)
        for size in args.sizes:
            fit, valid = inner_split(y, trains[size], repeat)
            for learner in args.learners:
                name = learner + (suffix if "view" in learner else "")
                if (name, size, repeat) in done:
                    continue
                started = time.perf_counter()
                result = run_learner(learner, actions, y, attrs, args.data, fit, valid, test, repeat, cache,
                                     args.min_steps, view)
                record = {"learner": name, "size": size, "repeat": repeat, "n_fit": len(fit), "n_valid": len(valid),
                          "n_test": len(test), **result, "seconds": round(time.perf_counter() - started, 1),
                          "dataset": str(args.data), "command": command}
                append_record(args.out, record)
                print(f"{learner:>18} n={size:>5} r{repeat}: balanced accuracy {result['test_balanced_accuracy']:.3f} "
                      f"(valid threshold {result['test_balanced_accuracy_valid_threshold']:.3f}, "
                      f"AUC {result['test_auc']:.3f}) in {record['seconds']} s", flush=True)
    records = read_records(args.out)
    table = summary(records)
    print(table)
    if args.report:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        commands = "\n".join(f"    {c}" for c in dict.fromkeys(r["command"] for r in records))
        args.report.write_text(f"# What reads the plan: learning curves on {args.data}\n\nThe records' commands "
                               f"(each record of `{args.out}` holds its own):\n\n{commands}\n\n{table}\n")
        print(f"wrote {args.report}")
    if args.plot:
        plot(records, args.plot, args.data.stem)
    return 0


def run_learner(learner: str, actions: np.ndarray, y: np.ndarray, attrs: dict, data: Path, fit: np.ndarray,
                valid: np.ndarray, test: np.ndarray, repeat: int, cache: dict, min_steps: int = 1500,
                view: dict | None = None) -> dict:
    source, kind = learner.split(":")
    if source == "raw":
        return fit_gb(raw_plan(actions), y, fit, valid, test)
    if source == "grasp_frame":
        if "grasp_frame" not in cache:
            cache["grasp_frame"] = grasp_frame(actions)
        X = cache["grasp_frame"]
        return fit_gb(X, y, fit, valid, test) if kind == "gb" else fit_small_mlp(X, y, fit, valid, test)
    from firp.model.config import PlanEventsConfig
    from firp.model.plan_events import build_plan_events

    if "kinematics" not in attrs:
        raise SystemExit(f"{data}: the dataset carries no kinematics; collect it with --framed or --view-size")
    cfg = PlanEventsConfig(enabled=True, kinematics=attrs["kinematics"])
    inputs = {"actions": torch.from_numpy(actions)}
    if learner == "events:gb":
        if "events_flat" not in cache:
            cache["events_flat"] = flat_events(build_plan_events(cfg, actions.shape[-1]), actions)
        return fit_gb(cache["events_flat"], y, fit, valid, test)
    if source == "events":
        return fit_net(lambda: EventClassifier(build_plan_events(cfg, actions.shape[-1])), inputs, y, fit, valid,
                       test, seed=repeat, min_steps=min_steps)
    final = source == "events_final_view"
    if ("views", final) not in cache:
        cache[("views", final)] = view_inputs(data, attrs, final)
    inputs.update(cache[("views", final)])
    cfg = replace(cfg, view=True, **(view or {}))
    return fit_net(lambda: EventClassifier(build_plan_events(cfg, actions.shape[-1])), inputs, y, fit, valid, test,
                   seed=repeat, min_steps=min_steps)


def flat_events(events, actions: np.ndarray) -> np.ndarray:
    """The relation network's raw inputs, flattened per plan: every event's token and the geometric part of
    every pair (offset, distance, relative rotation), zeros for absent events (padded to the most events of
    any plan, so a column means one event or pair in every row)."""
    chunks = []
    with torch.no_grad():
        for i in range(0, len(actions), 512):
            tokens, pairs, present = events.raw_features(torch.from_numpy(actions[i:i + 512]).double())
            both = (present.unsqueeze(1) & present.unsqueeze(2)).unsqueeze(-1)
            chunks.append((tokens * present.unsqueeze(-1), pairs[..., :10] * both))
    E = max(t.shape[1] for t, _ in chunks)
    rows = []
    for tokens, pairs in chunks:
        pad = E - tokens.shape[1]
        tokens = torch.nn.functional.pad(tokens, (0, 0, 0, pad))
        pairs = torch.nn.functional.pad(pairs, (0, 0, 0, pad, 0, pad))
        rows.append(torch.cat([tokens.flatten(1), pairs.flatten(1)], dim=1).numpy())
    return np.concatenate(rows)


def view_inputs(data: Path, attrs: dict, final: bool = False) -> dict[str, torch.Tensor]:
    """Every episode's view image ``(N, S, S, 3)`` -- the initial scene, or with ``final`` the settled final one --
    and the base-frame projection into it ``(N, 3, 4)``."""
    from firp.core.camera import CameraCalibration
    from firp.core.kinematics import KinematicChain

    with EpisodeDataset(data) as ds:
        if not (ds.has_final_view if final else ds.has_view):
            raise SystemExit(f"{data}: no {'final ' if final else ''}view images; collect with --view-size"
                             + (" --final-view" if final else ""))
        views = np.stack([(ds.final_view if final else ds.view)(n) for n in ds.demo_names])
    size = views.shape[1]
    calibration = CameraCalibration.from_dict(attrs["camera_calibration"]).resized(size, size)
    base = KinematicChain.from_dict(attrs["kinematics"]).base.matrix()
    projection = torch.tensor(calibration.projection(base), dtype=torch.float32)
    return {"view": torch.from_numpy(views), "projection": projection.expand(len(views), 3, 4)}


def summary(records: list[dict]) -> str:
    """Markdown: per learner and training size, the mean test balanced accuracy / AUC over the repeats, and the
    mean seconds a fit took (on this machine, beside whatever else ran)."""
    sizes = sorted({r["size"] for r in records})
    lines = ["| learner | " + " | ".join(f"{n} episodes" for n in sizes) + " | seconds per fit (largest) |",
             "|---" * (len(sizes) + 2) + "|"]
    for learner in sorted({r["learner"] for r in records}):
        cells, seconds = [], ""
        for n in sizes:
            rows = [r for r in records if r["learner"] == learner and r["size"] == n]
            if rows:
                cells.append(f"{np.mean([r['test_balanced_accuracy'] for r in rows]):.3f} / "
                             f"{np.mean([r['test_auc'] for r in rows]):.3f}" + (f" ({len(rows)})" if len(rows) > 1 else ""))
                seconds = f"{np.mean([r['seconds'] for r in rows]):.0f}"
            else:
                cells.append("")
        lines.append(f"| {learner} | " + " | ".join(cells) + f" | {seconds} |")
    return "\n".join(lines) + "\n\nCells: test balanced accuracy at 0.5 / test AUC, mean over (repeats) where more than one."


def plot(records: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for learner in sorted({r["learner"] for r in records}):
        sizes = sorted({r["size"] for r in records if r["learner"] == learner})
        means = [np.mean([r["test_balanced_accuracy"] for r in records if r["learner"] == learner and r["size"] == n])
                 for n in sizes]
        ax.plot(sizes, means, marker="o", label=learner)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("test balanced accuracy (threshold 0.5)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
