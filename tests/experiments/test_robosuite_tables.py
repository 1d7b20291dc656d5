"""The robosuite world's report helpers: the paper's table beside firp's, and the failure modes of a tower."""

from __future__ import annotations

import json

from experiments.paper_table import PAPER, main, render, targets
from experiments.robosuite_choices import failure_mode

SCENE = {"table_height": 0.8, "cube_half": {"cubeA": 0.02, "cubeB": 0.025, "cubeC": 0.02}}


def _results(scores: dict[str, list[float]]) -> dict:
    rows = [{"method": m, "repeat": r, "test_balanced_accuracy": v} for m, vs in scores.items()
            for r, v in enumerate(vs)]
    return {"command": "firp evaluate --data d.h5 --repeats 2", "rows": rows, "not_run": {"dvd": "no weights here"}}


def test_the_table_puts_firps_numbers_beside_the_papers_and_checks_the_targets(tmp_path):
    results = _results({"a_mlp": [0.6, 0.7], "a_mlp_image": [0.8, 0.9], "gru": [0.84, 0.86], "firp": [0.9, 0.9],
                        "firp_ensemble": [0.91, 0.93], "oracle": [0.96, 0.98]})
    text = render({"stack_three": [results]})
    rows = {line.split(" | ")[0].strip("| "): line for line in text.splitlines() if line.startswith("| ")}
    assert "| 0.923 ± 0.028 |" in rows["FIRP"] and rows["FIRP"].endswith("| 0.900 ± 0.000 (2) |")
    assert rows["A-MLP"].endswith("| not run yet | not run yet | 0.650 ± 0.071 (2) |")
    assert "not run: no weights here" in rows["DVD"]
    assert targets(2, {"firp_ensemble": [0.92], "a_mlp_image": [0.85], "oracle": [0.94]}) == [
        "FIRP ensemble 0.920 vs the paper's FIRP 0.923 − 0.03 = 0.893: met",
        "FIRP ensemble 0.920 vs the best non-oracle baseline (a_mlp_image, 0.850) + 0.02 = 0.870: met",
        "Oracle 0.940 vs 0.95: not met"]
    assert "vs the best non-oracle baseline (a_mlp_image, 0.850) + 0.02 = 0.870: not met" in \
        targets(2, {"firp_ensemble": [0.86], "a_mlp_image": [0.85]})[1]
    assert "(geometry_mlp, 0.880) + 0.02 = 0.900: not met" in \
        targets(2, {"firp_ensemble": [0.89], "a_mlp_image": [0.85], "geometry_mlp": [0.88]})[1]
    path = tmp_path / "r.json"
    path.write_text(json.dumps(results))
    assert main(["--stack-three", str(path), "--out", str(tmp_path / "t.md")]) == 0
    assert (tmp_path / "t.md").read_text() == text
    assert PAPER["oracle"][1] == (0.981, 0.016)


def test_a_task_run_on_two_datasets_gets_a_column_for_each_with_its_own_targets(tmp_path):
    small = {**_results({"gru": [0.75, 0.77], "firp_ensemble": [0.76, 0.78], "oracle": [0.90, 0.91]}),
             "dataset": "data/robosuite_stack_three.h5", "overrides": {}}
    large = {**_results({"gru": [0.88, 0.88], "firp_ensemble": [0.90, 0.92], "oracle": [0.99, 0.98]}),
             "dataset": "data/robosuite_stack_three_workspaceview_2000.h5",
             "overrides": {"plan_description": "table_sized_clearance_and_heights"}}
    text = render({"stack_three": [small, large]})
    head = text.splitlines()[0]
    assert head.endswith("| firp: robosuite `stack_three` (`robosuite_stack_three`) | firp: robosuite `stack_three` "
                         "(`robosuite_stack_three_workspaceview_2000`, table_sized_clearance_and_heights) |")
    rows = {line.split(" | ")[0].strip("| "): line for line in text.splitlines() if line.startswith("| ")}
    assert rows["GRU"].endswith("| not run yet | not run yet | 0.760 ± 0.014 (2) | 0.880 ± 0.000 (2) |")
    assert "- FIRP ensemble 0.770 vs the paper's FIRP 0.923 − 0.03 = 0.893: not met" in text
    assert "- FIRP ensemble 0.910 vs the paper's FIRP 0.923 − 0.03 = 0.893: met" in text
    assert "- FIRP ensemble 0.910 vs the best non-oracle baseline (gru, 0.880) + 0.02 = 0.900: met" in text
    assert "**stack_three**, `robosuite_stack_three_workspaceview_2000`, table_sized_clearance_and_heights" in text
    paths = []
    for name, results in (("small", small), ("large", large)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(results))
    assert main(["--stack-three", *map(str, paths), "--out", str(tmp_path / "t.md")]) == 0
    assert (tmp_path / "t.md").read_text() == text


def _blocks(**z: float) -> dict:
    return {name: {"position": [0.0, 0.0, 0.8 + height], "yaw": 0.0} for name, height in z.items()}


