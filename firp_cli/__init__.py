"""``firp``: the one command of the product, each subcommand a part of it.

    firp run        the main job: plan, score, replan, execute (python -m planner_client run)
    firp collect    simulate a labelled dataset (python -m planner_client collect)
    firp tune       Optuna study and the top-five bundle (python -m firp.tune)
    firp evaluate   the evaluation protocol (python -m firp.evaluate)
    firp serve      the scoring service (python -m service)
    firp sim        the sim worker (python -m sim_worker serve)
    firp robosuite  the robosuite worker, in its own environment (python -m robosuite_worker serve)

This package sits above every part and imports each one only when its subcommand runs, so the
torch-free subcommands (run, collect, sim) never load torch and ``firp --help`` loads nothing.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

__all__ = ["COMMANDS", "main"]


def _run(module: str, *, prefix: tuple[str, ...] = (), prog: bool = True) -> Callable[[list[str], str], int]:
    def call(argv: list[str], name: str) -> int:
        entry = importlib.import_module(module).main
        return entry([*prefix, *argv], prog=name) if prog else entry([*prefix, *argv])
    return call


#: subcommand -> (what it does, how to run it)
COMMANDS: dict[str, tuple[str, Callable[[list[str], str], int]]] = {
    "run": ("the main job: TAMP alone, TAMP + FIRP and the oracle on the same scenes",
            _run("planner_client.__main__", prefix=("run",))),
    "collect": ("simulate labelled episodes into an HDF5 dataset (resumable)",
                _run("planner_client.__main__", prefix=("collect",))),
    "tune": ("Optuna study over the training parameters; --export writes the top-five bundle",
             _run("firp.tune", prog=False)),
    "certify": ("measure a bundle's decision evidence on its validation episodes (into its manifest)",
                _run("firp.bundle.evidence")),
    "refresh": ("retrain the bundle on collected + recorded data; promote it only if not worse on held-out scenes",
                _run("firp.refresh")),
    "evaluate": ("the evaluation protocol: every method on the same splits", _run("firp.evaluate", prog=False)),
    "serve": ("the scoring service (FastAPI): POST /v1/score, the V2 inference protocol", _run("service.__main__")),
    "sim": ("the sim worker (FastAPI over MuJoCo): start episodes, execute plans",
            _run("sim_worker.__main__", prefix=("serve",))),
    "robosuite": ("the robosuite worker: the same API over robosuite's tasks (run from .venv-robosuite)",
                  _run("robosuite_worker.__main__", prefix=("serve",))),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: firp COMMAND [options]   (firp COMMAND --help for a command's options)", "", "commands:"]
    lines += [f"  {name:<{width}}  {summary}" for name, (summary, _) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"firp: unknown command {name!r}; one of {', '.join(COMMANDS)}\n\n{usage()}", file=sys.stderr)
        return 2
    result = COMMANDS[name][1](rest, f"firp {name}" if name not in ("run", "collect") else "firp")
    return int(result or 0)
