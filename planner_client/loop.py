"""The trial loop: per trial a new episode, replanning until FIRP accepts a plan, execution, baselines.

One trial (scene seed ``seed + trial``):

1. **TAMP + FIRP** -- under the run's decision rule (``--rule``, :mod:`firp.core.decisions`):

   * ``threshold``, the paper's and the default: plan with the planner's first candidate (in our world the
     first block order of :func:`block_orders`; in the robosuite world the default
     :class:`~planner_client.robosuite_tamp.Choice`), score the plan with the scoring service; while the
     score is below the threshold and fewer than ``max_iterations`` plans were scored, replan with the next
     candidate and score again. The accepted plan -- or, when the budget ran out, the *last* one scored, as
     the paper does -- is executed in the simulator.
   * ``rank``: plan every candidate, score them in one ``/v1/score/batch`` call, execute the highest.
   * ``conformal``: the paper's loop at the threshold that bounds the rate of accepted failures at
     ``alpha``, from the bundle's validation failures' scores.

   When the bundle's validation interval reaches 0.5 (not shown better than chance), no rule is applied:
   TAMP's first plan is executed (``firp_rule: tamp_first``), so the scorer cannot make the loop worse than
   TAMP alone. With ``compare_rules`` every candidate is also scored in one call and each rule's pick
   executed, so the record says what every rule would have done on the scene.
2. **TAMP alone** -- the planner's first plan, executed without scoring, on the same episode.
3. **Oracle** -- the first candidate (same order, same budget) whose plan succeeds when executed:
   the ceiling of replanning over the planner's candidates within this budget.
4. **Exploration** (``explore`` > 0, with a scorer) -- besides all of the above, up to ``explore`` more
   candidates are executed, those the ensemble is least sure of first (score nearest the threshold), so
   a recording run (``--record``) lands labels where the model is weakest. The record's
   ``candidate_outcomes`` then holds the label of every candidate executed, beside ``candidate_scores``.

Every execution starts from the episode's initial state and the simulator is deterministic, so a
plan is planned and executed at most once per trial and the three lines share executions (the
record says how many were really run). Records are appended to a JSONL file as each trial ends;
each carries the run's identity (task, seed, threshold setting, budget, horizon, model), so an
interrupted run resumes without repeating or losing trials and a file is never continued with
different settings.
"""

from __future__ import annotations

import copy
import json
import queue
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable, Iterator, Protocol, Sequence

import numpy as np

from firp.core.decisions import (DECISION_RULES, chosen_by_rule, conformal_threshold, first_accepted,
                                 is_informative)
from firp.core.tracing import configure_tracing, span, tracer_of
from planner_client.backend import SimBackend, SimOutcome
from planner_client.ik import IKFailure
from planner_client.ray_trials import RayTrials, trials_on_ray
from planner_client.recording import ExecutionRecorder, frames_of
from planner_client.transport import TRACING_SERVICE_NAME, request_id


@dataclass(frozen=True)
class RunConfig:
    task: str = "stacking"
    trials: int = 50
    seed: int = 100_000  # trial i uses scene seed seed + i (apart from the dataset seeds 0..)
    max_iterations: int = 6
    oracle: bool = True
    out: Path = Path("runs/run.jsonl")
    resume: bool = False
    threshold: float | None = None  # None: the service's own threshold (each answer carries it)
    record: Path | None = None  # record every executed plan, with frames, as episodes here (planner_client.recording)
    world: str = "mujoco"  # for the recorded dataset's attrs
    rule: str = "threshold"  # firp.core.decisions.DECISION_RULES: the paper's, the ranking, the conformal one
    alpha: float = 0.1  # the conformal rule's bound on the false-accept rate
    compare_rules: bool = True  # also score every candidate, so the summary shows every rule side by side
    explore: int = 0  # execute up to this many more candidates, the least sure first (labels for --record)
    replan_on_uninformative: bool = False  # replan even when the bundle is not shown better than chance


