"""The trial loop with real parts: the embedded simulator or a launched sim worker, and the scoring
service launched on loopback with a tiny seeded random bundle (it scores every plan about alike, so
the threshold is set to force a path: 0.0 accepts the first plan, 1.01 never accepts). The accept
rule itself -- the first plan at or above the threshold, whichever of the six it is -- is checked with
a scripted scorer; the shipped bundles' loop is replayed against the committed main job in
tests/golden/test_main_job.py.

Also: resume without double counting and refusing other settings, the report's numbers against
hand-computed records, the CLI end to end with both services launched, and its missing-bundle error.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys

import numpy as np
import pytest

from planner_client.__main__ import main
from planner_client.embedded import EmbeddedSim
from planner_client.launcher import Launcher
from planner_client.loop import ResumeMismatch, RunConfig, RunSetupError, read_records, run_trials
from planner_client.report import markdown, summarise, summary_paths, write_report
from planner_client.tamp import PlannerConfig, TampPlanner, block_orders
from planner_client.transport import RetryPolicy

from .records import assert_same_trials

T = 16  # inside the tiny bundle's T range (8, 16)
FAST = RetryPolicy(attempts=3, base_delay=0.05)
ORDERS = [list(o) for o in block_orders()]


@pytest.fixture(scope="module")
def sim_and_planner():
    sim = EmbeddedSim()
    yield sim, TampPlanner(PlannerConfig(horizon=T))
    sim.close()


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory):
    import torch

    from tests.firp.bundle_helpers import export_tiny

    torch.manual_seed(0)  # the same random members in every run: the scores below are reproducible
    return export_tiny(tmp_path_factory.mktemp("bundle") / "tiny")


class ScriptedScorer:
    """The scoring service's two calls, answered from a script: the k-th plan scored gets ``scores[k]``.

    What a bundle would say does not matter to the loop's rule (the first plan at or above the
    threshold is executed, else the last one scored); a script reaches every branch of it, which an
    untrained bundle scoring every plan alike cannot. It keeps the plans it was sent."""

    def __init__(self, scores: list[float], threshold: float):
        self.scores, self.threshold = list(scores), threshold
        self.plans: list = []
        self.batches: list[list] = []

    def model(self) -> dict:
        return {"name": "scripted", "version": "1", "task": "stacking", "contract": {"t_min": T, "t_max": T}}

    def score(self, image_b64: str, plan, task: str) -> dict:
        assert image_b64 and task == "stacking"
        self.plans.append(plan)
        return {"score": self.scores[len(self.plans) - 1], "threshold": self.threshold}

    def score_batch(self, image_b64: str, plans, task: str) -> dict:
        """All candidates in one call (the ranking, the side-by-side table): the k-th candidate gets
        ``scores[k]``, so a plan scored alone before gets the same score again, as from the service."""
        assert image_b64 and task == "stacking"
        self.batches.append(list(plans))
        return {"results": [{"score": self.scores[k]} for k in range(len(plans))], "threshold": self.threshold}


@pytest.fixture(scope="module")
def scorer(tiny_bundle, tmp_path_factory):
    """The real scoring service as a subprocess (only the service: ``sim=False``)."""
    with Launcher(tmp_path_factory.mktemp("service"), bundle=tiny_bundle, sim=False, ready_timeout=120) as services:
        assert not services.runs_sim
        with services.score_client() as client:
            yield client


# -- without scoring (--no-score): TAMP alone and the oracle -------------------------------------------
def test_records_are_written_as_trials_end_and_resume_skips_them(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    first = list(run_trials(RunConfig(trials=2, out=out, max_iterations=2), sim, planner))
    assert [r["trial"] for r in first] == [0, 1]
    assert len(read_records(out)) == 2
    for r in first:
        assert r["tamp_success"] in (True, False) and "oracle_success" in r and "firp_success" not in r
        # the oracle can only be at least as good as the first plan
        assert r["oracle_success"] or not r["tamp_success"]
    # a torn last line (killed mid-write) is dropped, and the run continues after the good records
    with out.open("a") as f:
        f.write('{"trial": 2, "se')
    more = list(run_trials(RunConfig(trials=3, out=out, max_iterations=2, resume=True), sim, planner))
    assert [r["trial"] for r in more] == [2]
    records = read_records(out)
    assert [r["trial"] for r in records] == [0, 1, 2]
    assert all(json.loads(line) for line in out.read_text().splitlines())
    assert summarise(records)["trials"] == 3
    # each trial's calls carried its own X-Request-ID, kept in its record
    assert [r["request_id"].split("-")[:2] for r in records] == [["trial", "0"], ["trial", "1"], ["trial", "2"]]
    assert len({r["request_id"] for r in records}) == 3


def test_existing_output_needs_resume(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    out.write_text("")
    with pytest.raises(FileExistsError, match="--resume"):
        list(run_trials(RunConfig(trials=1, out=out), sim, planner))


# -- TAMP + FIRP ---------------------------------------------------------------------------------------
def test_threshold_zero_accepts_the_first_plan_and_tamp_reuses_its_execution(tmp_path, sim_and_planner, scorer):
    sim, planner = sim_and_planner
    records = list(run_trials(RunConfig(trials=2, out=tmp_path / "r.jsonl", max_iterations=3, threshold=0.0),
                              sim, planner, scorer))
    for r in records:
        assert r["firp_accepted"] is True and r["firp_iterations"] == 1 and len(r["scores"]) == 1
        assert r["firp_order"] == ORDERS[0] and r["threshold"] == 0.0 and r["service_threshold"] == 0.5
        assert 0.0 <= r["scores"][0] <= 1.0
        # TAMP alone executed the very same plan: one execution, one label
        assert r["tamp_reused_firp_execution"] is True
        assert (r["tamp_success"], r["tamp_reason"]) == (r["firp_success"], r["firp_reason"])
        assert r["run"]["model"]["name"] == "tiny" and r["run"]["threshold"] == 0.0
        assert all(r[k] >= 0 for k in ("plan_s", "score_s", "execute_s", "seconds"))
        assert r["executions"] <= 3  # the oracle reused the first execution


def test_unreachable_threshold_replans_to_the_budget_and_executes_the_last_plan(tmp_path, sim_and_planner, scorer):
    sim, planner = sim_and_planner
    budget = 3
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=budget, threshold=1.01),
                     sim, planner, scorer)
    assert r["firp_accepted"] is False and r["firp_iterations"] == budget and len(r["scores"]) == budget
    assert r["firp_order"] == ORDERS[budget - 1] and r["tamp_reused_firp_execution"] is False
    # what was scored and executed is exactly the last order's plan: redo it by hand and compare
    episode = sim.start("stacking", r["seed"])
    for k in range(budget):
        plan = planner.plan("stacking", episode.observation, block_orders()[k]).actions
        assert scorer.score(episode.image_b64, plan, "stacking")["score"] == pytest.approx(r["scores"][k], abs=1e-6)
    last = sim.execute(episode, planner.plan("stacking", episode.observation, block_orders()[budget - 1]).actions)
    first = sim.execute(episode, planner.plan("stacking", episode.observation, block_orders()[0]).actions)
    assert (r["firp_success"], r["firp_reason"]) == (last.success, last.reason)
    assert (r["tamp_success"], r["tamp_reason"]) == (first.success, first.reason)
    assert r["executions"] == budget  # FIRP's last plan, TAMP's first, the oracle's middle one


def test_service_threshold_is_used_when_none_is_given(tmp_path, sim_and_planner, scorer):
    sim, planner = sim_and_planner
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=2, oracle=False),
                     sim, planner, scorer)
    assert r["threshold"] == r["service_threshold"] == 0.5 and r["run"]["threshold"] is None
    assert "oracle_success" not in r


@pytest.mark.parametrize("accept_at", [1, 2, 3, 4, 5, 6])
def test_the_first_plan_at_or_above_the_threshold_is_the_one_executed(tmp_path, sim_and_planner, accept_at):
    sim, planner = sim_and_planner
    scores = [0.1] * 6
    scores[accept_at - 1] = 0.6  # exactly at the service's threshold: accepted
    scores[accept_at:] = [0.9] * (6 - accept_at)  # better plans later must not be reached
    scripted = ScriptedScorer(scores, threshold=0.6)
    executed_plans = []

    class Recording:  # the real simulator, noting what it is asked to execute
        def start(self, task, seed):
            return sim.start(task, seed)

        def execute(self, episode, plan):
            executed_plans.append(plan)
            return sim.execute(episode, plan)

        def close(self):
            pass

    # the paper's loop alone: no side-by-side scoring of the other candidates
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=6, oracle=False,
                               compare_rules=False), Recording(), planner, scripted)
    order = ORDERS[accept_at - 1]
    assert (r["firp_accepted"], r["firp_iterations"], r["firp_order"]) == (True, accept_at, order)
    assert r["scores"] == scores[:accept_at] and r["threshold"] == 0.6
    # the plans scored were the planner's plans for the orders in the loop's order, and the accepted one ran
    episode = sim.start("stacking", r["seed"])
    planned = [planner.plan("stacking", episode.observation, tuple(o)).actions for o in ORDERS[:accept_at]]
    assert len(scripted.plans) == accept_at
    for sent, plan in zip(scripted.plans, planned):
        np.testing.assert_array_equal(sent, plan)
    np.testing.assert_array_equal(executed_plans[0], planned[-1])  # the accepted plan ran first...
    assert len(executed_plans) == (1 if accept_at == 1 else 2)  # ...then TAMP alone's, unless it was the same
    executed = sim.execute(episode, planned[-1])
    assert (r["firp_success"], r["firp_reason"]) == (executed.success, executed.reason)
    assert r["tamp_reused_firp_execution"] == (accept_at == 1)
    first = sim.execute(episode, planned[0])
    assert (r["tamp_success"], r["tamp_reason"]) == (first.success, first.reason)


def test_the_clients_threshold_overrides_the_services(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    scripted = ScriptedScorer([0.3, 0.55, 0.9], threshold=0.6)
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=3, threshold=0.5, oracle=False),
                     sim, planner, scripted)
    assert (r["firp_iterations"], r["firp_order"], r["threshold"], r["service_threshold"]) == (2, ORDERS[1], 0.5, 0.6)


def test_a_horizon_outside_the_bundles_range_fails_before_any_trial(tmp_path, sim_and_planner, scorer):
    sim, _ = sim_and_planner
    out = tmp_path / "r.jsonl"
    with pytest.raises(RunSetupError, match=r"--horizon 32.*\[8, 16\]"):
        list(run_trials(RunConfig(trials=1, out=out), sim, TampPlanner(PlannerConfig(horizon=32)), scorer))
    assert not out.exists()


# -- resume --------------------------------------------------------------------------------------------
def test_an_interrupted_run_resumes_without_repeating_or_losing_trials(tmp_path, sim_and_planner, scorer):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    config = RunConfig(trials=3, out=out, max_iterations=2, threshold=0.0)
    trials = run_trials(config, sim, planner, scorer)
    assert next(trials)["trial"] == 0
    trials.close()  # interrupted after one trial (as Ctrl-C between trials)...
    with out.open("a") as f:
        f.write('{"trial": 1, "seed": 1000')  # ...or killed while writing the next record
    resumed = list(run_trials(RunConfig(trials=3, out=out, max_iterations=2, threshold=0.0, resume=True),
                              sim, planner, scorer))
    assert [r["trial"] for r in resumed] == [1, 2]
    records = read_records(out)
    assert sorted(r["trial"] for r in records) == [0, 1, 2]
    assert summarise(records)["all_trials"]["tamp_firp"]["trials"] == 3
    # nothing left to do: resuming again runs no trial
    assert list(run_trials(RunConfig(trials=3, out=out, max_iterations=2, threshold=0.0, resume=True),
                           sim, planner, scorer)) == []


@pytest.mark.parametrize("change", [{"threshold": 0.3}, {"max_iterations": 3}, {"seed": 7}, {"task": "replacement"},
                                    {"scorer": None}])
def test_resume_refuses_a_file_written_with_other_settings(tmp_path, sim_and_planner, scorer, change):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    list(run_trials(RunConfig(trials=1, out=out, max_iterations=2, threshold=0.0), sim, planner, scorer))
    before = out.read_text()
    settings = {"trials": 2, "out": out, "max_iterations": 2, "threshold": 0.0, "resume": True, **change}
    use_scorer = settings.pop("scorer", scorer)
    with pytest.raises(ResumeMismatch, match="other settings") as err:
        list(run_trials(RunConfig(**settings), sim, planner, use_scorer))
    key = next(iter(change)).replace("scorer", "scoring")
    assert f"{key}: file" in str(err.value)
    assert out.read_text() == before


# -- the report ----------------------------------------------------------------------------------------
def _record(trial, tamp, firp, accepted, oracle, iterations=1, threshold=0.5):
    return {"trial": trial, "task": "stacking", "tamp_success": tamp, "firp_success": firp, "firp_accepted": accepted,
            "firp_iterations": iterations, "threshold": threshold, "oracle_success": oracle, "plan_s": 0.1,
            "score_s": 0.2, "execute_s": 0.3, "seconds": 1.0,
            "run": {"task": "stacking", "seed": 10, "max_iterations": 6, "threshold": None, "horizon": 120,
                    "oracle": True, "scoring": True, "model": {"name": "m", "version": "v"}}}


def test_summary_tables_match_hand_computed_rates(tmp_path):
    records = [
        _record(0, tamp=True, firp=True, accepted=True, oracle=True),
        _record(1, tamp=False, firp=True, accepted=True, oracle=True, iterations=3),
        _record(2, tamp=False, firp=False, accepted=False, oracle=True, iterations=6),
        _record(3, tamp=False, firp=False, accepted=True, oracle=False, iterations=2),
        _record(4, tamp=True, firp=False, accepted=False, oracle=True, iterations=6),
    ]
    s = summarise(records)
    every = s["all_trials"]
    assert (every["tamp"]["successes"], every["tamp"]["trials"], every["tamp"]["rate"]) == (2, 5, 0.4)
    assert (every["tamp_firp"]["successes"], every["tamp_firp"]["rate"]) == (2, 0.4)
    assert (every["oracle"]["successes"], every["oracle"]["rate"]) == (4, 0.8)
    acc = s["accepted_trials"]  # trials 0, 1, 3
    assert (acc["accepted"], acc["of"]) == (3, 5)
    assert (acc["tamp"]["successes"], acc["tamp"]["trials"]) == (1, 3)
    assert (acc["tamp_firp"]["successes"], acc["tamp_firp"]["rate"]) == (2, pytest.approx(2 / 3))
    assert (acc["oracle"]["successes"], acc["oracle"]["rate"]) == (2, pytest.approx(2 / 3))
    assert s["firp_mean_iterations"] == pytest.approx(18 / 5)
    assert s["mean_timing_s"]["score_s"] == pytest.approx(0.2)

    text = markdown(s)
    assert "| TAMP alone | 2/5 | 40.0% |" in text and "| TAMP + FIRP | 2/5 | 40.0% |" in text
    assert "| oracle (first of 6 block orders that succeeds in simulation) | 4/5 | 80.0% |" in text
    assert "accepted a plan in 3 of 5 trials" in text and "| TAMP + FIRP | 2/3 | 66.7% |" in text

    out = tmp_path / "run.jsonl"
    paths = write_report(s, out)
    assert paths == summary_paths(out)
    assert [p.name for p in paths.values()] == ["run.summary.md", "run.summary.json", "run.summary.png"]
    assert json.loads(paths["json"].read_text()) == json.loads(json.dumps(s))
    assert paths["md"].read_text() == text
    assert paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summary_without_scoring_or_accepted_trials():
    s = summarise([{k: v for k, v in _record(0, True, False, False, True).items()
                    if not k.startswith("firp") and k != "threshold"}])
    assert s["accepted_trials"] is None and s["all_trials"]["tamp_firp"] is None
    assert "| TAMP + FIRP | not run | n/a |" in markdown(s)
    none_accepted = summarise([_record(0, True, False, False, True)])
    assert none_accepted["accepted_trials"]["tamp_firp"] == {"successes": 0, "trials": 0, "rate": None}
    assert "| TAMP + FIRP | 0/0 | n/a |" in markdown(none_accepted)


# -- a killed sim worker mid-run -----------------------------------------------------------------------
@pytest.mark.slow
def test_a_sim_worker_killed_mid_run_loses_no_trial(tmp_path, launcher, scorer):
    sim = launcher.sim(retry=FAST)
    planner = TampPlanner(PlannerConfig(horizon=T))
    restarts = launcher.sim_restarts
    seen = []
    try:
        for record in run_trials(RunConfig(trials=3, out=tmp_path / "r.jsonl", max_iterations=2, threshold=0.0),
                                 sim, planner, scorer):
            seen.append(record["trial"])
            if len(seen) == 1:
                process = launcher.sim_server.process
                os.kill(process.pid, signal.SIGKILL)
                process.wait(10)
    finally:
        sim.close()
    assert seen == [0, 1, 2] and [r["trial"] for r in read_records(tmp_path / "r.jsonl")] == [0, 1, 2]
    assert launcher.sim_restarts == restarts + 1


@pytest.mark.slow
def test_a_scoring_service_killed_mid_run_loses_no_trial(tmp_path, sim_and_planner, tiny_bundle):
    """The launched service is SIGKILLed after the first trial: the next score restarts it on a new
    port, the run goes on, and the restarted service scores the same plan exactly as before."""
    sim, planner = sim_and_planner
    with Launcher(tmp_path / "services", bundle=tiny_bundle, sim=False, ready_timeout=120) as services:
        scorer = services.scorer(retry=FAST)
        seen = []
        try:
            for record in run_trials(RunConfig(trials=3, out=tmp_path / "r.jsonl", max_iterations=2, oracle=False),
                                     sim, planner, scorer):
                seen.append(record)
                if len(seen) == 1:
                    old_url, process = services.service_url, services.service_server.process
                    os.kill(process.pid, signal.SIGKILL)
                    process.wait(10)
            episode = sim.start("stacking", 100_000)
            plan = planner.plan("stacking", episode.observation).actions
            assert scorer.score(episode.image_b64, plan, "stacking")["score"] == pytest.approx(seen[0]["scores"][0])
        finally:
            scorer.close()
        assert [r["trial"] for r in seen] == [0, 1, 2]
        assert [r["trial"] for r in read_records(tmp_path / "r.jsonl")] == [0, 1, 2]
        assert all(len(r["scores"]) >= 1 for r in seen)
        assert services.service_restarts == 1 and services.service_url != old_url
        assert scorer.client.base_url == services.service_url


# -- the CLI -------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_launches_both_services_runs_and_writes_the_report(tmp_path, tiny_bundle, capsys):
    out = tmp_path / "runs" / "run.jsonl"
    code = main(["run", "--trials", "2", "--horizon", str(T), "--max-iterations", "2", "--threshold", "1.01",
                 "--bundle", str(tiny_bundle), "--out", str(out), "--seed", "5"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "## 1. Success rate over all trials" in printed and "accepted a plan in 0 of 2 trials" in printed
    records = read_records(out)
    assert [r["trial"] for r in records] == [0, 1] and [r["seed"] for r in records] == [5, 6]
    assert all(r["firp_iterations"] == 2 and r["firp_order"] == ORDERS[1] for r in records)
    for path in summary_paths(out).values():
        assert path.exists()
    assert {p.name for p in (out.parent / "logs").iterdir()} == {"service.log", "sim_worker.log"}
    # a finished run resumed with other settings is refused, naming them
    assert main(["run", "--trials", "2", "--horizon", str(T), "--max-iterations", "3", "--threshold", "1.01",
                 "--bundle", str(tiny_bundle), "--out", str(out), "--seed", "5", "--resume"]) == 2
    assert "max_iterations: file 2, now 3" in capsys.readouterr().err


def test_cli_names_a_missing_bundle_and_how_to_make_one(tmp_path, capsys):
    missing = tmp_path / "no-bundle"
    out = tmp_path / "runs" / "run.jsonl"
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--trials", "1", "--bundle", str(missing), "--out", str(out)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "does not exist" in err
    assert "firp tune --data data/stacking.h5" in err and "--export models/stacking" in err
    assert not out.parent.exists()  # nothing was launched or written


def test_the_shipped_bundles_are_found_in_the_repositorys_models_folder_or_where_the_setting_says(monkeypatch,
                                                                                                    tmp_path):
    from firp.core.bundle_format import MODELS_DIR_ENV, shipped_bundle_dir

    monkeypatch.delenv(MODELS_DIR_ENV, raising=False)
    root = Path(__file__).resolve().parents[2]
    for task in ("stacking", "replacement"):
        assert shipped_bundle_dir(task) == root / "models" / task
        assert (shipped_bundle_dir(task) / "manifest.json").is_file()
    monkeypatch.setenv(MODELS_DIR_ENV, str(tmp_path))
    assert shipped_bundle_dir("stacking") == tmp_path / "stacking"


def test_the_run_path_never_imports_torch():
    code = ("import sys, planner_client.__main__, planner_client.loop, planner_client.report, "
            "planner_client.session, matplotlib.figure; "
            "from firp.core.bundle_format import shipped_bundle_dir; shipped_bundle_dir('stacking'); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


class Unreachable(TampPlanner):
    """Our planner, except that the arm cannot reach the poses of some block orders (their IK fails)."""

    def __init__(self, unreachable: set[int]):
        super().__init__(PlannerConfig(horizon=T))
        self.unreachable = {block_orders()[k] for k in unreachable}

    def plan(self, task, observation, order=None, planner_seed=None):
        from planner_client.ik import IKFailure

        if tuple(order) in self.unreachable:
            raise IKFailure(f"no IK solution for {order}")
        return super().plan(task, observation, order, planner_seed)


def test_a_candidate_the_planner_cannot_plan_is_skipped_not_scored_and_fails_tamp_alone(sim_and_planner, tmp_path):
    sim, _ = sim_and_planner
    scorer = ScriptedScorer([0.1, 0.9, 0.9], threshold=0.5)
    config = RunConfig(trials=1, seed=5, max_iterations=4, out=tmp_path / "run.jsonl")
    (record,) = list(run_trials(config, sim, Unreachable({0, 2}), scorer))
    # orders 0 and 2 have no plan: order 1 is scored (0.1, rejected), order 3 next (0.9, accepted)
    assert record["scores"] == [0.1, 0.9] and record["firp_order"] == ORDERS[3] and record["firp_accepted"]
    assert len(scorer.plans) == 2
    assert record["tamp_success"] is False and record["tamp_reason"].startswith("no plan: no IK solution")
    assert set(record["unplannable"]) == {str(ORDERS[0]), str(ORDERS[2])}
    if record["oracle_success"]:
        assert record["oracle_order"] in (ORDERS[1], ORDERS[3])
    assert 1 <= record["executions"] <= 2  # only orders 1 and 3 have plans to execute; TAMP alone executes none


def test_a_trial_with_no_plannable_candidate_says_so(sim_and_planner, tmp_path):
    from planner_client.ik import IKFailure

    sim, _ = sim_and_planner
    config = RunConfig(trials=1, seed=5, max_iterations=2, out=tmp_path / "run.jsonl")
    with pytest.raises(IKFailure, match="could plan none of its 2 candidates"):
        list(run_trials(config, sim, Unreachable({0, 1}), ScriptedScorer([0.9], threshold=0.5)))


# -- every execution is data (--record) ------------------------------------------------------------
def test_recorded_executions_are_a_dataset_with_frames_scores_and_scene_ids(tmp_path, sim_and_planner):
    """A scripted scorer rejects the first two plans: the loop executes the third (FIRP), the first (TAMP
    alone) and the oracle's; each execution becomes an episode of the project's layout, whose frame 0
    is the scene's initial image and whose score and bundle version are the ones that chose it."""
    from firp.core.episodes import EpisodeDataset
    from world_api.images import decode_png_b64

    sim, planner = sim_and_planner
    scorer = ScriptedScorer([0.1, 0.2, 0.9] * 4, threshold=0.5)
    config = RunConfig(trials=2, out=tmp_path / "run.jsonl", max_iterations=3, record=tmp_path / "rec")
    records = list(run_trials(config, sim, planner, scorer))
    with EpisodeDataset(tmp_path / "rec" / "executions.h5") as ds:
        assert len(ds) == sum(r["executions"] for r in records) and ds.attrs["T"] == T
        # demo names are trial * 100 + the candidate's place in the loop's order; training reads them by name
        rows = [ds.demo_attrs(n) | {"success": ds.success(n), "frames": ds.frames(n), "actions": ds.actions(n)}
                for n in ds.demo_names]
    for trial, record in enumerate(records):
        mine = [row for row in rows if row["trial"] == trial]
        assert {row["scene_id"] for row in mine} == {f"stacking/{record['seed']}"}
        firp = next(row for row in mine if row["candidate"] == str(record["firp_order"]))
        assert firp["score"] == 0.9 and firp["scored_by"] == {"name": "scripted", "version": "1"}
        assert firp["success"] == record["firp_success"] and firp["candidate_index"] == 2
        tamp = next(row for row in mine if row["candidate_index"] == 0)
        assert tamp["success"] == record["tamp_success"] and tamp["score"] == 0.1
        episode = sim.start("stacking", record["seed"])
        np.testing.assert_array_equal(firp["frames"][0], decode_png_b64(episode.image_b64))
        assert firp["frames"].shape == (T, 84, 84, 3) and firp["actions"].shape == (T, 16)
    # resuming a finished run records nothing twice
    config2 = RunConfig(trials=2, out=tmp_path / "run.jsonl", max_iterations=3, record=tmp_path / "rec", resume=True)
    assert list(run_trials(config2, sim, planner, ScriptedScorer([0.9] * 12, 0.5))) == []
    with EpisodeDataset(tmp_path / "rec" / "executions.h5") as ds:
        assert len(ds) == len(rows)