def test_failure_modes_name_the_cube_that_did_not_reach_the_tower():
    order = ["cubeA", "cubeB", "cubeC"]
    assert failure_mode(order, _blocks(cubeA=0.02, cubeB=0.025, cubeC=0.065), SCENE, "not_done") == \
        "middle cube on the table"
    assert failure_mode(order, _blocks(cubeA=0.02, cubeB=0.065, cubeC=0.02), SCENE, "not_done") == \
        "top cube on the table"
    assert failure_mode(order, _blocks(cubeA=0.02, cubeB=0.025, cubeC=0.02), SCENE, "not_done") == \
        "middle cube on the table and top cube on the table"
    assert failure_mode(order, _blocks(cubeA=0.02, cubeB=0.065, cubeC=0.11), SCENE, "not_done").startswith(
        "tower stands incomplete")
    assert failure_mode(order, {}, SCENE, "unstable") == "unstable"


def test_nut_failure_modes_say_where_the_nut_ended():
    from experiments.robosuite_choices import nut_failure_mode

    scene = {"peg": [0.23, 0.1, 0.85], "table_height": 0.82, "nut_half_height": 0.01}

    def at(x, y, z):
        return {"SquareNut": {"position": [x, y, z], "yaw": 0.0}}

    assert nut_failure_mode(at(0.235, 0.1, 0.90), scene, "not_done") == "on the peg, not down (jammed)"
    assert nut_failure_mode(at(0.30, 0.05, 0.831), scene, "not_done") == "on the table beside the peg"
    assert nut_failure_mode(at(0.0, 0.0, 1.10), scene, "not_done") == "in the air (still held, or resting on something)"
    assert nut_failure_mode(at(0.9, 0.9, 0.2), scene, "not_done") == "off the table"
    assert nut_failure_mode(at(0.0, 0.0, 0.0), scene, "unstable") == "unstable"


def test_the_survey_counts_what_tamp_alone_ran_and_what_the_loops_budget_rescued():
    from experiments.robosuite_choices import survey_summary

    ok = {"choice": "x", "success": True, "kind": "success", "mode": None}
    bad = {"choice": "y", "success": False, "kind": "not_done", "mode": "top cube on the table"}
    skipped = {"choice": "z", "unplannable": "no IK solution"}
    rows = [{"seed": 0, "tried": [ok]},
            {"seed": 1, "tried": [skipped, bad, ok]},  # TAMP alone runs the first plannable choice: it fails
            {"seed": 2, "tried": [bad] * 6 + [ok]},  # rescued, but by the seventh choice: outside the loop's 6
            {"seed": 3, "tried": [skipped] * 3}]  # nothing plannable within the tries
    summary = survey_summary(rows, max_tries=24)
    assert summary["scenes"] == 4 and summary["scenes_with_no_plannable_choice"] == 1
    assert summary["default_failures"] == 2 and summary["default_success_rate"] == round(1 / 3, 3)
    assert summary["rescued_within_6_choices"] == 1 and summary["rescued_within_24_choices"] == 2
    assert summary["unplannable_choices_skipped"] == 4
    assert summary["default_failure_modes"] == {"top cube on the table": 2}


def test_sensitivity_shifts_are_seeded_per_draw_and_scaled():
    import numpy as np
    import pytest

    from experiments.robosuite_sensitivity import shifts

    a = shifts(["cubeB", "cubeA"], seed=3, k=0, xy_std_m=0.003, yaw_std_deg=3.0)
    assert a == shifts(["cubeA", "cubeB"], seed=3, k=0, xy_std_m=0.003, yaw_std_deg=3.0)  # order of names aside
    assert a != shifts(["cubeA", "cubeB"], seed=3, k=1, xy_std_m=0.003, yaw_std_deg=3.0)
    draws = np.array([v for k in range(200) for v in shifts(["o"], 9, k, 0.003, 3.0).values()])
    assert np.std(draws[:, 0]) == pytest.approx(0.003, rel=0.2)
    assert np.degrees(np.std(draws[:, 2])) == pytest.approx(3.0, rel=0.2)


def test_the_choice_features_mark_the_unmoved_base_and_read_every_moved_objects_grasp():
    from experiments.choice_predictability import choice_features

    tower = {"block_order": ["cubeC", "cubeA", "cubeB"], "choice": "cubeC-cubeA-cubeB:10:hc"}
    assert choice_features(tower, ["cubeA", "cubeB", "cubeC"]) == [1.0, 2.0, 0.0, 1.0, 1.0, 0.0, 0.0, -1.0, -1.0]
    bins = {"block_order": ["Bread", "Can", "Cereal", "Milk"], "choice": "Bread-Can-Cereal-Milk:1001:cchh"}
    assert choice_features(bins, ["Bread", "Can", "Cereal", "Milk"]) == [
        0.0, 1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]


def test_the_oracles_errors_are_grouped_by_end_state():
    from experiments.oracle_errors import end_state, tabulate

    attrs = {"block_order": ["cubeA", "cubeB", "cubeC"], "kind": "not_done", "scene": SCENE,
             "final_blocks": {"cubeA": {"position": [0, 0, 0.82]}, "cubeB": {"position": [0.1, 0, 0.825]},
                              "cubeC": {"position": [0, 0, 0.865]}}}
    assert end_state(attrs, False) == "middle cube on the table" and end_state(attrs, True) == "success"
    table = tabulate([("middle cube on the table", False, True), ("middle cube on the table", False, False),
                      ("success", True, True)])
    assert list(table) == ["success", "middle cube on the table"]
    assert table["middle cube on the table"] == {"test_episodes": 2, "errors": 1, "error_rate": 0.5}
    assert table["success"]["errors"] == 0