class Planner(Protocol):
    """What the loop needs of a planner (:class:`planner_client.tamp.TampPlanner` for our world,
    :class:`planner_client.robosuite_tamp.RobosuiteTampPlanner` for robosuite's): its candidates for a scene,
    the default first, a plan per candidate, the plan length, and a JSON name per candidate for records."""

    def candidates(self, task: str, observation: dict) -> list[Hashable]: ...

    def plan(self, task: str, observation: dict, candidate: Any) -> Any: ...  # .actions: (T, 16)

    def horizon(self, task: str) -> int: ...

    def describe(self, candidate: Any) -> Any: ...


class Scorer(Protocol):
    """What the loop needs of the scoring service (:class:`planner_client.clients.ScoreClient`)."""

    def score(self, image_b64: str, plan: np.ndarray, task: str) -> dict: ...

    def score_batch(self, image_b64: str, plans: Sequence[np.ndarray], task: str) -> dict: ...

    def model(self) -> dict: ...


class RunSetupError(ValueError):
    """The run cannot start as asked (settings that contradict the service or the run file)."""


class ResumeMismatch(RunSetupError):
    """The run file was written by a run with other settings; continuing it would mix two runs."""


def read_records(path: Path) -> list[dict]:
    """Completed trial records; a torn last line (killed mid-write) is ignored."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return records


def run_identity(config: RunConfig, planner: Planner, model: dict | None, scoring: bool | None = None) -> dict:
    """What must not change between the parts of one run (``trials`` may grow: that extends it).

    ``scoring`` defaults to whether a model is given (the CLI checks its flags before the service names it)."""
    scoring = model is not None if scoring is None else scoring
    identity = {
        "task": config.task, "seed": config.seed, "max_iterations": config.max_iterations,
        "threshold": config.threshold, "horizon": planner.horizon(config.task), "oracle": config.oracle,
        "scoring": scoring,
        "model": None if model is None else {"name": model.get("name"), "version": model.get("version"),
                                             "evidence": _evidence_summary(model.get("decision_evidence"))},
    }
    if scoring:
        identity.update(rule=config.rule, alpha=config.alpha, compare_rules=config.compare_rules,
                        replan_on_uninformative=config.replan_on_uninformative)
        if config.explore:  # absent when off, so runs recorded before the option resume unchanged
            identity["explore"] = config.explore
    return json.loads(json.dumps(identity))  # as it reads back from the file


def _evidence_summary(evidence: dict | None) -> dict | None:
    """The bundle's validation evidence as a run's records keep it (the failure scores stay in the bundle)."""
    if not evidence:
        return None
    return {"balanced_accuracy": evidence.get("balanced_accuracy"), "interval": evidence.get("interval"),
            "informative": is_informative(evidence)}


def check_resumable(records: list[dict], identity: dict, out: Path, ignore: tuple[str, ...] = ()) -> None:
    """Refuse to continue ``out`` if any record was written with different settings (keys in
    ``ignore`` are not compared: the CLI checks its flags before the service tells the model)."""
    identity = {k: v for k, v in identity.items() if k not in ignore}
    for record in records:
        theirs = record.get("run")
        if theirs is not None:
            theirs = {k: v for k, v in theirs.items() if k not in ignore}
        if theirs == identity:
            continue
        if theirs is None:
            raise ResumeMismatch(f"--out {out}: trial {record.get('trial')} was written without the run's settings "
                                 "(an older version of the loop); start a new run with another --out")
        diff = ", ".join(f"{k}: file {theirs.get(k)!r}, now {identity.get(k)!r}"
                         for k in sorted(set(theirs) | set(identity)) if theirs.get(k) != identity.get(k))
        raise ResumeMismatch(f"--out {out} was written with other settings ({diff}); resume with the same settings "
                             "or choose another --out")


def check_model(model: dict, config: RunConfig, planner: Planner) -> None:
    """A bundle for another task, or plans outside its T range, would be rejected at every call:
    fail before the first trial."""
    if model.get("task") not in (None, config.task):
        raise RunSetupError(f"--task {config.task}: the scoring service's bundle {model.get('name')!r} is for task "
                            f"{model.get('task')!r}")
    contract = model.get("contract") or {}
    t_min, t_max = contract.get("t_min"), contract.get("t_max")
    horizon = planner.horizon(config.task)
    if t_min is not None and t_max is not None and not t_min <= horizon <= t_max:
        raise RunSetupError(f"--horizon {horizon}: the scoring service's bundle {model.get('name')!r} accepts plans of "
                            f"T in [{t_min}, {t_max}] only; pass --horizon in that range or use another bundle")


@dataclass(frozen=True)
class NoPlan:
    """The outcome of a candidate the planner could not plan (the arm cannot reach its poses): a failure
    that costs no execution."""

    reason: str
    success: bool = False
    kind: str = "no_plan"
    sim_seconds: float = 0.0


@dataclass
class TrialWork:
    """One trial's plans and executions, each made at most once, with the time each kind took."""

    sim: SimBackend[Any]
    planner: Planner
    episode: Any
    plans: dict[Hashable, np.ndarray | None] = field(default_factory=dict)
    outcomes: dict[Hashable, SimOutcome] = field(default_factory=dict)
    unplannable: dict[Hashable, str] = field(default_factory=dict)  # candidate -> why it has no plan
    timing: dict[str, float] = field(default_factory=lambda: {"start_s": 0.0, "plan_s": 0.0, "score_s": 0.0,
                                                              "execute_s": 0.0})
    # recording (firp run --record): the trial, the loop's order of candidates, the scores they got
    recorder: ExecutionRecorder | None = None
    trial: int = 0
    candidates: list[Hashable] = field(default_factory=list)
    scores: dict[Hashable, float] = field(default_factory=dict)
    model: dict | None = None
    # the bundle version that answered each score: the run's model unless a hot swap came mid-run
    versions: dict[Hashable, str] = field(default_factory=dict)

    def keep_score(self, candidate: Hashable, score: float, answer: dict) -> None:
        """A candidate's first score and the version that gave it (a score kept before stays)."""
        if candidate not in self.scores:
            self.scores[candidate] = score
            version = (answer.get("model") or {}).get("version")
            if version is not None:
                self.versions[candidate] = str(version)

    def scored_by(self, candidate: Hashable) -> dict | None:
        """Name and version of the bundle that scored ``candidate`` (None: not scored)."""
        if candidate not in self.scores:
            return None
        return {**(self.model or {}), **({"version": self.versions[candidate]} if candidate in self.versions else {})}

    def plan(self, candidate: Hashable) -> np.ndarray | None:
        """The candidate's plan, or None when the planner cannot plan it (the reason is kept)."""
        if candidate not in self.plans:
            started = time.perf_counter()
            try:
                self.plans[candidate] = self.planner.plan(self.episode.task, self.episode.observation,
                                                          candidate).actions
            except IKFailure as exc:
                self.plans[candidate] = None
                self.unplannable[candidate] = f"no plan: {exc}"
            self.timing["plan_s"] += time.perf_counter() - started
        return self.plans[candidate]

    def score(self, scorer: Scorer, candidate: Hashable) -> dict:
        """The scoring service's answer for ``candidate``'s plan (which must exist), timed and kept in
        :attr:`scores` (a score kept before stays: the service is deterministic)."""
        started = time.perf_counter()
        answer = scorer.score(self.episode.image_b64, self.plans[candidate], self.episode.task)
        self.timing["score_s"] += time.perf_counter() - started
        self.keep_score(candidate, float(answer["score"]), answer)
        return answer

    def execute(self, candidate: Hashable) -> SimOutcome:
        """The outcome of ``candidate``'s plan; executed once -- the simulator is deterministic from the
        episode's initial state, so a second execution would give the same label."""
        plan = self.plan(candidate)
        if plan is None:
            return NoPlan(self.unplannable[candidate])
        if candidate not in self.outcomes:
            started = time.perf_counter()
            if self.recorder is None:
                self.outcomes[candidate] = self.sim.execute(self.episode, plan)
            else:
                self.outcomes[candidate] = outcome = self.sim.execute(self.episode, plan, record_frames=True)
                self.recorder.record(trial=self.trial, place=self.candidates.index(candidate), episode=self.episode,
                                     candidate=str(self.planner.describe(candidate)), plan=plan, outcome=outcome,
                                     frames=frames_of(outcome), score=self.scores.get(candidate),
                                     model=self.scored_by(candidate))
            self.timing["execute_s"] += time.perf_counter() - started
        return self.outcomes[candidate]