def test_frames_of_reads_the_sim_workers_base64_frames_and_refuses_none():
    from types import SimpleNamespace

    from planner_client.recording import frames_of
    from world_api.images import encode_png_b64

    frames = np.random.default_rng(0).integers(0, 256, (3, 8, 8, 3), dtype=np.uint8)
    np.testing.assert_array_equal(frames_of(SimpleNamespace(frames_b64=[encode_png_b64(f) for f in frames])), frames)
    np.testing.assert_array_equal(frames_of(SimpleNamespace(frames=frames)), frames)
    with pytest.raises(ValueError, match="no frames"):
        frames_of(SimpleNamespace(frames_b64=None))


# -- the decision rules, the side-by-side table and uninformative bundles ---------------------------------
class EvidencedScorer(ScriptedScorer):
    """A scripted scorer whose bundle carries decision evidence (firp.core.decisions)."""

    def __init__(self, scores: list[float], threshold: float, evidence: dict):
        super().__init__(scores, threshold)
        self.evidence = evidence

    def model(self) -> dict:
        return {**super().model(), "decision_evidence": self.evidence}


def _evidence(low: float, failure_scores: list[float]) -> dict:
    return {"balanced_accuracy": low + 0.1, "interval": [low, low + 0.2], "informative": low > 0.5,
            "failure_scores": failure_scores}


