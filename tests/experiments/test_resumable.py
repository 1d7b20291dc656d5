"""Long experiments resume: only the seeds a records file lacks are run, each appended as it ends."""

from __future__ import annotations

import json

from experiments.resumable import run_seeds


def _init(tag: str) -> None:
    global TAG
    TAG = tag


def _square(seed: int) -> dict:
    return {"seed": seed, "square": seed * seed, "tag": TAG}


def _never(seed: int) -> dict:
    raise AssertionError(f"seed {seed} was already done and must not run again")


def test_run_seeds_runs_only_the_missing_seeds_and_appends_them(tmp_path):
    records = tmp_path / "records.jsonl"
    records.write_text(json.dumps({"seed": 0, "square": 0, "tag": "earlier"}) + "\n"
                       + json.dumps({"seed": 1, "square": 1, "tag": "earlier"}) + "\n" + '{"seed": 2, "sq')  # torn line
    done = run_seeds(records, _square, [0, 1, 2, 3], workers=2, initializer=_init, initargs=("now",), desc="test")
    assert {s: (r["square"], r["tag"]) for s, r in done.items()} == {0: (0, "earlier"), 1: (1, "earlier"),
                                                                     2: (4, "now"), 3: (9, "now")}
    again = run_seeds(records, _never, [0, 1, 2, 3], workers=2, initializer=_init, initargs=("never",), desc="test")
    assert again == done


def test_a_torn_last_line_is_cut_before_appending_so_later_records_stay_readable(tmp_path):
    records = tmp_path / "records.jsonl"
    records.write_text(json.dumps({"seed": 0}) + "\n" + '{"seed": 1, "squ')
    run_seeds(records, _square, [0, 1], workers=1, initializer=_init, initargs=("now",), desc="test")
    lines = records.read_text().splitlines()
    assert [json.loads(line)["seed"] for line in lines] == [0, 1]  # the torn half-line is gone, not glued to
