"""What decides robosuite's nut assembly beyond the planner's choice, and whether the image can show it.

On ``nut_assembly`` (robosuite's ``NutAssemblySquare``) the planner picks one of 30 choices -- which way
the fingers close on the nut's handle, where along the handle (:data:`planner_client.robosuite_tamp.NUT_GRIPS`)
and how the nut goes onto the peg -- and plans it from the nut's perceived pose (3 mm / 3 deg error). Where
the fingers really close on the handle is the choice's grip *plus* that perception error, and a nut held a
few millimetres off its handle's centre jams on the peg or falls beside it. This experiment measures, on
``firp evaluate``'s splits (gradient boosting trained on each repeat's training and validation episodes,
balanced accuracy on its test episodes):

* ``choice`` -- knowing the planner's choice exactly (grasp axis, release, grip point): the most a scorer
  can take from the plan alone, which carries the choice but not the perception error;
* ``plan_geometry`` -- the plan's grasp-frame description (``--plan-description grasp_frame``, forward
  kinematics of the joint targets at the grasp and the release), the product preset's input;
* ``choice_and_true_grip`` -- the choice and where the fingers really close on the handle: the plan's grasp
  point and finger yaw read in the nut's *true* frame (along and across the handle in mm, the fingers'
  misalignment in degrees). The ceiling of a scorer that sees the nut exactly;
* ``true_grip_seen_with_error@s`` -- the same, the nut seen with an error of ``s`` mm and ``s`` degrees
  (Gaussian, seeded): what a scorer that locates the nut as well as ``s`` could reach.

And whether the 84 px image locates the nut that well, on the same splits (trained on training and
validation episodes, root-mean-square error on the test episodes):

* ``frozen_features_ridge`` -- ridge regression on the first frame's EfficientNet-Lite0 features, what
  every FIRP model sees of the image;
* ``small_cnn`` -- a small CNN trained on the first frame's pixels (augmentation-free, early-stopped on the
  validation episodes), what the pixels hold as far as the dataset's episodes teach;
* ``planner`` -- the planner's own estimate, for scale.

Each regresses the handle's centre (where the grip points are measured from) and the nut's yaw. Finally, a
scorer built from the image and the plan alone: the nut located by small CNNs that never saw the episode
(cross-fitted over the training episodes, so the classifier learns with the error it meets on test
episodes), the grip read in that frame:

* ``choice_and_image_located_grip`` -- beside the choice;
* ``plan_geometry_and_image_located_grip`` -- beside the plan's grasp-frame description and the located pose,
  with no choice label: what the image and the plan show, with the nut's pose taught to the image model.

    python -m experiments.nut_perception --data data/robosuite_nut_assembly.h5 \\
        --protocol docs/results/robosuite_nut_assembly_protocol.json \\
        --out docs/results/robosuite_nut_assembly_perception.json \\
        --plot docs/results/robosuite_nut_assembly_perception.png
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from firp.core.episodes import EpisodeDataset
from firp.evaluate import split_indices
from firp.metrics import balanced_accuracy

# numpy only: importing it does not import robosuite, which the main environment lacks
from robosuite_worker.tasks import quat_yaw

#: robosuite's ``NutAssemblySquare`` state: 7 arm joints and 2 finger joints, then the square nut's free joint
#: (x, y, z, then the quaternion w, x, y, z) -- checked against the planner's estimates on every episode
NUT_QPOS = slice(9, 16)
#: an episode whose recorded nut lies farther than this from the planner's estimate means the state layout
#: is not the one above (the estimate's error is a few millimetres)
LAYOUT_CHECK_M = 0.02
SEEN_ERRORS = (0.5, 1.0, 2.0, 3.0, 5.0)  # mm and degrees a scorer might locate the nut with
CROSS_FIT_FOLDS = 3  # CNNs per repeat that locate the nut in the episodes they did not see


def wrap(angle: np.ndarray, period: float) -> np.ndarray:
    """Angles to ``[-period / 2, period / 2)``."""
    return (angle + period / 2) % period - period / 2


def true_nut_poses(first_states: np.ndarray, estimates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(N, S)`` states at the first frame -> the nut's xy ``(N, 2)`` and yaw ``(N,)``, checked against the
    planner's estimated xy ``(N, 2)``."""
    nut = first_states[:, NUT_QPOS]
    off = np.linalg.norm(nut[:, :2] - estimates, axis=1)
    if np.any(off > LAYOUT_CHECK_M):
        worst = int(np.argmax(off))
        raise ValueError(f"states: episode {worst}'s nut (qpos {NUT_QPOS.start}-{NUT_QPOS.stop - 1}) lies "
                         f"{100 * off[worst]:.1f} cm from the planner's estimate; not a NutAssemblySquare dataset "
                         f"with the state layout this experiment reads")
    return nut[:, :2], np.array([quat_yaw(q) for q in nut[:, 3:7]])