def test_the_ranking_executes_the_highest_scored_candidate_and_every_rule_is_compared(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    scores = [0.2, 0.7, 0.1, 0.95, 0.3, 0.4]  # the paper's rule takes the 2nd (0.7 >= 0.6); the ranking the 4th
    scripted = ScriptedScorer(scores, threshold=0.6)
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=6, oracle=False, rule="rank"),
                     sim, planner, scripted)
    assert (r["firp_rule"], r["firp_order"], r["firp_accepted"]) == ("rank", list(ORDERS[3]), True)
    assert r["scores"] == scores and scripted.plans == [] and len(scripted.batches[0]) == 6
    rules = r["rules"]
    assert rules["threshold"]["order"] == list(ORDERS[1]) and rules["threshold"]["accepted"] is True
    assert rules["rank"]["order"] == list(ORDERS[3]) and "conformal" not in rules  # no evidence: no conformal
    assert rules["tamp_first"]["order"] == list(ORDERS[0])
    assert rules["rank"]["success"] == r["firp_success"] and rules["tamp_first"]["success"] == r["tamp_success"]
    assert list(r["candidate_scores"].values()) == scores
    summary = summarise(read_records(tmp_path / "r.jsonl"))
    assert summary["firp_rule"] == ["rank"] and set(summary["rules"]) == {"threshold", "rank", "tamp_first"}
    assert "## 3. Decision rules side by side" in markdown(summary) and "(this run)" in markdown(summary)


