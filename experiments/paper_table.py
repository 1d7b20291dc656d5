"""The paper's classification table beside firp's, on the same rows: MimicGen's columns and robosuite's.

The paper's numbers are its Table "Balanced accuracies in the classification experiment" (MimicGen:
three-piece assembly, pick & place, stacking; 3 repeats). firp's come from ``firp evaluate``'s
``results.json`` on the robosuite task nearest each MimicGen column (assembly -> ``nut_assembly``,
pick & place -> ``pick_place``, stacking -> ``stack_three``). A column firp has not run stays empty.
A task given several runs (other datasets or plan descriptions of the same task) gets a column per run,
named by its dataset and description, so a larger collection stands beside the paper-sized one instead
of replacing it. The targets of the robosuite world are checked per column: the FIRP ensemble at least
the paper's FIRP − 0.03 and at least the best non-oracle baseline + 0.02 of the same run; the Oracle ≥ 0.95.

    python -m experiments.paper_table --stack-three runs/eval-robosuite_stack_three/results.json \\
        runs/eval-robosuite_stack_three_2000/results.json --out docs/results/robosuite_paper_table.md
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import NamedTuple

from firp.evaluate import BASELINES, target_margin

#: (column, robosuite task) in the paper's order
COLUMNS = (("three-piece assembly", "nut_assembly"), ("pick & place", "pick_place"), ("stacking", "stack_three"))
#: the paper's MimicGen numbers: row -> (mean, std) per column
PAPER = {
    "oracle": ((1.000, 0.000), (0.981, 0.016), (1.000, 0.000)),
    "a_mlp": ((0.605, 0.042), (0.817, 0.023), (0.583, 0.356)),
    "a_mlp_image": ((0.938, 0.065), (0.882, 0.024), (0.889, 0.060)),
    "gru": ((0.905, 0.034), (0.926, 0.028), (0.903, 0.052)),
    "dvd": ((0.561, 0.010), (0.685, 0.078), (0.494, 0.035)),
    "firp": ((0.932, 0.034), (0.952, 0.023), (0.923, 0.028)),
}
ROWS = (("oracle", "Oracle"), ("a_mlp", "A-MLP"), ("a_mlp_image", "A-MLP + image (paper: ResNet; firp: EfficientNet-Lite0)"),
        ("gru", "GRU"), ("geometry_mlp", "Geometry MLP (firp's: the plan's description alone, the one its run reads)"),
        ("dvd", "DVD"), ("firp", "FIRP"), ("firp_tcr", "FIRP + TCR"),
        ("firp_ensemble", "FIRP ensemble (firp's: FIRP, +TTC, +ATC, +TCR)"))
#: the robosuite world's bars: the paper's FIRP − 0.03; ``firp evaluate``'s margin over the best baseline (one
#: source, so the table and the protocol's summary cannot disagree); the Oracle's floor
PAPER_MARGIN, BASELINE_MARGIN, ORACLE_BAR = 0.03, target_margin("robosuite"), 0.95


def method_scores(results: dict) -> dict[str, list[float]]:
    """Test balanced accuracy per method over the run's repeats."""
    scores: dict[str, list[float]] = {}
    for row in results["rows"]:
        scores.setdefault(row["method"], []).append(float(row["test_balanced_accuracy"]))
    return scores


def _cell(values: list[float] | None) -> str:
    if not values:
        return ""
    std = statistics.stdev(values) if len(values) > 1 else 0.0  # as firp evaluate reports it
    return f"{statistics.fmean(values):.3f} ± {std:.3f} ({len(values)})"


