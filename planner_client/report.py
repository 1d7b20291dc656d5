"""The run's report: the paper's two tables from the trial records, as text, Markdown, JSON and a chart.

Table 1 -- success rate over all trials: TAMP alone, TAMP + FIRP, and the oracle line (the ceiling
of replanning over block orders within the budget). Table 2 -- the same three, over the trials in
which FIRP accepted a plan (a score reached the threshold), with how many that were: what a
deployment that refuses to execute unaccepted plans would see. Table 3 -- the decision rules side by
side on the same scenes (the paper's rule, the ranking, the conformal rule, TAMP's first plan), when
the run scored every candidate. Above the tables: the bundle's validation evidence and what the run
did with an uninformative bundle.

Everything is computed from the JSONL records alone (a resumed run's records included), so the
report can be rebuilt from a run file at any time. Rates of an empty set are ``None`` (JSON null),
not NaN, which is not JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

LINES = (("tamp", "tamp_success", "TAMP alone"),
         ("tamp_firp", "firp_success", "TAMP + FIRP"),
         ("oracle", "oracle_success", "oracle"))
TIMING = ("start_s", "plan_s", "score_s", "execute_s", "seconds")


def _rate(records: list[dict], key: str, universe: list[dict]) -> dict | None:
    """``{successes, trials, rate}`` of ``key`` over ``records``; None if no record of ``universe``
    (the records the table is drawn from) has ``key`` -- that line was not run."""
    if not any(key in r for r in universe):
        return None
    have = [r for r in records if key in r]
    k = sum(bool(r[key]) for r in have)
    return {"successes": k, "trials": len(have), "rate": k / len(have) if have else None}


def _table(records: list[dict], universe: list[dict]) -> dict:
    return {name: _rate(records, key, universe) for name, key, _ in LINES}


RULES = (("threshold", "the paper's rule: first plan at or above the threshold, else the last scored"),
         ("rank", "ranking: the highest-scored of all candidates"),
         ("conformal", "conformal: the paper's rule at the threshold bounding accepted failures at alpha"),
         ("tamp_first", "TAMP's first plan (what an uninformative bundle gets)"))


def _rules_table(records: list[dict]) -> dict | None:
    """Per rule, over the trials that compared the rules: successes, trials, rate, how many accepted."""
    compared = [r for r in records if "rules" in r]
    if not compared:
        return None
    table = {}
    for rule, _ in RULES:
        picks = [r["rules"][rule] for r in compared if rule in r["rules"]]
        if picks:
            k = sum(p["success"] for p in picks)
            table[rule] = {"successes": k, "trials": len(picks), "rate": k / len(picks),
                           "accepted": sum(bool(p["accepted"]) for p in picks)}
    return table


def summarise(records: list[dict]) -> dict:
    """Both tables and the run's settings, from the records (one per trial)."""
    n = len(records)
    run = records[0].get("run", {}) if records else {}
    scored = [r for r in records if "firp_accepted" in r]
    accepted = [r for r in scored if r["firp_accepted"]]
    out: dict = {
        "task": run.get("task", records[0]["task"] if records else None), "trials": n, "run": run,
        "all_trials": _table(records, records),
        "accepted_trials": ({"accepted": len(accepted), "of": len(scored), **_table(accepted, scored)}
                            if scored else None),
    }
    if scored:
        out["firp_rule"] = sorted({r.get("firp_rule", "threshold") for r in scored})
        out["rules"] = _rules_table(scored)
        out["firp_mean_iterations"] = sum(r["firp_iterations"] for r in scored) / len(scored)
        out["thresholds"] = sorted({r["threshold"] for r in scored})
    out["mean_timing_s"] = {k: sum(r[k] for r in records if k in r) / n
                            for k in TIMING if n and any(k in r for r in records)}
    return out


def _cell(line: dict | None) -> tuple[str, str]:
    if line is None:
        return "not run", "n/a"
    if line["rate"] is None:
        return "0/0", "n/a"
    return f"{line['successes']}/{line['trials']}", f"{100 * line['rate']:.1f}%"


