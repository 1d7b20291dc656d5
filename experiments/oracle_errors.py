"""Which robosuite stacking episodes does the Oracle get wrong? Its test errors by the episode's end state.

The Oracle baseline reads the executed frames; on ``stack_three`` it stays near 0.90 although the last
frame's state decides every label (``experiments.oracle_frames``). This groups its test predictions
(at 0.5), over every repeat of a ``firp evaluate`` run, by what the episode ended as: success, or which
cube never reached the tower (``experiments.robosuite_choices.failure_mode``). A mode the image cannot
tell from a finished tower shows as a high error rate there.

    python -m experiments.oracle_errors --data data/robosuite_stack_three.h5 \\
        --eval-dir runs/eval-robosuite_stack_three-geometry --out docs/results/robosuite_stack_three_oracle_errors.json
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from experiments.robosuite_choices import failure_mode
from firp.core.episodes import EpisodeDataset

SUCCESS = "success"


def end_state(attrs: dict, success: bool) -> str:
    """``success``, or the failure mode of a ``stack_three`` episode from its recorded end state."""
    if success:
        return SUCCESS
    return failure_mode(list(attrs["block_order"]), attrs["final_blocks"], attrs["scene"], str(attrs["kind"]))


def tabulate(predictions: list[tuple[str, bool, bool]]) -> dict[str, dict]:
    """``(end state, label, predicted)`` triples -> per end state: test episodes, errors, error rate."""
    total, wrong = Counter(), Counter()
    for state, label, predicted in predictions:
        total[state] += 1
        wrong[state] += int(label != predicted)
    return {state: {"test_episodes": total[state], "errors": wrong[state],
                    "error_rate": round(wrong[state] / total[state], 4)}
            for state in sorted(total, key=lambda s: (s != SUCCESS, s))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a firp collect --world robosuite stack_three dataset")
    parser.add_argument("--eval-dir", type=Path, required=True, help="a firp evaluate --out folder with r<k>-oracle.json")
    parser.add_argument("--method", default="oracle")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    runs = sorted(args.eval_dir.glob(f"r*-{args.method}.json"))
    if not runs:
        parser.error(f"--eval-dir: no r<k>-{args.method}.json in {args.eval_dir}")
    predictions = []
    with EpisodeDataset(args.data) as ds:
        labels = ds.success_labels().astype(bool)
        for path in runs:
            row = json.loads(path.read_text())
            for index, score in zip(row["test_index"], row["test_scores"]):
                label = bool(labels[int(index)])
                predictions.append((end_state(ds.demo_attrs(int(index)), label), label, score >= 0.5))
    table = tabulate(predictions)
    for state, cell in table.items():
        print(f"{state}: {cell['errors']} wrong of {cell['test_episodes']} ({cell['error_rate']:.1%})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "method": args.method, "repeats": len(runs),
                                    "by_end_state": table,
                                    "command": f"python -m experiments.oracle_errors --data {args.data} "
                                               f"--eval-dir {args.eval_dir} --out {args.out}"}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