def accepts(score: float, threshold: float) -> bool:
    """The paper's acceptance rule: a plan is executed when its score reaches the threshold."""
    return score >= threshold


def chosen_candidate(scores: Sequence[float], threshold: float) -> int:
    """Which of the plans scored in the loop's order the loop executes: the first one :func:`accepts`
    takes, else the last one scored (the paper's rule when the budget runs out). The replays of the
    loop on recorded candidates (``experiments.replan_threshold``) call this, so there is one rule."""
    return first_accepted(scores, threshold)[0]


NEVER = float(np.nextafter(1.0, 2.0))  # a threshold no probability reaches (finite, so JSON can hold it)


@dataclass(frozen=True)
class Decision:
    """How the run decides, fixed before its first trial from the settings and the bundle's evidence."""

    rule: str  # the rule whose pick TAMP + FIRP executes; "tamp_first" when the bundle is uninformative
    threshold: float | None  # the run's threshold (None: the service's, read from each answer)
    conformal: float | None  # the conformal threshold at alpha (None: the bundle carries no evidence)


def decision_for(config: RunConfig, model: dict) -> Decision:
    """The run's :class:`Decision`; refuses a conformal rule on a bundle without failure scores."""
    if config.rule not in DECISION_RULES:
        raise RunSetupError(f"--rule {config.rule}: one of {', '.join(DECISION_RULES)}")
    evidence = model.get("decision_evidence") or {}
    conformal = None
    if evidence.get("failure_scores"):
        # too few failures to bound alpha gives inf: no score clears NEVER either, and JSON can hold it
        conformal = min(conformal_threshold(evidence["failure_scores"], config.alpha), NEVER)
    elif config.rule == "conformal":
        raise RunSetupError(f"--rule conformal: the scoring service's bundle {model.get('name')!r} carries no "
                            "validation failure scores (decision_evidence); run `firp certify` on it first")
    rule = config.rule
    if is_informative(evidence) is False and not config.replan_on_uninformative:
        rule = "tamp_first"
    return Decision(rule, config.threshold, conformal)


