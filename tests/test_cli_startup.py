"""`cellctl` starts without what its command does not use: `--help`, a refused argument and a
command that reads a file import no controller, API server, broker client or driver (they
load when the command runs), and the kind registry reads every kind's declaration without
its driver or emulator. Checked on the real entry point in a child process (the modules it
imported when it ended), never by timing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import click
import pytest

from cellctl.kinds import registry
from cellctl.ui.cli import COMMANDS, main
from cellctl.ui.common import HELP_WIDTH, clause_summary, subcommands

#: What a command that does not run the cell (or talk to it) must not import.
HEAVY = (
    "cellctl.cell.controller",
    "cellctl.service.access",
    "cellctl.service.functions",
    "cellctl.service.methods",
    "cellctl.service.server",
    "cellctl.service.client",
    "cellctl.mailbox.mqtt",
    "cellctl.factory.controller",
    "cellctl.plan.engine",
    "cellctl.drivers.plc",
    "cellctl.kinds.ibm7545.driver",
    "cellctl.kinds.dyna2400.driver",
    "cellctl.kinds.iso_cnc.driver",
    "cellctl.kinds.ur.driver",
    "aiomqtt",
    "paho",
    "uvicorn",
    "starlette",
    "websockets",
    "textual",
    "pymodbus",
    "asyncua",
    "playwright",
)

#: Commands as a user types them: help of every kind of command, and a file-only check.
LIGHT = [
    ["--help"],
    ["cell", "check", "--help"],
    ["run", "--help"],
    ["orders", "--help"],
    ["robot", "status", "--help"],
    ["mill", "download", "--help"],
    ["dnc", "send", "--help"],
    ["emulate", "--help"],
    ["console", "--help"],
    ["dashboard", "--help"],
    ["demo", "--help"],
    ["factory", "--help"],
    ["estop", "--help"],
    ["plan", "--help"],
    ["kinds"],
]


#: A child process: runs its code, then writes every module it imported (sys.modules) to
#: the file named by its first argument.
CHILD = """
import json, sys
out, sys.argv = sys.argv[1], ["cellctl", *sys.argv[2:]]
try:
    {code}
finally:
    with open(out, "w") as f:
        json.dump(sorted(sys.modules), f)
