"""The ``firp`` command: every subcommand reaches its part, and the torch-free ones stay torch-free."""

from __future__ import annotations

import subprocess
import sys

import pytest

from firp_cli import COMMANDS, main

PROBE = """
import sys
import firp_cli
try:
    firp_cli.main([{command!r}, "--help"])
except SystemExit:
    pass
print("LOADED", "torch" in sys.modules, "mujoco" in sys.modules)
"""


@pytest.mark.parametrize("command, torch_free", [("run", True), ("collect", True), ("sim", True), ("robosuite", True),
                                                 ("tune", False), ("certify", False),
                                                 ("evaluate", False), ("serve", False)])
@pytest.mark.slow
def test_each_subcommand_shows_its_own_options_and_imports_only_its_part(command, torch_free):
    out = subprocess.run([sys.executable, "-c", PROBE.format(command=command)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert f"usage: firp {command}" in out.stdout
    loaded = out.stdout.strip().splitlines()[-1].split()
    if torch_free:
        assert loaded[1] == "False", f"firp {command} imported torch"
    if command in ("tune", "certify", "evaluate", "serve"):
        assert loaded[2] == "False", f"firp {command} imported mujoco"


def test_the_list_of_commands_and_the_errors(capsys):
    assert main([]) == 2 and "usage: firp COMMAND" in capsys.readouterr().out
    assert main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert all(f"  {name} " in listed for name in COMMANDS)
    assert main(["juggle"]) == 2
    assert "unknown command 'juggle'; one of run, collect, tune, certify, refresh, evaluate, serve, sim, robosuite" in \
        capsys.readouterr().err


def test_the_console_script_is_installed():
    import shutil
    from pathlib import Path

    script = Path(sys.executable).with_name("firp")
    assert script.exists() or shutil.which("firp"), "pip install -e . installs the firp console script"
    out = subprocess.run([str(script if script.exists() else "firp"), "collect", "--task", "juggling"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "invalid choice: 'juggling'" in out.stderr