def score_every_candidate(work: TrialWork, scorer: Scorer, orders: list[Hashable]) -> tuple[list[Hashable], dict]:
    """The plannable candidates (in the planner's order) and one ``/v1/score/batch`` answer for all of
    them; candidates scored before keep their scores (the service is deterministic: the same numbers)."""
    plannable = [c for c in orders if work.plan(c) is not None]
    if not plannable:
        raise IKFailure(f"seed {work.episode.seed}: the planner could plan none of its {len(orders)} candidates")
    started = time.perf_counter()
    answer = scorer.score_batch(work.episode.image_b64, [work.plans[c] for c in plannable], work.episode.task)
    work.timing["score_s"] += time.perf_counter() - started
    for candidate, result in zip(plannable, answer["results"]):
        work.keep_score(candidate, float(result["score"]), answer)
    return plannable, answer


def rules_side_by_side(work: TrialWork, scorer: Scorer, orders: list[Hashable], decision: Decision,
                       service_threshold: float) -> dict:
    """Every rule's pick among all candidates, executed (executions are shared), for the summary's
    side-by-side table: what each rule would have given on this scene."""
    plannable, _ = score_every_candidate(work, scorer, orders)
    scores = [work.scores[c] for c in plannable]
    threshold = service_threshold if decision.threshold is None else decision.threshold
    rules: dict[str, dict] = {}
    for rule in DECISION_RULES:
        if rule == "conformal" and decision.conformal is None:
            continue
        index, accepted = chosen_by_rule(rule, scores, threshold, decision.conformal)
        outcome = work.execute(plannable[index])
        rules[rule] = {"order": work.planner.describe(plannable[index]), "accepted": bool(accepted),
                       "success": bool(outcome.success),
                       "threshold": decision.conformal if rule == "conformal" else threshold}
    first = work.execute(orders[0])
    rules["tamp_first"] = {"order": work.planner.describe(orders[0]), "accepted": None,
                           "success": bool(first.success)}
    return {"rules": rules, "candidate_scores": {json.dumps(work.planner.describe(c)): work.scores[c]
                                                 for c in plannable}}