def grip_on_handle(grasp_xy: np.ndarray, finger_yaw: np.ndarray, axis: np.ndarray, nut_xy: np.ndarray,
                   nut_yaw: np.ndarray, handle: np.ndarray) -> np.ndarray:
    """Where the fingers close, in a nut's frame: ``(N, 3)`` = mm outwards of the handle's centre, mm across
    the handle, and the fingers' misalignment in degrees (axis 0 closes across the handle, 1 along it)."""
    c, s = np.cos(-nut_yaw), np.sin(-nut_yaw)
    rel = grasp_xy - nut_xy
    local = np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], axis=1)
    length = float(np.linalg.norm(handle))
    direction = handle / length
    along = local @ direction - length
    across = local @ np.array([-direction[1], direction[0]])
    handle_yaw = nut_yaw + math.atan2(direction[1], direction[0])
    misalign = wrap(finger_yaw - handle_yaw - np.where(axis == 0, np.pi / 2, 0.0), np.pi)
    return np.stack([1000 * along, 1000 * across, np.degrees(misalign)], axis=1)


def handle_centres(nut_xy: np.ndarray, nut_yaw: np.ndarray, handle: np.ndarray) -> np.ndarray:
    """The handle's centre in the world ``(N, 2)``."""
    c, s = np.cos(nut_yaw), np.sin(nut_yaw)
    return nut_xy + np.stack([c * handle[0] - s * handle[1], s * handle[0] + c * handle[1]], axis=1)


def choice_columns(choice: str) -> list[float]:
    """``SquareNut:<axis>:<l|d>:q<turn>:<grip letter>`` -> axis, dropped, turn, grip point (mm outwards)."""
    from planner_client.robosuite_tamp import NUT_GRIP_NAMES, NUT_GRIPS

    _, axis, drop, turn, grip = choice.split(":")
    return [float(axis), 1.0 if drop == "d" else 0.0, float(turn[1:]), 1000 * NUT_GRIPS[NUT_GRIP_NAMES.index(grip)]]


def read(path: Path) -> dict:
    """Everything the measurements need from a ``nut_assembly`` dataset."""
    import torch

    from firp.model.plan_geometry import pick_events, plan_geometry

    with EpisodeDataset(path) as ds:
        if ds.attrs.get("task") != "nut_assembly":
            raise ValueError(f"--data: a nut_assembly dataset is needed, {path} holds {ds.attrs.get('task')!r}")
        names = ds.demo_names
        attrs = [ds.demo_attrs(n) for n in names]
        labels = ds.success_labels().astype(bool)
        actions = np.stack([ds.actions(n) for n in names])  # (N, T, 16)
        first_states = np.stack([ds.states(n)[0] for n in names])  # (N, S)
        first_frames = np.stack([ds.frames(n)[0] for n in names])  # (N, H, W, 3)
    name = attrs[0]["block_order"][0]
    estimates = np.array([a["pose_estimates"][name]["position"][:2] for a in attrs])
    estimated_yaw = np.array([a["pose_estimates"][name]["yaw"] for a in attrs])
    handle = np.asarray(attrs[0]["scene"]["handle_offset"], dtype=float)
    nut_xy, nut_yaw = true_nut_poses(first_states, estimates)
    plans = torch.as_tensor(actions, dtype=torch.float64)
    events = pick_events(plans, None, max_picks=1)
    grasp_xy = events["grasp_pos"][:, 0, :2].numpy()
    finger_yaw = events["grasp_yaw"][:, 0].numpy()
    choices = np.array([choice_columns(str(a["choice"])) for a in attrs])
    axis = choices[:, 0]
    return {"labels": labels, "choices": choices, "frames": first_frames, "handle": handle,
            "plan_geometry": plan_geometry(plans, None, 1).numpy(),
            "true_grip": grip_on_handle(grasp_xy, finger_yaw, axis, nut_xy, nut_yaw, handle),
            "believed_grip": grip_on_handle(grasp_xy, finger_yaw, axis, estimates, estimated_yaw, handle),
            "true_handle": handle_centres(nut_xy, nut_yaw, handle), "true_yaw": nut_yaw,
            "estimated_handle": handle_centres(estimates, estimated_yaw, handle), "estimated_yaw": estimated_yaw,
            "grasp_xy": grasp_xy, "finger_yaw": finger_yaw, "axis": axis}


