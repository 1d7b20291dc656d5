"""The command-line flags ``firp tune`` and ``firp evaluate`` share: the data, a preset, and overrides of it.

Every flag that changes the recipe defaults to "the preset's value" (``None``), so a command line
says only what differs from ``--preset`` (:mod:`firp.presets`), and :func:`recipe_from` turns the
flags into one :class:`~firp.train.TrainConfig` plus the list of what was overridden, which runs
and bundles record beside the preset's name.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from firp.core.cli_types import int_in_range, non_negative_float, positive_float

#: flag destination -> the field of Preset.with_overrides it sets
RECIPE_FLAGS = ("epochs", "patience", "min_epochs", "image_size", "action_chunk", "deter_dim", "hidden",
                "head_temperature", "plan_geometry", "plan_description", "description_layers", "plan_events",
                "plan_view", "overshooting", "prediction", "description_weight")


def add_training_flags(parser: argparse.ArgumentParser) -> None:
    """Data, preset and training-loop flags."""
    from firp.features import DEFAULT_CACHE_DIR
    from firp.presets import PRESETS

    parser.add_argument("--data", type=Path, required=True, help="recorded episodes (firp collect)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="product",
                        help="the recipe to start from (default product: what ships; paper: the paper's defaults); "
                             "the flags below override single fields of it")
    g = parser.add_argument_group("training loop (default: the preset's)")
    g.add_argument("--epochs", type=int_in_range("--epochs", 1, 10_000), default=None)
    g.add_argument("--patience", type=int_in_range("--patience", 1, 10_000), default=None,
                   help="early stopping: epochs without a better validation balanced accuracy")
    g.add_argument("--min-epochs", type=int_in_range("--min-epochs", 0, 10_000), default=None,
                   help="no early stop before this many epochs (FIRP starts at chance for tens of epochs)")
    g.add_argument("--image-size", type=int_in_range("--image-size", 16, 512), default=None,
                   help="backbone input size (product: 84, the frames' own size; paper: 224)")
    parser.add_argument("--threads", type=int_in_range("--threads", 1, 64), default=2, help="torch CPU threads")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="where models train: auto takes a CUDA GPU where torch sees one, else the CPU (results "
                             "may differ in the last digits between devices)")
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE_DIR, help="backbone feature cache")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (logs, CI)")


def add_model_flags(parser: argparse.ArgumentParser) -> None:
    """The FIRP architecture flags."""
    from firp.model.config import PLAN_DESCRIPTIONS

    g = parser.add_argument_group("model architecture (default: the preset's; product 8, 128, 128, 0.05, on; "
                                  "paper 1, 200, 200, 20, off)")
    g.add_argument("--action-chunk", type=int_in_range("--action-chunk", 1, 64), default=None,
                   help="plan steps per RSSM transition")
    g.add_argument("--deter-dim", type=int_in_range("--deter-dim", 1, 4096), default=None,
                   help="RSSM deterministic state size")
    g.add_argument("--hidden", type=int_in_range("--hidden", 1, 4096), default=None,
                   help="width of the RSSM's two-layer MLPs")
    g.add_argument("--head-temperature", type=positive_float("--head-temperature"), default=None,
                   help="attention temperature L of the success head")
    g.add_argument("--plan-geometry", action=argparse.BooleanOptionalAction, default=None,
                   help="give every plan-reading model the plan's grasp-frame description (firp.model.plan_geometry)")
    g.add_argument("--plan-description", choices=PLAN_DESCRIPTIONS, default=None,
                   help="what that description holds: the numbers in each grasp's frame (product), how near the "
                        "hand comes to the nearest other block at each grasp and release (clearance), that and "
                        "each pick's grasp and release heights (clearance_and_heights), the same with the clearance to "
                        "blocks of the sizes the plan's tower shows (sized_clearance_and_heights), or the first two "
                        "(both)")
    g.add_argument("--plan-events", action=argparse.BooleanOptionalAction, default=None,
                   help="give every plan-reading model the plan's events read through the arm's kinematics by a "
                        "relation network (firp.model.plan_events; generic: no task's sizes; replaces the "
                        "hand-built description)")
    g.add_argument("--plan-view", action=argparse.BooleanOptionalAction, default=None,
                   help="with --plan-events: each event also reads a hand-aligned crop of the dataset's view image "
                        "(firp.model.plan_view; needs a dataset collected with --view-size)")
    g.add_argument("--description-layers", type=int_in_range("--description-layers", 1, 2), default=None,
                   help="hidden layers FIRP's and the GRU's success heads read the description through (product: 2; "
                        "1: one ReLU layer -- no gain measured on robosuite's stacking)")


def add_loss_flags(parser: argparse.ArgumentParser) -> None:
    """Loss weights a protocol run fixes (a study tunes them)."""
    g = parser.add_argument_group("loss weights of the FIRP methods (default: the preset's)")
    g.add_argument("--lambda", dest="overshooting", type=non_negative_float("--lambda"), default=None,
                   help="latent-overshooting weight")
    g.add_argument("--prediction-weight", dest="prediction", type=non_negative_float("--prediction-weight"),
                   default=None, help="weight of FIRP's one-step prediction terms L_KL^1 + L_re^1 (paper: 1)")
    g.add_argument("--description-weight", type=non_negative_float("--description-weight"), default=None,
                   help="weight of a classification loss on the plan description's own share of FIRP's score, so "
                        "the description predicts by itself and the pooled sequence adds to it (product: 0, off; "
                        "needs the plan's description)")


def recipe_from(args: argparse.Namespace, parser: argparse.ArgumentParser | None = None) -> tuple[Any, dict[str, Any]]:
    """``(TrainConfig, overrides)``: the preset with every recipe flag that was given; ``overrides`` maps
    each of those flags to its value (what a run adds to the preset's name). Flags that contradict each
    other (``--plan-description`` with ``--no-plan-geometry``) are a ValueError, or with ``parser`` its CLI
    error."""
    from firp.presets import preset

    overrides = {k: getattr(args, k) for k in RECIPE_FLAGS if getattr(args, k, None) is not None}
    try:
        config = preset(args.preset).with_overrides(**overrides)
    except ValueError as error:
        if parser is None:
            raise
        parser.error(str(error))
    from dataclasses import replace

    return replace(config, threads=args.threads), overrides


def recipe_flags(preset_name: str, overrides: dict[str, Any]) -> str:
    """The command-line words that rebuild a recipe: ``--preset NAME`` and one flag per override."""
    words = [f"--preset {preset_name}"]
    for key, value in overrides.items():
        flag = {"overshooting": "--lambda", "prediction": "--prediction-weight"}.get(key, "--" + key.replace("_", "-"))
        if isinstance(value, bool):
            words.append(flag if value else "--no-" + flag[2:])
        else:
            words.append(f"{flag} {value}")
    return " ".join(words)


def check_data_flag(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Fail with a CLI error naming --data when the dataset file is missing."""
    if not args.data.exists():
        parser.error(f"--data: {args.data} does not exist (collect it with firp collect)")
