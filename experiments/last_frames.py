"""What the Oracle sees at the end: the last recorded frame of some successes and some failures, as a picture.

The Oracle baseline reads the executed frames, and what limits it is whether a finished scene can be
told from a failed one in the dataset's camera (``experiments.oracle_frames``: the last frame's state
holds the label). This draws the last frame of the first ``--per-class`` successes (top row) and
failures (bottom row) of a dataset, in episode order, each titled with its episode and, for robosuite
stacking, its failure mode -- the same picture for any camera the dataset was collected with.

    .venv/bin/python -m experiments.last_frames --data data/robosuite_stack_three.h5 \\
        --out docs/results/robosuite_stack_three_last_frames.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from experiments.robosuite_choices import failure_mode  # noqa: E402
from firp.core.episodes import EpisodeDataset  # noqa: E402


def pick(labels: np.ndarray, per_class: int) -> tuple[list[int], list[int]]:
    """Positions of the first ``per_class`` successes and failures, in episode order."""
    successes = [int(i) for i in np.flatnonzero(labels)[:per_class]]
    failures = [int(i) for i in np.flatnonzero(~labels)[:per_class]]
    return successes, failures


def caption(ds: EpisodeDataset, name: str) -> str:
    """The episode's name and, where the dataset records it, how it ended."""
    if ds.success(name):
        return f"{name}\nsuccess"
    attrs = ds.demo_attrs(name)
    if {"block_order", "final_blocks", "scene", "kind"} <= attrs.keys():  # robosuite stacking
        ending = failure_mode(list(attrs["block_order"]), attrs["final_blocks"], attrs["scene"], str(attrs["kind"]))
        return f"{name}\n" + ending.replace(" and ", "\nand ")
    return f"{name}\nfailure"


def draw(data: Path, out: Path, per_class: int = 6) -> Path:
    """Write the picture; returns ``out``."""
    with EpisodeDataset(data) as ds:
        names = ds.demo_names
        labels = np.asarray(ds.success_labels(), dtype=bool)
        successes, failures = pick(labels, per_class)
        if not successes or not failures:
            raise ValueError(f"--data: {data} needs both successes and failures to compare")
        camera = ds.attrs.get("camera", "agentview")
        columns = max(len(successes), len(failures))
        fig, axes = plt.subplots(2, columns, figsize=(1.9 * columns, 4.6), squeeze=False)
        for row, positions in enumerate((successes, failures)):
            for col in range(columns):
                ax = axes[row][col]
                ax.axis("off")
                if col < len(positions):
                    name = names[positions[col]]
                    ax.imshow(ds.frames(name)[-1])
                    ax.set_title(caption(ds, name), fontsize=6)
        fig.suptitle(f"{data.name}: last frames ({camera}), successes above, failures below", fontsize=8)
        fig.tight_layout()
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=130)
        plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a firp collect dataset")
    parser.add_argument("--per-class", type=int, default=6, help="episodes per row (default 6)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args(argv)
    if args.per_class < 1:
        parser.error("--per-class: must be at least 1")
    if not args.data.is_file():
        parser.error(f"--data: {args.data} does not exist")
    try:
        print(f"wrote {draw(args.data, args.out, args.per_class)}")
    except ValueError as exc:
        parser.error(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