def seen_with_error(data: dict, error: float, seed: int) -> np.ndarray:
    """The choice and the grip as a scorer sees it that locates the nut with ``error`` mm and degrees."""
    rng = np.random.default_rng(seed)
    n = len(data["labels"])
    # the scorer's belief of the nut: the truth moved by the error (the handle's centre by error mm, the yaw
    # by error degrees about it), and the grip read in that believed frame
    yaw = data["true_yaw"] + np.radians(rng.normal(0.0, error, n))
    centre = data["true_handle"] + rng.normal(0.0, error / 1000, (n, 2))
    believed = np.concatenate([centre, np.cos(yaw)[:, None], np.sin(yaw)[:, None]], axis=1)
    return np.concatenate([data["choices"], grip_seen_at(data, believed)], axis=1)


def classify(X: np.ndarray, labels: np.ndarray, train: np.ndarray, test: np.ndarray, seed: int) -> float:
    from sklearn.ensemble import GradientBoostingClassifier

    model = GradientBoostingClassifier(random_state=seed).fit(X[train], labels[train])
    return balanced_accuracy(labels[test], model.predict_proba(X[test])[:, 1] >= 0.5)


def pose_targets(data: dict) -> np.ndarray:
    """What the regressors predict: the handle's centre (m) and the nut's yaw as cos/sin (one turn: the
    handle makes the square nut's yaw unique)."""
    yaw = data["true_yaw"]
    return np.concatenate([data["true_handle"], np.cos(yaw)[:, None], np.sin(yaw)[:, None]], axis=1)