def executed_part(work: TrialWork, candidate: Hashable, accepted: bool, scores: list[float], threshold: float,
                  service_threshold: float) -> dict:
    """The FIRP part of the record: ``candidate``'s plan executed, with the scores the rule looked at."""
    outcome = work.execute(candidate)
    return {"firp_success": bool(outcome.success), "firp_reason": outcome.reason, "firp_accepted": bool(accepted),
            "firp_iterations": len(scores), "firp_order": work.planner.describe(candidate), "scores": scores,
            "threshold": threshold, "service_threshold": service_threshold}


def rank_all(work: TrialWork, scorer: Scorer, orders: list[Hashable], threshold: float | None) -> dict:
    """The ranking rule: plan every candidate, score them in one call, execute the highest-scored."""
    plannable, answer = score_every_candidate(work, scorer, orders)
    scores = [work.scores[c] for c in plannable]
    used_threshold = float(answer["threshold"]) if threshold is None else threshold
    index, accepted = chosen_by_rule("rank", scores, used_threshold)
    return executed_part(work, plannable[index], accepted, scores, used_threshold, float(answer["threshold"]))


def tamp_first(work: TrialWork, scorer: Scorer, orders: list[Hashable]) -> dict:
    """An uninformative bundle: its score of TAMP's first plan is recorded, the plan executed regardless
    (``firp_accepted`` says whether the score reached the threshold, as for the ranking's pick)."""
    if work.plan(orders[0]) is None:
        raise IKFailure(f"seed {work.episode.seed}: the planner cannot plan its first candidate "
                        f"({work.unplannable[orders[0]]})")
    answer = work.score(scorer, orders[0])
    score, threshold = work.scores[orders[0]], float(answer["threshold"])
    return executed_part(work, orders[0], score >= threshold, [score], threshold, threshold)


def decide(work: TrialWork, scorer: Scorer, orders: list[Hashable], decision: Decision) -> dict:
    """The FIRP part of the record under the run's rule."""
    if decision.rule == "tamp_first":
        part = tamp_first(work, scorer, orders)
    elif decision.rule == "rank":
        part = rank_all(work, scorer, orders, decision.threshold)
    else:
        threshold = decision.conformal if decision.rule == "conformal" else decision.threshold
        part = replan_until_accepted(work, scorer, orders, threshold)
    return {"firp_rule": decision.rule, **part}


def replan_until_accepted(work: TrialWork, scorer: Scorer, orders: list[Hashable],
                          threshold: float | None) -> dict:
    """Score the plans of the candidates ``orders`` until one reaches the threshold; the FIRP part of the record."""
    scores: list[float] = []
    accepted = False
    answer: dict = {}
    used_threshold = float("nan")
    order = orders[0]  # the last candidate scored
    for candidate in orders:
        if work.plan(candidate) is None:  # nothing to score: the next candidate
            continue
        order = candidate
        answer = work.score(scorer, candidate)
        used_threshold = float(answer["threshold"]) if threshold is None else threshold
        scores.append(float(answer["score"]))
        if accepts(scores[-1], used_threshold):
            accepted = True
            break
    if not scores:
        raise IKFailure(f"seed {work.episode.seed}: the planner could plan none of its {len(orders)} candidates")
    # the accepted plan, or the last one when the budget ran out
    return executed_part(work, order, accepted, scores, used_threshold, float(answer["threshold"]))


def explore(work: TrialWork, scorer: Scorer, orders: list[Hashable], budget: int, threshold: float) -> dict:
    """Execute up to ``budget`` candidates not executed yet, those whose score lies nearest ``threshold``
    first (the ensemble's least sure), so their labels are recorded where the model is weakest."""
    if all(c in work.scores for c in orders if work.plan(c) is not None):
        plannable = [c for c in orders if work.plans[c] is not None]
    else:
        plannable, _ = score_every_candidate(work, scorer, orders)
    waiting = sorted((c for c in plannable if c not in work.outcomes), key=lambda c: abs(work.scores[c] - threshold))
    chosen = waiting[:budget]
    for candidate in chosen:
        work.execute(candidate)
    return {"explored": [work.planner.describe(c) for c in chosen]}