"""
#: `cellctl ARGS` as the installed script runs it (its entry point, cellctl.ui.cli:main).
CELLCTL = "from cellctl.ui.cli import main; main()"


def _imported(
    tmp_path: Path, code: str, *args: str
) -> tuple[subprocess.CompletedProcess[str], set[str]]:
    """Run ``code`` in a child process (``sys.argv`` is ``cellctl ARGS``): the finished
    process and every module it had imported when it ended."""
    out = tmp_path / f"modules-{len(list(tmp_path.iterdir()))}.json"
    indented = "\n    ".join(code.split("; "))
    done = subprocess.run(
        [sys.executable, "-c", CHILD.format(code=indented), str(out), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,  # nothing a command writes lands outside the test's directory
        env={**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")},
    )
    return done, set(json.loads(out.read_text()))


def _heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY))


@pytest.mark.parametrize("args", LIGHT, ids=" ".join)
def test_a_command_that_does_not_run_the_cell_imports_none_of_it(
    tmp_path: Path, args: list[str]
) -> None:
    done, modules = _imported(tmp_path, CELLCTL, *args)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Usage:" in done.stdout or args == ["kinds"], done.stdout
    assert "cellctl.ui.cli" in modules  # the real entry point ran
    assert not _heavy(modules), f"cellctl {' '.join(args)} imported {_heavy(modules)}"


def test_a_refused_argument_imports_none_of_the_cell(tmp_path: Path) -> None:
    done, modules = _imported(tmp_path, CELLCTL, "submit", "wax-robot-base", "--qty", "0")
    assert done.returncode == 2 and "--qty" in done.stderr, done.stderr[-2000:]
    assert not _heavy(modules), _heavy(modules)


def test_a_command_that_runs_imports_what_it_needs(tmp_path: Path) -> None:
    """The guard above is not vacuous: a command that goes to a machine imports the service
    and the driver (here one whose link nobody answers: exit 3, the link's error)."""
    link = "socket://127.0.0.1:1"
    done, modules = _imported(tmp_path, CELLCTL, "robot", "--link", link, "status")
    assert done.returncode == 3 and f"cannot connect to {link}" in done.stderr, done.stderr
    assert {"cellctl.service.access", "cellctl.kinds.ibm7545.driver"} <= set(_heavy(modules))


def test_the_api_client_imports_neither_the_server_nor_the_cells_access(tmp_path: Path) -> None:
    """A command that asks a running controller (``cellctl alarm list`` beside ``cellctl
    run``) loads the client alone: the server, the method table and the cell's own access
    (the standalone cell) come with a command that opens the machines itself. The client's
    WebSocket library comes when it connects: a command that finds no controller running
    (most of them, on a cell nobody runs) never loads it."""
    done, modules = _imported(tmp_path, "import cellctl.service.client")
    assert done.returncode == 0, done.stderr[-2000:]
    assert set(_heavy(modules)) == {"cellctl.service.client"}, _heavy(modules)
    # A connection refused (no server on the port) went through websockets: a LinkError.
    code = (
        "import asyncio, contextlib; from cellctl.errors import LinkError; "
        "from cellctl.service.client import RemoteCell; "
        "with contextlib.suppress(LinkError): "
        "asyncio.run(RemoteCell.connect(token='t', url='ws://127.0.0.1:1')); print('refused')"
    )
    done, modules = _imported(tmp_path, code)
    assert done.returncode == 0 and "refused" in done.stdout, done.stderr[-2000:]
    assert "websockets" in modules


def test_the_registry_reads_every_kind_without_its_driver_or_emulator(tmp_path: Path) -> None:
    code = (
        "from cellctl.kinds import registry; "
        "print(','.join(k.name + ':' + k.options.__name__ for k in registry.kinds()))"
    )
    done, modules = _imported(tmp_path, code)
    assert done.returncode == 0, done.stderr[-2000:]
    shipped = ("ibm7545", "ibm7547", "dyna2400", "iso-cnc", "ur", "kerf100")
    assert all(f"{name}:" in done.stdout for name in shipped), done.stdout
    # The shipped kinds' and the example plug-in's (tests/plugins/cellctl_saw).
    loaded = sorted(
        m
        for m in modules
        if m.startswith(("cellctl.kinds.", "cellctl_saw."))
        and m.split(".")[-1] in ("driver", "emulator")
    )
    assert not loaded, f"the registry imported {loaded}"


def test_a_kinds_fault_table_and_driver_load_when_used() -> None:
    """What the declaration defers is there when asked for: the faults of `emulate cell`'s
    help, the driver that opens a machine."""
    robot = registry.kind("ibm7545")
    mill = registry.kind("dyna2400")
    assert "drop" in robot.faults and "stall" in mill.faults
    assert dict(robot.faults) == dict(registry.kind("ibm7547").faults)
    from cellctl.kinds.ibm7545.emulator import FAULTS

    assert dict(robot.faults) == FAULTS


def test_each_declared_summary_is_the_commands_own() -> None:
    """`cellctl --help` shows a command's declared summary without importing it: each must
    be what the command's help says, cut as a group's listing cuts it."""
    ctx = click.Context(main, info_name="cellctl")
    widest = max(len(name) for name in main.list_commands(ctx))
    limit = HELP_WIDTH - 6 - widest
    for name, lazy in COMMANDS.items():
        command = lazy.load()
        assert command.help, name
        assert lazy.summary == clause_summary(command.help, limit), name
    assert set(COMMANDS) <= set(subcommands(main))


#: Each kind's command-line module: a command of one kind imports no other kind's.
KIND_CLIS = {
    "dyna2400": "cellctl.kinds.dyna2400.cli",
    "ibm7545": "cellctl.kinds.ibm7545.cli",
    "iso-cnc": "cellctl.kinds.iso_cnc.cli",
    "ur": "cellctl.kinds.ur.cli",
}


@pytest.mark.parametrize(
    ("args", "kinds"),
    [
        (["dnc", "send", "--help"], ("iso-cnc",)),
        (["emulate", "iso-cnc", "--help"], ("iso-cnc",)),
        (["mill", "download", "--help"], ("dyna2400",)),
        (["robot", "unlock", "--help"], ("ibm7545", "ur")),  # the UR's, in the IBM's group
        (["emulate", "ur", "--help"], ("ur",)),
    ],
    ids=" ".join,
)
def test_a_kinds_command_imports_no_other_kinds_command_line(
    tmp_path: Path, args: list[str], kinds: tuple[str, ...]
) -> None:
    done, modules = _imported(tmp_path, CELLCTL, *args)
    assert done.returncode == 0 and "Usage:" in done.stdout, done.stderr[-2000:]
    loaded = {kind for kind, module in KIND_CLIS.items() if module in modules}
    assert loaded == set(kinds), f"cellctl {' '.join(args)} imported the CLI of {sorted(loaded)}"


def test_each_kind_names_the_commands_it_gives() -> None:
    """``command_names`` is what lets ``cellctl dnc`` import one kind's CLI: it must be
    exactly what the kind's ``commands`` gives (a missing name would hide the command)."""
    declared = 0
    for kind in registry.kinds():
        if kind.commands is None or kind.command_names is None:
            continue
        given = {(group, command.name) for group, command in kind.commands()}
        assert set(kind.command_names) == given, kind.name
        declared += 1
    assert declared >= len(KIND_CLIS)


def test_every_kinds_command_is_in_the_help_and_the_emulate_group() -> None:
    top = subcommands(main)
    assert {"robot", "mill", "dnc"} <= set(top)
    robot, emulate = top["robot"], top["emulate"]
    assert isinstance(robot, click.Group) and isinstance(emulate, click.Group)
    assert "unlock" in subcommands(robot)
    assert {"robot", "mill", "iso-cnc", "ur", "plc", "cell"} <= set(subcommands(emulate))