def targets(column: int, scores: dict[str, list[float]]) -> list[str]:
    mean = {m: statistics.fmean(v) for m, v in scores.items() if v}
    lines = []
    if "firp_ensemble" in mean:
        ours, paper = mean["firp_ensemble"], PAPER["firp"][column][0]
        lines.append(f"FIRP ensemble {ours:.3f} vs the paper's FIRP {paper:.3f} − {PAPER_MARGIN} = "
                     f"{paper - PAPER_MARGIN:.3f}: {'met' if ours >= paper - PAPER_MARGIN else 'not met'}")
        base = max((m for m in BASELINES if m in mean), key=mean.get, default=None)
        if base:
            lines.append(f"FIRP ensemble {ours:.3f} vs the best non-oracle baseline ({base}, {mean[base]:.3f}) + "
                         f"{BASELINE_MARGIN} = {mean[base] + BASELINE_MARGIN:.3f}: "
                         f"{'met' if ours >= mean[base] + BASELINE_MARGIN else 'not met'}")
    if "oracle" in mean:
        lines.append(f"Oracle {mean['oracle']:.3f} vs {ORACLE_BAR}: {'met' if mean['oracle'] >= ORACLE_BAR else 'not met'}")
    return lines


def run_label(results: dict) -> str:
    """What tells two runs of one task apart: the dataset's file name and the plan description read."""
    label = f"`{Path(results.get('dataset', 'dataset')).stem}`"
    description = results.get("overrides", {}).get("plan_description")
    return f"{label}, {description}" if description else label


class FirpColumn(NamedTuple):
    """One firp column: the paper's column it stands beside, its run (None: not run yet) and that run's scores."""
    paper_column: int
    task: str
    results: dict | None
    scores: dict[str, list[float]]
    label: str  # what tells the task's runs apart ("" when the task has one)


def firp_columns(runs: dict[str, list[dict]]) -> list[FirpColumn]:
    """A column per run of every task, in the paper's column order and the runs' given order."""
    columns = []
    for paper_column, (_, task) in enumerate(COLUMNS):
        listed = runs.get(task) or [None]
        columns += [FirpColumn(paper_column, task, results, method_scores(results) if results else {},
                               run_label(results) if len(listed) > 1 else "") for results in listed]
    return columns


def render(runs: dict[str, list[dict]]) -> str:
    """``runs``: robosuite task -> its runs' results.json (a column each, in the order given)."""
    columns = firp_columns(runs)
    head = ["method"] + [f"paper: MimicGen {name}" for name, _ in COLUMNS] + [
        f"firp: robosuite `{c.task}`" + (f" ({c.label})" if c.label else "") for c in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key, label in ROWS:
        paper = [f"{m:.3f} ± {s:.3f}" for m, s in PAPER[key]] if key in PAPER else [""] * 3
        ours = []
        for c in columns:
            if c.results is None:
                ours.append("not run yet")
            elif key == "dvd":
                ours.append("not run: " + c.results.get("not_run", {}).get("dvd", "no weights"))
            else:
                ours.append(_cell(c.scores.get(key)))
        lines.append("| " + " | ".join([label, *paper, *ours]) + " |")
    lines += ["", ("Each firp cell: mean ± std over the repeats (their number in brackets) of the test balanced "
                   "accuracy, `firp evaluate`'s protocol (stratified 80/20 split per repeat, 20% of train for "
                   "validation, every method on the same splits); an empty one, a method its run left out.")]
    for c in columns:
        if c.results is not None:
            which = f", {c.label}" if c.label else ""
            heading = f"**{c.task}**{which} (nearest to MimicGen {COLUMNS[c.paper_column][0]}): `{c.results['command']}`"
            lines += ["", heading, ""]
            lines += [f"- {line}" for line in targets(c.paper_column, c.scores)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for _, task in COLUMNS:
        parser.add_argument(f"--{task.replace('_', '-')}", type=Path, nargs="+", default=None, metavar="RESULTS_JSON",
                            help=f"firp evaluate's results.json on robosuite {task} (several: a column each)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    runs = {task: [json.loads(path.read_text()) for path in paths] for _, task in COLUMNS
            if (paths := getattr(args, task)) is not None}
    if not runs:
        parser.error("--stack-three / --nut-assembly / --pick-place: give at least one results.json")
    text = render(runs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