def pose_errors(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """Root-mean-square error of the handle's centre (mm) and of the yaw (degrees)."""
    centre = 1000 * np.linalg.norm(predicted[:, :2] - truth[:, :2], axis=1)
    yaw = np.degrees(wrap(np.arctan2(predicted[:, 3], predicted[:, 2]) - np.arctan2(truth[:, 3], truth[:, 2]),
                          2 * np.pi))
    return {"handle_centre_rmse_mm": float(np.sqrt(np.mean(centre ** 2))),
            "yaw_rmse_deg": float(np.sqrt(np.mean(yaw ** 2)))}


def frozen_features(frames: np.ndarray) -> np.ndarray:
    """The first frames' EfficientNet-Lite0 features at 84 px, as every FIRP model's image encoder has them."""
    import torch

    from firp.model.config import EncoderConfig
    from firp.model.encoder import ImageEncoder

    encoder = ImageEncoder(EncoderConfig(image_size=frames.shape[1])).eval()
    with torch.inference_mode():
        return encoder.backbone_features(torch.from_numpy(frames), chunk_size=64).float().numpy()


def ridge_pose(features: np.ndarray, targets: np.ndarray, seen: np.ndarray, test: np.ndarray) -> np.ndarray:
    from sklearn.linear_model import RidgeCV
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = make_pipeline(StandardScaler(), RidgeCV(alphas=np.logspace(-2, 4, 13)))
    return model.fit(features[seen], targets[seen]).predict(features[test])


def cnn_pose(frames: np.ndarray, targets: np.ndarray, train: np.ndarray, valid: np.ndarray, predict: np.ndarray,
             seed: int, epochs: int, progress: bool, label: str = "") -> np.ndarray:
    """A small CNN on the pixels (firp's ``small_cnn`` backbone and a linear head), trained with Adam on the
    training episodes' standardised targets; the epoch with the lowest validation error is kept and predicts
    the ``predict`` episodes ``(len(predict), 4)``."""
    import torch
    from torch import nn

    from firp.model.encoder import SmallCNN

    torch.manual_seed(seed)
    x = torch.from_numpy(frames).permute(0, 3, 1, 2).float().div(127.5).sub(1.0)  # (N, 3, H, W) in [-1, 1]
    mean, std = targets[train].mean(axis=0), targets[train].std(axis=0) + 1e-9
    y = torch.from_numpy((targets - mean) / std).float()
    backbone = SmallCNN()
    model = nn.Sequential(backbone, nn.Linear(backbone.out_dim, targets.shape[1]))
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    best, best_state = math.inf, None
    generator = torch.Generator().manual_seed(seed)
    for _ in tqdm(range(epochs), desc=f"small CNN, repeat {seed}{label}", disable=not progress, leave=False):
        model.train()
        for batch in torch.split(torch.as_tensor(train)[torch.randperm(len(train), generator=generator)], 32):
            optimiser.zero_grad()
            nn.functional.mse_loss(model(x[batch]), y[batch]).backward()
            optimiser.step()
        model.eval()
        with torch.no_grad():
            loss = float(nn.functional.mse_loss(model(x[valid]), y[valid]))
        if loss < best:
            best, best_state = loss, {k: v.clone() for k, v in model.state_dict().items()}
    model.load_state_dict(best_state)
    with torch.no_grad():
        return model(x[predict]).numpy() * std + mean


def cross_fitted_cnn_pose(frames: np.ndarray, targets: np.ndarray, seen: np.ndarray, test: np.ndarray, seed: int,
                          epochs: int, progress: bool, folds: int = CROSS_FIT_FOLDS) -> np.ndarray:
    """The small CNN's located pose for every episode ``(N, 4)`` where no CNN saw the episode it locates.

    A classifier trained on the located grip must meet the localisation error it will meet on test episodes,
    so each fold of the ``seen`` episodes is located by a CNN trained on the other folds (a tenth of them
    held out for early stopping), and the test episodes by the mean of the fold CNNs' poses.
    """
    rng = np.random.default_rng(seed)
    parts = np.array_split(rng.permutation(seen), folds)
    located = np.zeros_like(targets)
    test_poses = []
    for k, part in enumerate(parts):
        rest = rng.permutation(np.concatenate([p for j, p in enumerate(parts) if j != k]))
        n_valid = max(1, len(rest) // 10)
        poses = cnn_pose(frames, targets, rest[n_valid:], rest[:n_valid], np.concatenate([part, test]), seed, epochs,
                         progress, f", fold {k + 1}/{folds}")
        located[part] = poses[: len(part)]
        test_poses.append(poses[len(part):])
    located[test] = np.mean(test_poses, axis=0)
    return located


def grip_seen_at(data: dict, pose: np.ndarray) -> np.ndarray:
    """The grip read in a located nut frame: ``pose`` ``(N, 4)`` = the handle's centre and the yaw's cos, sin."""
    handle = data["handle"]
    yaw = np.arctan2(pose[:, 3], pose[:, 2])
    c, s = np.cos(yaw), np.sin(yaw)
    nut_xy = pose[:, :2] - np.stack([c * handle[0] - s * handle[1], s * handle[0] + c * handle[1]], axis=1)
    return grip_on_handle(data["grasp_xy"], data["finger_yaw"], data["axis"], nut_xy, yaw, handle)


def plot(summary: dict, errors: dict, firp_ensemble: float | None, target: float | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6.5))
    xs = [0.0, *SEEN_ERRORS]
    keys = ["choice_and_true_grip", *(f"true_grip_seen_with_error@{e:g}" for e in SEEN_ERRORS)]
    means = [summary[k][0] for k in keys]
    stds = [summary[k][1] for k in keys]
    ax.errorbar(xs, means, yerr=stds, marker="o", capsize=3, label="choice + the grip as a scorer sees it")
    for key, style, text in (("choice", "--", "the planner's choice exactly"),
                             ("plan_geometry", ":", "the plan's grasp-frame description")):
        ax.axhline(summary[key][0], linestyle=style, color="grey", label=f"{text}: {summary[key][0]:.3f}")
    if "small_cnn_cross_fitted" in errors:
        x = errors["small_cnn_cross_fitted"]["handle_centre_rmse_mm"][0]
        for key, marker, text in (("choice_and_image_located_grip", "s", "choice + the grip where the CNN locates the nut"),
                                  ("plan_geometry_and_image_located_grip", "D",
                                   "the plan's description + the grip where the CNN locates the nut (image and plan alone)")):
            ax.errorbar([x], [summary[key][0]], yerr=[summary[key][1]], marker=marker, capsize=3, linestyle="none",
                        label=f"{text}: {summary[key][0]:.3f}")
    if firp_ensemble is not None:
        ax.axhline(firp_ensemble, color="tab:red", linestyle="-.", label=f"FIRP ensemble (protocol): {firp_ensemble:.3f}")
    if target is not None:
        ax.axhline(target, color="tab:green", linestyle="-", label=f"target: {target:.3f}")
    for name, colour in (("planner", "black"), ("small_cnn", "tab:purple"), ("frozen_features_ridge", "tab:orange")):
        if name in errors:
            value = errors[name]["handle_centre_rmse_mm"][0]
            ax.axvline(value, color=colour, alpha=0.6, label=f"{name.replace('_', ' ')} locates the handle: {value:.1f} mm")
    ax.set_xlabel("how well the scorer locates the nut (mm of the handle's centre, and degrees)")
    ax.set_ylabel("test balanced accuracy (gradient boosting)")
    ax.set_title("nut_assembly: the grip's millimetres, and how well the image shows them")
    ax.set_xlim(-0.3, max(12.0, 1.1 * max((errors[k]["handle_centre_rmse_mm"][0] for k in errors), default=0.0)))
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def mean_std(rows: list[dict], key: str) -> list[float]:
    values = [r[key] for r in rows]
    return [float(np.mean(values)), float(np.std(values, ddof=1)) if len(values) > 1 else 0.0]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a firp collect --world robosuite --task nut_assembly set")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cnn-epochs", type=int, default=60, help="0 skips the small CNN")
    parser.add_argument("--protocol", type=Path, help="the task's firp evaluate record: its FIRP ensemble on the plot")
    parser.add_argument("--target", type=float, default=0.902, help="drawn on the plot (the paper's FIRP - 0.03)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats: at least 1")
    if args.cnn_epochs < 0:
        parser.error("--cnn-epochs: 0 or more")
    data = read(args.data)
    labels = data["labels"]
    features = {"choice": data["choices"], "plan_geometry": data["plan_geometry"],
                "choice_and_true_grip": np.concatenate([data["choices"], data["true_grip"]], axis=1)}
    targets = pose_targets(data)
    image_features = frozen_features(data["frames"])
    planner = np.concatenate([data["estimated_handle"], np.cos(data["estimated_yaw"])[:, None],
                              np.sin(data["estimated_yaw"])[:, None]], axis=1)
    rows, pose_rows = [], []
    for repeat in range(args.repeats):
        train, valid, test = split_indices(labels.astype(int), repeat)
        seen = np.concatenate([train, valid])
        row = {"repeat": repeat, **{k: classify(X, labels, seen, test, repeat) for k, X in features.items()}}
        for error in SEEN_ERRORS:
            row[f"true_grip_seen_with_error@{error:g}"] = classify(seen_with_error(data, error, repeat), labels, seen,
                                                                   test, repeat)
        poses = {"repeat": repeat, "planner": pose_errors(planner[test], targets[test]),
                 "frozen_features_ridge": pose_errors(ridge_pose(image_features, targets, seen, test), targets[test])}
        if args.cnn_epochs:
            poses["small_cnn"] = pose_errors(cnn_pose(data["frames"], targets, train, valid, test, repeat,
                                                      args.cnn_epochs, not args.no_progress), targets[test])
            # a scorer from the image and the plan alone: the nut located by CNNs that never saw the episode,
            # the grip read in that frame, beside the plan's own description (no choice label)
            located = cross_fitted_cnn_pose(data["frames"], targets, seen, test, repeat, args.cnn_epochs,
                                            not args.no_progress)
            poses["small_cnn_cross_fitted"] = pose_errors(located, targets)
            grip = grip_seen_at(data, located)
            row["plan_geometry_and_image_located_grip"] = classify(
                np.concatenate([data["plan_geometry"], grip, located], axis=1), labels, seen, test, repeat)
            row["choice_and_image_located_grip"] = classify(np.concatenate([data["choices"], grip], axis=1), labels,
                                                            seen, test, repeat)
        rows.append(row)
        pose_rows.append(poses)
        print(f"repeat {repeat}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "repeat")
              + " | " + ", ".join(f"{k} {v['handle_centre_rmse_mm']:.1f} mm {v['yaw_rmse_deg']:.1f} deg"
                                  for k, v in poses.items() if k != "repeat"), flush=True)
    summary = {k: mean_std(rows, k) for k in rows[0] if k != "repeat"}
    errors = {name: {m: mean_std([p[name] for p in pose_rows], m) for m in pose_rows[0][name]}
              for name in pose_rows[0] if name != "repeat"}
    grip = data["true_grip"] - data["believed_grip"]
    firp_ensemble = None
    if args.protocol:
        from experiments.paper_table import method_scores

        scores = method_scores(json.loads(args.protocol.read_text())).get("firp_ensemble")
        firp_ensemble = float(np.mean(scores)) if scores else None
    result = {"command": "python -m experiments.nut_perception " + shlex.join(sys.argv[1:] if argv is None else argv),
              "data": str(args.data), "episodes": len(labels), "success_rate": float(labels.mean()),
              "perception_error_at_the_grip": {f"{name}_rms": float(np.sqrt(np.mean(grip[:, k] ** 2)))
                                               for k, name in enumerate(("along_mm", "across_mm", "misalignment_deg"))},
              "classifiers": summary, "rows": rows, "localisation": errors, "localisation_rows": pose_rows,
              "firp_ensemble": firp_ensemble, "target": args.target}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    if args.plot:
        plot(summary, errors, firp_ensemble, args.target, args.plot)
    print(json.dumps({"classifiers": summary, "localisation": errors}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