def test_the_conformal_rule_accepts_above_the_validation_failures_quantile(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    failures = [i / 100 for i in range(19)]  # 19 failures at 0.00 .. 0.18: at alpha 0.1 k = 18, q just above 0.17
    scripted = EvidencedScorer([0.1, 0.175, 0.2, 0.9, 0.9, 0.9], threshold=0.6, evidence=_evidence(0.7, failures))
    [r] = run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", max_iterations=6, oracle=False, rule="conformal",
                               alpha=0.1), sim, planner, scripted)
    assert r["firp_rule"] == "conformal" and r["firp_order"] == list(ORDERS[1]) and r["firp_iterations"] == 2
    assert 0.17 < r["threshold"] < 0.171 and r["service_threshold"] == 0.6 and r["run"]["alpha"] == 0.1
    assert r["rules"]["conformal"]["order"] == list(ORDERS[1]) and r["rules"]["threshold"]["order"] == list(ORDERS[3])


def test_too_few_failures_for_alpha_accept_nothing_and_the_record_stays_json(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    scripted = EvidencedScorer([0.99] * 6, threshold=0.5, evidence=_evidence(0.7, [0.1, 0.2, 0.3]))
    out = tmp_path / "r.jsonl"
    [r] = run_trials(RunConfig(trials=1, out=out, max_iterations=6, oracle=False, rule="conformal", alpha=0.1),
                     sim, planner, scripted)
    assert r["firp_accepted"] is False and r["firp_iterations"] == 6 and 1.0 < r["threshold"] < 1.0 + 1e-12
    json.loads(out.read_text().splitlines()[0], parse_constant=lambda c: pytest.fail(f"{c} in the record"))


def test_the_conformal_rule_needs_the_bundles_failure_scores(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    with pytest.raises(RunSetupError, match="firp certify"):
        list(run_trials(RunConfig(trials=1, out=tmp_path / "r.jsonl", rule="conformal"), sim, planner,
                        ScriptedScorer([0.9], threshold=0.5)))


def test_an_uninformative_bundle_executes_tamps_first_plan_and_the_summary_says_so(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    scripted = EvidencedScorer([0.1, 0.9, 0.9, 0.9, 0.9, 0.9], threshold=0.5, evidence=_evidence(0.45, [0.1, 0.2]))
    out = tmp_path / "r.jsonl"
    [r] = run_trials(RunConfig(trials=1, out=out, max_iterations=6, oracle=False), sim, planner, scripted)
    assert (r["firp_rule"], r["firp_order"], r["firp_accepted"]) == ("tamp_first", list(ORDERS[0]), False)
    assert r["firp_success"] == r["tamp_success"] and r["scores"] == [0.1]
    assert r["rules"]["threshold"]["order"] == list(ORDERS[1])  # what replanning would have executed
    assert r["run"]["model"]["evidence"]["informative"] is False
    text = markdown(summarise(read_records(out)))
    assert "not shown better than chance" in text and "executed TAMP's first plan" in text
    # the override replans on the scores anyway, and says so
    [again] = run_trials(RunConfig(trials=1, out=tmp_path / "o.jsonl", max_iterations=6, oracle=False,
                                   replan_on_uninformative=True), sim, planner,
                         EvidencedScorer([0.1, 0.9, 0.9, 0.9, 0.9, 0.9], threshold=0.5, evidence=_evidence(0.45, [0.1, 0.2])))
    assert (again["firp_rule"], again["firp_order"]) == ("threshold", list(ORDERS[1]))
    assert "replanned on its scores anyway" in markdown(summarise(read_records(tmp_path / "o.jsonl")))


# -- trials in parallel ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_trials_in_parallel_on_two_sim_workers_equal_a_sequential_run(tmp_path, scorer):
    planner = TampPlanner(PlannerConfig(horizon=T))
    config = dict(trials=4, max_iterations=3, threshold=0.5, seed=20)
    with Launcher(tmp_path / "a", sim=True) as first, Launcher(tmp_path / "b", sim=True) as second:
        sim_a, sim_b = first.sim(), second.sim()
        try:
            sequential = list(run_trials(RunConfig(out=tmp_path / "seq.jsonl", **config), sim_a, planner, scorer))
            # two trials at once, one on each worker; a run of 2 resumed to 4 in parallel
            list(run_trials(RunConfig(out=tmp_path / "par.jsonl", **{**config, "trials": 2}), sim_a, planner, scorer,
                            sims=[sim_a, sim_b]))
            resumed = list(run_trials(RunConfig(out=tmp_path / "par.jsonl", resume=True, **config), sim_a, planner,
                                      scorer, sims=[sim_a, sim_b]))
        finally:
            sim_a.close()
            sim_b.close()
    assert [r["trial"] for r in resumed] == [2, 3]
    parallel = read_records(tmp_path / "par.jsonl")
    assert [r["trial"] for r in parallel] == [0, 1, 2, 3]  # the run file stays in trial order
    assert_same_trials(parallel, sequential)
    assert len({r["request_id"] for r in parallel}) == 4


@pytest.mark.slow
def test_cli_parallel_launches_k_sim_workers_and_one_service(tmp_path, tiny_bundle):
    out = tmp_path / "runs" / "run.jsonl"
    assert main(["run", "--trials", "3", "--horizon", str(T), "--max-iterations", "2", "--threshold", "1.01",
                 "--bundle", str(tiny_bundle), "--out", str(out), "--seed", "5", "--parallel", "2"]) == 0
    records = read_records(out)
    assert [r["trial"] for r in records] == [0, 1, 2] and [r["seed"] for r in records] == [5, 6, 7]
    assert {p.name for p in (out.parent / "logs").iterdir()} == {"service.log", "sim_worker.log"}
    assert {p.name for p in (out.parent / "sim-1" / "logs").iterdir()} == {"sim_worker.log"}


def test_cli_parallel_must_match_the_sim_urls_given(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--trials", "1", "--no-score", "--sim", "http://127.0.0.1:9,http://127.0.0.1:10",
              "--parallel", "3", "--out", str(tmp_path / "r.jsonl")])
    assert exit_.value.code == 2
    assert "--parallel: with --sim one trial runs on each given sim worker at a time; 3 asked, 2 URL(s)" in \
        capsys.readouterr().err


def test_exploration_executes_the_least_sure_candidates_and_records_every_label(tmp_path, sim_and_planner, scorer):
    sim, planner = sim_and_planner
    threshold = 0.5
    records = list(run_trials(RunConfig(trials=2, out=tmp_path / "run.jsonl", max_iterations=4, threshold=threshold,
                                        seed=60, explore=4), sim, planner, scorer))
    for record in records:
        scores, outcomes = record["candidate_scores"], record["candidate_outcomes"]
        assert outcomes.keys() == scores.keys()  # with a budget of 4 every plannable candidate is executed
        assert record["executions"] == len(outcomes)
        explored = [scores[json.dumps(order)] for order in record["explored"]]
        assert [abs(s - threshold) for s in explored] == sorted(abs(s - threshold) for s in explored)
        assert outcomes[json.dumps(record["firp_order"])] == record["firp_success"]
    assert records[0]["run"]["explore"] == 4


def test_cli_exploration_needs_scores(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["run", "--trials", "1", "--no-score", "--explore", "2", "--out", str(tmp_path / "r.jsonl")])
    assert "--explore picks the candidates the ensemble is least sure of" in capsys.readouterr().err


class SwappedMidRun(ScriptedScorer):
    """The run starts on version 1 (``/v1/model``); once ``swapped`` is set, version 2 answers (a hot swap)."""

    swapped = False

    def _version(self) -> dict:
        return {"name": "scripted", "version": "2" if self.swapped else "1"}

    def score(self, image_b64: str, plan, task: str) -> dict:
        self.plans.clear()  # every trial replays the same script
        return {**super().score(image_b64, plan, task), "model": self._version()}

    def score_batch(self, image_b64: str, plans, task: str) -> dict:
        return {**super().score_batch(image_b64, plans, task), "model": self._version()}


def test_records_name_the_version_that_scored_when_a_swap_comes_mid_run(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    scorer = SwappedMidRun([0.9] * 6, threshold=0.5)
    trials = run_trials(RunConfig(trials=2, out=tmp_path / "run.jsonl", max_iterations=3, record=tmp_path / "rec"),
                        sim, planner, scorer)
    first = next(trials)
    scorer.swapped = True
    (second,) = list(trials)
    assert "scored_by" not in first  # the run's model scored everything: its identity says so
    assert set(second["scored_by"].values()) == {"2"} and second["run"]["model"]["version"] == "1"
    from firp.core.episodes import EpisodeDataset

    with EpisodeDataset(tmp_path / "rec" / "executions.h5") as ds:
        versions = {ds.demo_attrs(n)["trial"]: ds.demo_attrs(n)["scored_by"]["version"]
                    for n in ds.demo_names if "scored_by" in ds.demo_attrs(n)}
    assert versions == {0: "1", 1: "2"}