def _candidates(run: dict) -> str:
    """What the loop replans over: block orders in our world, the planner's choices in robosuite's."""
    return "block orders" if run.get("task") in ("stacking", "replacement", None) else "planner choices"


def _labels(summary: dict) -> dict[str, str]:
    budget = summary["run"].get("max_iterations")
    oracle = (f"oracle (first of {budget} {_candidates(summary['run'])} that succeeds in simulation)" if budget
              else "oracle")
    return {"tamp": "TAMP alone", "tamp_firp": "TAMP + FIRP", "oracle": oracle}


def _markdown_table(table: dict, labels: dict[str, str]) -> list[str]:
    rows = ["| method | successes | success rate |", "|---|---|---|"]
    for name, _, _ in LINES:
        rows.append("| {} | {} | {} |".format(labels[name], *_cell(table.get(name))))
    return rows


def _settings_line(summary: dict) -> str:
    """One sentence saying how the run was made (seeds, budget, threshold, horizon, model)."""
    run = summary["run"]
    first = run.get("seed")
    seeds = f"{first}..{first + summary['trials'] - 1}" if first is not None and summary["trials"] else "none"
    budget = run.get("max_iterations")
    if not run.get("scoring", True):
        firp = f"no scoring (--no-score), oracle over {budget} {_candidates(run)}"
    else:
        threshold = run.get("threshold")
        thresholds = ", ".join(f"{t:g}" for t in summary.get("thresholds", []))
        firp = (f"at most {budget} plans scored per trial, threshold "
                + (f"{threshold:g}" if threshold is not None else f"{thresholds} (the service's)"))
        if run.get("rule"):
            firp += f", decision rule {run['rule']}" + (f" (alpha {run['alpha']:g})" if run["rule"] == "conformal" else "")
    model = run.get("model")
    model_text = f", model {model.get('name')} (version {model.get('version')})" if model else ""
    return f"Scene seeds {seeds}, {firp}, plan horizon T = {run.get('horizon')}{model_text}."


def _evidence_line(summary: dict) -> list[str]:
    """What the bundle's validation evidence says, and what the run did about it."""
    evidence = (summary["run"].get("model") or {}).get("evidence")
    if not evidence:
        return ["The bundle carries no validation evidence (`firp certify` measures it); its scores were used."]
    low, high = evidence["interval"]
    text = (f"The bundle's validation balanced accuracy is {evidence['balanced_accuracy']:.3f}, "
            f"95% interval [{low:.3f}, {high:.3f}]")
    if evidence["informative"]:
        return [text + ": above chance."]
    if "tamp_first" in summary.get("firp_rule", []):
        return [text + ", which reaches 0.5: the bundle is not shown better than chance, so TAMP + FIRP executed "
                "TAMP's first plan (its scores were recorded, not used; `--replan-on-uninformative` overrides)."]
    return [text + ", which reaches 0.5; the run replanned on its scores anyway (`--replan-on-uninformative`)."]


def _rules_section(summary: dict) -> list[str]:
    table = summary.get("rules")
    if not table:
        return []
    used = summary.get("firp_rule", [])
    rows = ["", "## 3. Decision rules side by side", "",
            "Every candidate planned and scored in one call; each rule's pick executed on the same scene "
            "(executions shared).", "",
            "| rule | successes | success rate | picks at or above the threshold |", "|---|---|---|---|"]
    for rule, label in RULES:
        if rule in table:
            line = table[rule]
            mark = " (this run)" if rule in used else ""
            if rule == "conformal":
                label = label.replace("at alpha", f"at alpha = {summary['run'].get('alpha', 0.1):g}")
            accepted = "n/a" if rule == "tamp_first" else f"{line['accepted']}/{line['trials']}"
            rows.append(f"| {label}{mark} | {line['successes']}/{line['trials']} | {100 * line['rate']:.1f}% | "
                        f"{accepted} |")
    return rows


