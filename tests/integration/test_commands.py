"""Every command as a user meets it: ``--help`` and ``-v`` everywhere, and a bad flag, a bad
scenario or a bad transport exits with status 2 and a message naming it, sending nothing.

The commands are the console scripts the installed ``scara-fuzzy`` distribution declares,
run as a user runs them (the scripts pip wrote), so a command added to ``pyproject.toml`` is
tested without being listed here."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sysconfig
import tomllib
from pathlib import Path

import pytest
from support import ROOT, SLOWDOWN

from controller.node import GIVE_UP_VARIABLE, STARTUP_VARIABLE

DISTRIBUTION = "scara-fuzzy"
SCRIPTS = Path(sysconfig.get_path("scripts"))
COMMANDS = {
    entry.name: entry.value
    for entry in importlib.metadata.distribution(DISTRIBUTION).entry_points.select(
        group="console_scripts"
    )
}
"""Each installed command and its ``module:function``."""

pytestmark = pytest.mark.timeout(120)


def run(command: str, *args: str) -> subprocess.CompletedProcess[str]:
    """The installed ``command`` with ``args``, from the repository root, to its end."""
    return subprocess.run(
        [str(SCRIPTS / command), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60 * SLOWDOWN,
    )


def test_the_installed_commands_are_those_pyproject_declares() -> None:
    """An install older than ``pyproject.toml`` would leave a new command untested here."""
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert declared == COMMANDS, "reinstall: pip install -e '.[test]'"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_explains_the_command_and_offers_verbosity(command: str) -> None:
    done = run(command, "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:") and "-v, --verbose" in done.stdout, done.stdout


@pytest.mark.parametrize(
    ("command", "args", "named"),
    [
        ("controller", ["reference", "--rate", "0"], "--rate"),
        ("plant_sim", ["reference", "--rate", "0"], "--rate"),
        ("controller", ["reference", "--rate", "5000"], "--rate"),
        ("scara-run", ["reference", "--rate", "-1"], "--rate"),
        ("controller", ["reference", "--comms-timeout", "0"], "--comms-timeout"),
        ("controller", ["reference", "--max-wall-time", "nan"], "--max-wall-time"),
        ("plant_sim", ["reference", "--duration", "-3"], "--duration"),
        ("controller", ["reference", "--realtime-priority", "100"], "--realtime-priority"),
        ("scara-run", ["reference", "--timeout", "0"], "--timeout"),
        ("scara-router", ["--port", "70000"], "--port"),
        ("scara-busload", ["--rate", "0"], "--rate"),
        ("scara-soak", ["--minutes", "0"], "--minutes"),
        ("scara-soak", ["--seed", "-1"], "--seed"),
        ("controller", ["reference", "--comms-timeout", "0.004"], "--comms-timeout"),
        ("controller", ["reference", "--inject-faults", "drop=2"], "inject-faults.drop"),
        ("plant_sim", ["no-such-scenario"], "scenario"),
        ("scara-run", ["no-such-scenario"], "scenario"),
        ("scara-sim", ["no-such-scenario"], "scenario"),
        ("scara-bridge", ["--rate", "joints=fast"], "--rate"),
        ("scara-bridge", ["--rate", "speed=10"], "--rate"),
        ("scara-bridge", ["--robot", "arm/1"], "robot name"),
        ("scara-bridge", ["--zenoh-host", "10.1.2.3"], "--zenoh-host"),
        ("scara-bridge", ["--user", "operator"], "--password-file"),
        ("scara-monitor", ["--count", "0"], "--count"),
        ("scara-monitor", ["--zenoh-host", "10.1.2.3"], "--zenoh-host"),
        ("scara-monitor", ["--task", "no-such-scenario"], "scenario"),
        ("scara-record", ["--scenario", "no-such-scenario"], "scenario"),
        ("scara-record", ["--duration", "0"], "--duration"),
        ("scara-replay", ["x.mcap", "--rate", "0"], "--rate"),
        ("scara-replay", ["x.mcap", "--only", "Nope"], "--only"),
        ("scara-plot", ["no-such.mcap"], "no-such.mcap"),
    ],
)
def test_a_bad_value_exits_2_naming_it(command: str, args: list[str], named: str) -> None:
    transport = ["--interface", "virtual"] if command in ("controller", "plant_sim") else []
    done = run(command, *args, *transport)
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    assert named in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("variable", [GIVE_UP_VARIABLE, STARTUP_VARIABLE])
def test_a_bad_lockstep_wait_in_the_environment_exits_2_naming_it(
    variable: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(variable, "-1")
    done = run("controller", "reference", "--clock", "lockstep", "--interface", "virtual")
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    assert variable in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_a_bad_scenario_file_names_the_field(tmp_path: Path) -> None:
    scenario = tmp_path / "bad.toml"
    scenario.write_text(
        "[[waypoints]]\nt = 0.0\nx = 0.4\ny = 0.1\nz = 0.25\n"
        "[[waypoints]]\nt = 1.0\nx = 0.9\ny = 0.32\nz = 0.26\n"
    )
    done = run("controller", str(scenario), "--interface", "virtual")
    assert done.returncode == 2
    assert "waypoints[1]" in done.stderr and "out of reach" in done.stderr


def test_a_node_without_a_router_says_how_to_start_one(port: int) -> None:
    done = run(
        "plant_sim", "--interface", "zenoh", "--bus-option", f"port={port}",
        "--bus-option", "open_timeout=0.5",
    )  # fmt: skip
    assert done.returncode == 2
    assert "scara-router" in done.stderr and str(port) in done.stderr


def test_scara_report_of_a_missing_run_exits_2(tmp_path: Path) -> None:
    done = run("scara-report", str(tmp_path / "nothing"))
    assert done.returncode == 2 and "cannot read the run" in done.stderr