def candidate_outcomes(work: TrialWork) -> dict:
    """The label of every candidate executed in the trial, keyed as ``candidate_scores`` is."""
    return {json.dumps(work.planner.describe(c)): bool(o.success) for c, o in work.outcomes.items()}


def oracle_line(work: TrialWork, orders: list[Hashable]) -> dict:
    """The first candidate whose plan succeeds in simulation (executions already made are reused)."""
    for examined, order in enumerate(orders, start=1):
        if work.execute(order).success:
            return {"oracle_success": True, "oracle_order": work.planner.describe(order), "oracle_executions": examined}
    return {"oracle_success": False, "oracle_order": None, "oracle_executions": len(orders)}


def run_trial(trial: int, config: RunConfig, sim: SimBackend[Any], planner: Planner, scorer: Scorer | None,
              identity: dict, recorder: ExecutionRecorder | None = None, decision: Decision | None = None) -> dict:
    """One trial's record (see the module docstring for what is run). Every call of the trial to the sim
    worker and the scoring service carries the trial's ``X-Request-ID``, which the record keeps.
    ``decision`` (:func:`decision_for`, made once per run) is needed when there is a scorer."""
    if scorer is not None and decision is None:
        raise ValueError("a trial with a scorer needs the run's decision (decision_for)")
    tracer = tracer_of(configure_tracing(TRACING_SERVICE_NAME), "firp.planner")
    with request_id(f"trial-{trial}-{uuid.uuid4().hex[:12]}") as rid, \
            span(tracer, "trial", {"firp.trial": trial, "firp.seed": config.seed + trial, "firp.task": config.task,
                                   "firp.request_id": rid}) as trace_id:
        record = _run_trial(trial, config, sim, planner, scorer, identity, recorder, decision)
    return {**record, "request_id": rid, **({"trace_id": trace_id} if trace_id else {})}


def _run_trial(trial: int, config: RunConfig, sim: SimBackend[Any], planner: Planner, scorer: Scorer | None,
               identity: dict, recorder: ExecutionRecorder | None, decision: Decision | None) -> dict:
    started = time.perf_counter()
    seed = config.seed + trial
    episode = sim.start(config.task, seed)
    orders = planner.candidates(config.task, episode.observation)[: config.max_iterations]
    work = TrialWork(sim, planner, episode, recorder=recorder, trial=trial, candidates=list(orders),
                     model=identity.get("model"))
    work.timing["start_s"] = time.perf_counter() - started
    record: dict = {"trial": trial, "seed": seed, "task": config.task, "run": identity}
    if scorer is not None and decision is not None:
        record.update(decide(work, scorer, orders, decision))
        if config.compare_rules:
            record.update(rules_side_by_side(work, scorer, orders, decision, record["service_threshold"]))
    tamp = work.execute(orders[0])
    record.update(tamp_success=bool(tamp.success), tamp_reason=tamp.reason)
    if scorer is not None:
        # same plan, same initial state, deterministic simulator: TAMP alone reuses FIRP's execution
        record["tamp_reused_firp_execution"] = record["firp_order"] == planner.describe(orders[0])
    if config.oracle:
        record.update(oracle_line(work, orders))
    if scorer is not None and config.explore:
        threshold = record["service_threshold"] if config.threshold is None else config.threshold
        record.update(explore(work, scorer, orders, config.explore, threshold))
        record["candidate_outcomes"] = candidate_outcomes(work)
    run_version = (identity.get("model") or {}).get("version")
    if any(v != run_version for v in work.versions.values()):  # a bundle swapped in while the run went on
        record["scored_by"] = {json.dumps(planner.describe(c)): v for c, v in work.versions.items()}
    record["executions"] = len(work.outcomes)
    if work.unplannable:
        record["unplannable"] = {str(planner.describe(c)): why for c, why in work.unplannable.items()}
    delete = getattr(sim, "delete", None)  # a sim worker keeps episodes until they expire: free it now
    if delete is not None:
        delete(episode)
    record.update({k: round(v, 4) for k, v in work.timing.items() if scorer is not None or k != "score_s"})
    record["seconds"] = round(time.perf_counter() - started, 3)
    return record