def markdown(summary: dict) -> str:
    """Both tables as Markdown (also what is printed at the end of a run)."""
    labels = _labels(summary)
    evidence = _evidence_line(summary) if summary.get("accepted_trials") is not None else []
    lines = [f"# {summary['task']}: {summary['trials']} trials", "", _settings_line(summary), "",
             *([*evidence, ""] if evidence else []),
             "## 1. Success rate over all trials", "", *_markdown_table(summary["all_trials"], labels),
             "", "## 2. Success rate over the trials FIRP accepted", ""]
    acc = summary.get("accepted_trials")
    if acc is None:
        lines.append("FIRP did not run (--no-score).")
    else:
        # rules that execute their pick whatever its score: "accepted" says the score reached the threshold
        always = {"tamp_first": "TAMP's first plan", "rank": "The highest-scored plan"}
        rule = summary.get("firp_rule", [])
        if len(rule) == 1 and rule[0] in always:
            sentence = (f"{always[rule[0]]}, executed in every trial, scored at or above the threshold in "
                        f"{acc['accepted']} of {acc['of']} trials.")
        else:
            others = ("" if acc["accepted"] == acc["of"] else
                      "; in the others it executed the last plan after the budget ran out")
            sentence = f"FIRP accepted a plan in {acc['accepted']} of {acc['of']} trials{others}."
        lines += [sentence, "", *_markdown_table(acc, labels)]
    lines += _rules_section(summary)
    if "firp_mean_iterations" in summary:
        lines += ["", f"Mean plans scored per trial: {summary['firp_mean_iterations']:.2f}."]
    timing = summary.get("mean_timing_s") or {}
    if timing:
        parts = [f"{'total' if k == 'seconds' else k.removesuffix('_s')} {v:.3f}" for k, v in timing.items()]
        lines += ["", "Mean seconds per trial: " + ", ".join(parts) + "."]
    return "\n".join(lines) + "\n"


def bar_chart(summary: dict, path: Path) -> None:
    """Two panels (all trials; FIRP-accepted trials), three bars each; missing lines are marked n/a."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display; Agg renders the PNG

    fig = Figure(figsize=(9, 3.8), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    acc = summary.get("accepted_trials")
    panels = [(axes[0], summary["all_trials"], f"all trials (n = {summary['trials']})"),
              (axes[1], acc, f"trials FIRP accepted (n = {acc['accepted']} of {acc['of']})" if acc
               else "trials FIRP accepted (FIRP not run)")]
    colours = {"tamp": "#9e9e9e", "tamp_firp": "#1f77b4", "oracle": "#2ca02c"}
    for ax, table, title in panels:
        for x, (name, _, label) in enumerate(LINES):
            line = (table or {}).get(name)
            rate = line["rate"] if line and line["rate"] is not None else None
            ax.bar(x, rate or 0.0, color=colours[name])
            ax.text(x, (rate or 0.0) + 0.02, "n/a" if rate is None else f"{100 * rate:.0f}%", ha="center")
        ax.set_xticks(range(len(LINES)), [label for _, _, label in LINES])
        ax.set_ylim(0, 1.1)
        ax.set_title(title, fontsize=10)
    axes[0].set_ylabel("success rate")
    fig.suptitle(f"{summary['task']}: success rate", fontsize=11)
    fig.savefig(path, dpi=120)


def summary_paths(out: Path) -> dict[str, Path]:
    """``runs/run.jsonl`` -> ``runs/run.summary.md``, ``.summary.json``, ``.summary.png``."""
    stem = out.with_suffix("") if out.suffix == ".jsonl" else out
    return {ext: stem.with_name(stem.name + f".summary.{ext}") for ext in ("md", "json", "png")}


def write_report(summary: dict, out: Path) -> dict[str, Path]:
    """The three summary files beside the run file ``out``; their paths."""
    paths = summary_paths(out)
    paths["md"].write_text(markdown(summary))
    paths["json"].write_text(json.dumps(summary, indent=2) + "\n")
    bar_chart(summary, paths["png"])
    return paths
