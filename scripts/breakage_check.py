"""Break the product on purpose, one change at a time, and record which tests turn red.

A suite that stays green while the physics, the planner, the data pipeline or the scorer is broken
guards nothing. Each breakage below is a one-line change a careless edit could make; for each, a
copy of the working tree gets the change and the tests that should catch it are run. The unbroken
copy must pass the same tests first. The result is written to ``docs/results/breakages.json`` and
``docs/results/breakages.md`` (linked from ``docs/testing.md``).

    MUJOCO_GL=egl .venv/bin/python scripts/breakage_check.py            # every breakage (~10 min)
    MUJOCO_GL=egl .venv/bin/python scripts/breakage_check.py --only held_joint_targets   # updates its row
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOLDEN_SIM = ("tests/golden/test_planner_rates.py", "tests/golden/test_main_job.py",
              "tests/golden/test_shipped_bundles.py::test_the_recorded_outcomes_are_what_the_simulator_gives")


@dataclass(frozen=True)
class Breakage:
    name: str
    what: str  # the change, for people
    file: str
    old: str
    new: str
    tests: tuple[str, ...]  # pytest node ids expected to catch it


BREAKAGES = (
    Breakage("held_joint_targets", "the executor holds each step's joint targets instead of interpolating them",
             "sim_worker/executor.py", "alpha = k / controls_per_step", "alpha = 1.0", GOLDEN_SIM),
    Breakage("block_friction", "block friction 1.0 -> 0.3", "sim_worker/scene.py",
             "block_friction: tuple[float, float, float] = (1.0,", "block_friction: tuple[float, float, float] = (0.3,",
             GOLDEN_SIM),
    Breakage("release_gap", "the planner releases blocks 10 mm instead of 5 mm above their resting height",
             "planner_client/tamp.py", "release_gap: float = 0.005", "release_gap: float = 0.010",
             ("tests/planner_client/test_tamp.py", *GOLDEN_SIM)),
    Breakage("perception_error", "the pose estimates' in-plane error 3 mm -> 4 mm", "sim_worker/perception.py",
             "xy_std: float = 0.003", "xy_std: float = 0.004", GOLDEN_SIM),
    Breakage("features_shuffled", "training features shuffled against the labels", "firp/data.py",
             "    feats = cached_features(dataset_path, encoder, cache_dir, progress=progress, dataset_hash=dataset_hash)\n",
             "    feats = cached_features(dataset_path, encoder, cache_dir, progress=progress, dataset_hash=dataset_hash)\n"
             "    feats = np.asarray(feats)[np.random.default_rng(0).permutation(len(names))]\n",
             ("tests/firp/test_learnability.py",)),
    Breakage("threshold_of_one_member", "the bundle's threshold chosen on one member's scores, not the ensemble's",
             "firp/tune.py", "threshold, ba_at_threshold = choose_threshold(labels, ensemble)",
             "threshold, ba_at_threshold = choose_threshold(labels, probs[-1])",
             ("tests/firp/test_learnability.py::test_tuning_learns_and_the_bundles_manifest_numbers_are_its_own",)),
    Breakage("fused_attention_misattached", "the fused serving path gives each plan another plan's attention",
             "firp/serving/fused.py", "return logits, spread_chunk_weights(w.reshape(M * N, Tc), T, k).view(M, N, T)",
             "return logits, spread_chunk_weights(w.reshape(M * N, Tc), T, k).view(M, N, T).flip(1)",
             ("tests/golden/test_shipped_bundles.py::test_the_fused_path_on_the_shipped_configuration_equals_the_members_forward_pass",)),
    Breakage("strict_acceptance", "the loop accepts a plan only strictly above the threshold",
             "planner_client/loop.py", "return score >= threshold", "return score > threshold",
             ("tests/planner_client/test_loop.py", "tests/experiments/test_replan_threshold.py",
              "tests/golden/test_analyses.py")),
    Breakage("executes_the_first_plan", "the loop executes the first plan scored instead of the accepted one",
             "planner_client/loop.py", "outcome = work.execute(order)  # the accepted plan",
             "outcome = work.execute(orders[0])  # the accepted plan", ("tests/planner_client/test_loop.py",)),
    Breakage("tower_order_by_argsort", "the tower's levels ordered by height alone (ties broken by float noise)",
             "sim_worker/tasks.py", "order = tower_order([float(b.pos[2]) for b in blocks], config.height_tie)",
             "order = list(np.argsort([b.pos[2] for b in blocks]))", ("tests/sim_worker/test_tasks.py",)),
    Breakage("cache_key_without_dataset", "the feature cache's key forgets which dataset it is for",
             "firp/features.py", 'return f"{dataset_hash[:16]}-{cfg.backbone}', 'return f"dataset-{cfg.backbone}',
             ("tests/firp/test_features.py",)),
    Breakage("resume_restarts", "an interrupted feature extraction starts again from the first episode",
             "firp/features.py", 'done = int(json.loads(progress_file.read_text())["done"])', "done = 0",
             ("tests/firp/test_features.py",)),
    Breakage("core_imports_torch", "the shared core imports torch (every torch-free part would load it)",
             "firp/core/contract.py", "import numpy as np\n", "import numpy as np\nimport torch  # noqa: F401\n",
             ("tests/test_layers.py",)),
    Breakage("unstable_frames_kept", "frames after a physics blow-up are kept instead of blanked",
             "sim_worker/executor.py", "frames[t + 1:] = 0", "pass", ("tests/sim_worker/test_executor.py",)),
)


def copy_tree(dest: Path) -> None:
    """The working tree as git sees it (tracked and new files, nothing ignored)."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                           capture_output=True).stdout.decode().split("\0")
    for rel in filter(None, files):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def run_tests(tree: Path, tests: tuple[str, ...], report: Path) -> dict[str, str]:
    """Each test case's outcome (passed / failed / error / skipped), run in ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}", *tests],
                   cwd=tree, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    outcomes = {}
    for case in ET.parse(report).getroot().iter("testcase"):
        kind = next((child.tag for child in case if child.tag in ("failure", "error", "skipped")), "passed")
        outcomes[f"{case.get('classname')}::{case.get('name')}"] = {"failure": "failed"}.get(kind, kind)
    return outcomes


def check(breakage: Breakage, work: Path) -> dict:
    tree = work / breakage.name
    copy_tree(tree)
    target = tree / breakage.file
    text = target.read_text()
    if text.count(breakage.old) != 1:
        raise SystemExit(f"{breakage.name}: {breakage.file} must contain the text to change exactly once")
    target.write_text(text.replace(breakage.old, breakage.new))
    started = time.perf_counter()
    outcomes = run_tests(tree, breakage.tests, work / f"{breakage.name}.xml")
    red = sorted(t for t, o in outcomes.items() if o in ("failed", "error"))
    shutil.rmtree(tree)
    return {"name": breakage.name, "what": breakage.what, "file": breakage.file, "tests_run": len(outcomes),
            "red": red, "caught": bool(red), "seconds": round(time.perf_counter() - started, 1)}


def markdown(rows: list[dict], baseline: dict) -> str:
    lines = ["# Deliberate breakages and the tests that catch them", "",
             "Made by `MUJOCO_GL=egl .venv/bin/python scripts/breakage_check.py`. Every change below was applied "
             "alone to a copy of the tree; the tests listed turned red. Unbroken, the same "
             f"{baseline['tests_run']} tests pass ({baseline['passed']} passed).", "",
             "| breakage | file | caught | red tests (of those run) |", "|---|---|---|---|"]
    for r in rows:
        shown = ", ".join(f"`{t.split('::', 1)[1]}`" for t in r["red"][:4]) + (" ..." if len(r["red"]) > 4 else "")
        lines.append(f"| {r['what']} | `{r['file']}` | {'yes' if r['caught'] else '**no**'} | "
                     f"{len(r['red'])} of {r['tests_run']}: {shown} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", choices=[b.name for b in BREAKAGES], default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "breakages.json")
    args = ap.parse_args()
    chosen = [b for b in BREAKAGES if args.only is None or b.name in args.only]
    with tempfile.TemporaryDirectory(prefix="firp-breakages-") as tmp:
        work = Path(tmp)
        copy_tree(work / "unbroken")
        every = tuple(dict.fromkeys(t for b in chosen for t in b.tests))
        outcomes = run_tests(work / "unbroken", every, work / "unbroken.xml")
        bad = sorted(t for t, o in outcomes.items() if o != "passed")
        if bad:
            print("the unbroken tree does not pass its own tests:\n  " + "\n  ".join(bad), file=sys.stderr)
            return 1
        baseline = {"tests_run": len(outcomes), "passed": len(outcomes)}
        rows = []
        for b in chosen:
            rows.append(check(b, work))
            r = rows[-1]
            print(f"{r['name']:<30} {'caught' if r['caught'] else 'NOT CAUGHT':<10} {len(r['red']):>3}/{r['tests_run']:<3} "
                  f"red  ({r['seconds']} s)", flush=True)
    if args.only is not None and args.out.exists():  # update those rows of the last full run, keep the rest
        last = json.loads(args.out.read_text())
        fresh = {r["name"]: r for r in rows}
        baseline = last["baseline"]
        rows = [fresh.get(r["name"], r) for r in last["breakages"]]
    if args.only is None or args.out.exists():
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": "MUJOCO_GL=egl .venv/bin/python scripts/breakage_check.py",
                                        "baseline": baseline, "breakages": rows}, indent=1))
        args.out.with_suffix(".md").write_text(markdown(rows, baseline))
        print(f"wrote {args.out} and {args.out.with_suffix('.md')}")
    return 0 if all(r["caught"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