def in_trial_order(pending: list[int], sims: Sequence[SimBackend[Any]], planner: Planner,
                   run_one: Callable[[int, SimBackend[Any], Planner], dict]) -> Iterator[dict]:
    """``run_one(trial, sim, planner)`` for every pending trial, yielded in trial order.

    With one sim the trials run one after another. With several, one trial runs on each at a time, in
    threads that wait on HTTP (the sim workers simulate, the scoring service micro-batches the
    concurrent requests); each thread has its own copy of the planner (its IK's MuJoCo data is not
    shared). A trial's record is yielded once every earlier one is, so the run file stays in trial
    order and a resumed run skips a prefix plus what finished; an interrupt cancels the trials not
    begun."""
    if len(sims) <= 1:
        for trial in pending:
            yield run_one(trial, sims[0], planner)
        return
    slots: queue.SimpleQueue = queue.SimpleQueue()
    for sim in sims:
        slots.put((sim, copy.deepcopy(planner)))

    def job(trial: int) -> dict:
        sim, own_planner = slots.get()
        try:
            return run_one(trial, sim, own_planner)
        finally:
            slots.put((sim, own_planner))

    pool = ThreadPoolExecutor(len(sims), thread_name_prefix="trial")
    try:
        futures = [pool.submit(job, trial) for trial in pending]
        for future in futures:
            yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def run_trials(config: RunConfig, sim: SimBackend[Any] | None, planner: Planner,
               scorer: Scorer | None = None, sims: Sequence[SimBackend[Any]] = (),
               ray: RayTrials | None = None) -> Iterator[dict]:
    """Run the pending trials, appending one JSON line per finished trial; yields each record.

    Without a scorer only TAMP alone and the oracle line are run (``--no-score``). With ``sims`` (several
    sim backends, ``sim`` among them or not) the trials run in parallel, one on each (:func:`in_trial_order`);
    with ``ray`` they run on Ray actors, each with our world in its own process (``sim`` unused:
    :mod:`planner_client.ray_trials`). Every record equals the sequential run's but for its timings and
    request id."""
    if ray is not None and config.record is not None:
        raise RunSetupError("--record writes the executions on this machine's disk; it does not run with --ray")
    if ray is None and sim is None and not sims:
        raise ValueError("run_trials needs a sim backend (or ray)")
    model = scorer.model() if scorer is not None else None
    identity = run_identity(config, planner, model)
    if config.out.exists() and not config.resume:
        raise FileExistsError(f"--out: {config.out} exists; pass --resume to continue it or choose another file")
    records = read_records(config.out)
    check_resumable(records, identity, config.out)
    decision = None
    if model is not None:
        check_model(model, config, planner)
        decision = decision_for(config, model)
    config.out.parent.mkdir(parents=True, exist_ok=True)
    done = {r["trial"] for r in records}
    # rewrite without a torn tail so appends start on a clean line
    config.out.write_text("".join(json.dumps(r) + "\n" for r in records))
    recorder = None if config.record is None else ExecutionRecorder(config.record, config.task,
                                                                    planner.horizon(config.task), config.world)
    try:
        pending = [trial for trial in range(config.trials) if trial not in done]

        def run_one(trial: int, trial_sim: SimBackend[Any], trial_planner: Planner) -> dict:
            return run_trial(trial, config, trial_sim, trial_planner, scorer, identity, recorder, decision)

        if ray is not None:
            records_in_order = trials_on_ray(ray, pending, config=config, planner=planner, identity=identity,
                                             decision=decision)
        else:
            records_in_order = in_trial_order(pending, list(sims) or [sim], planner, run_one)
        with config.out.open("a") as sink:
            for record in records_in_order:
                if recorder is not None:
                    record["recorded_executions"] = record["executions"]
                sink.write(json.dumps(record) + "\n")
                sink.flush()
                yield record
    finally:
        if recorder is not None:
            recorder.consolidate()  # the parts of the trials run so far, merged: readable by training
