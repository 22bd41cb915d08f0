"""The CLI as a script and a new user meet it: orders need a cell, ``--cell`` goes before or
after the command, listings print JSON and whole ids (a real ``cellctl`` process, stdout a
pipe, COLUMNS=80: what a pipe gets depends on the process), and every acting API method has
its command. What is parsing and refusals runs the real command line in this process."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner, Result

from cellctl.kinds import registry
from cellctl.mailbox import open_mailbox
from cellctl.service.functions import functions, kind_menu
from cellctl.service.methods import METHODS
from cellctl.ui.cli import main
from cellctl.ui.common import clause_summary, subcommands
from cellctl.ui.dashboard.routes import DASHBOARD_METHODS

ROOT = Path(__file__).resolve().parent.parent
RUN_CLI = "import sys; from cellctl.ui.cli import main; sys.exit(main())"

CELL_TOML = """
[parts.wax-robot-base-with-a-long-name]
route = ["cnc1"]
"""

#: Each acting method of the control API and the CLI command that does it.
CLI_OF_METHOD = {
    "cell.pause": "pause",
    "cell.resume": "resume",
    "cell.estop": "estop",
    "orders.submit": "submit",
    "orders.cancel": "cancel",
    "alarms.clear": "alarm clear",
    "alarms.ack": "alarm ack",
    "alarms.shelve": "alarm shelve",
    "alarms.unshelve": "alarm unshelve",
    "parts.release": "part release",
    "parts.scrap": "part scrap",
    "machines.out_of_service": "machine out",
    "machines.return_to_service": "machine in",
    "robot.io_set": "robot io set",
}


def cellctl(
    cwd: Path, *args: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` in a process of its own, stdout a pipe, an 80-column terminal."""
    environment = {k: v for k, v in os.environ.items() if k != "CELLCTL_CELL"}
    return subprocess.run(
        [sys.executable, "-c", RUN_CLI, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
        env={**environment, "COLUMNS": "80", **(env or {})},
    )


def cli(*args: str) -> Result:
    """``cellctl ARGS`` on the real command line in this process (CELLCTL_CELL unset)."""
    return CliRunner().invoke(main, list(args), env={"CELLCTL_CELL": None})


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell-with-a-rather-long-directory-name"
    directory.mkdir()
    (directory / "cell.toml").write_text(CELL_TOML)
    return directory


def test_submit_without_a_cell_is_refused_and_says_where_it_looked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the default cell is ./cell
    done = cli("submit", "wax-robot-base")
    assert done.exit_code == 2, done.stdout + done.stderr
    assert "posted" not in done.stdout
    assert str(tmp_path / "cell") in done.stderr.replace("\n", "")
    assert "--cell DIR" in done.stderr and "CELLCTL_CELL" in done.stderr
    assert not (tmp_path / "cell").exists()


def test_cell_goes_before_or_after_the_command(cell: Path, tmp_path: Path) -> None:
    posted = cli("submit", "wax-robot-base-with-a-long-name", "--id", "A1", "--cell", str(cell))
    assert posted.exit_code == 0, posted.stderr
    before = cli("--cell", str(cell), "orders", "--json")
    after = cli("orders", "--json", "--cell", str(cell))
    assert before.exit_code == after.exit_code == 0, before.stderr + after.stderr
    assert json.loads(before.stdout) == json.loads(after.stdout)
    assert [o["id"] for o in json.loads(after.stdout)] == ["A1"]
    both = cli("--cell", str(cell), "orders", "--cell", str(tmp_path / "other"))
    assert both.exit_code == 2 and "--cell given twice" in both.stderr


def test_cancel_an_order_that_has_not_started(cell: Path) -> None:
    with open_mailbox(cell) as mailbox:
        mailbox.post_order("wax-robot-base-with-a-long-name", 1, order_id="C1")
    done = cli("--cell", str(cell), "cancel", "C1")
    assert done.exit_code == 0, done.stderr
    assert "order C1 cancelled" in done.stdout
    with open_mailbox(cell) as mailbox:
        assert mailbox.get_order("C1").state == "cancelled"
    again = cli("--cell", str(cell), "cancel", "C1")
    assert again.exit_code == 2 and "only an order that has not started" in again.stderr


def test_piped_listings_keep_whole_ids_on_one_line(cell: Path) -> None:
    long_id = "c9d6003a5e7b4f2e9d1c8b7a6f5e4d3c-a-very-long-order-id"
    with open_mailbox(cell) as mailbox:
        mailbox.post_order("wax-robot-base-with-a-long-name", 2, order_id=long_id)
        mailbox.post_report(
            "order-accepted", f"order {long_id} accepted " + "y" * 80, order_id=long_id
        )
    orders = cellctl(cell.parent, "--cell", str(cell), "orders")
    assert orders.returncode == 0, orders.stderr
    row = [line for line in orders.stdout.splitlines() if long_id in line]
    assert len(row) == 1 and "posted" in row[0] and "…" not in orders.stdout, orders.stdout
    reports = cellctl(cell.parent, "--cell", str(cell), "reports")
    assert any(long_id in line and "y" * 80 in line for line in reports.stdout.splitlines()), (
        reports.stdout
    )
    as_json = json.loads(cellctl(cell.parent, "--cell", str(cell), "reports", "--json").stdout)
    assert as_json[0]["order_id"] == long_id and as_json[0]["kind"] == "order-accepted"


@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
@pytest.mark.parametrize(
    "args",
    [
        ["--help"],  # Click's help, before any command runs
        ["orders"],  # a Rich table
        ["orders", "--json"],  # click.echo
        ["plan", "--dir", "{example}", "--add", "wax-robot-base:1", "--shift", "30m"],
    ],
    ids=["help", "table", "json", "plan"],
)
def test_a_reader_gone_ends_the_command_quietly_as_coreutils_do(
    cell: Path, args: list[str]
) -> None:
    """``cellctl ... | head``: the reader of the output goes before the command writes. The
    command ends with no message and no traceback, with the status a shell shows for git or
    ``seq 1 100000 | head -1`` (141: 128 + SIGPIPE), not Click's silent 1."""
    from cellctl.emulators.cell import EXAMPLE_CELL

    with open_mailbox(cell) as mailbox:
        mailbox.post_order("wax-robot-base-with-a-long-name", 2, order_id="A1")
    argv = [a.replace("{example}", str(EXAMPLE_CELL)) for a in args]
    environment = {k: v for k, v in os.environ.items() if k != "CELLCTL_CELL"}
    child = subprocess.Popen(
        [sys.executable, "-c", RUN_CLI, "--cell", str(cell), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=environment,
    )
    assert child.stdout is not None and child.stderr is not None
    child.stdout.close()  # the reader is gone: every write to the pipe fails (EPIPE)
    said = child.stderr.read().decode()
    assert (child.wait(timeout=280), said) == (141, "")


def _commands(group: click.Group, prefix: str = "") -> dict[str, click.Command]:
    found: dict[str, click.Command] = {}
    for name, command in subcommands(group).items():
        path = f"{prefix}{name}"
        found[path] = command
        if isinstance(command, click.Group):
            found.update(_commands(command, path + " "))
    return found


def test_every_acting_api_method_has_a_cli_command() -> None:
    commands = _commands(main)
    # A machine function is `cellctl FAMILY NAME` for the kinds cellctl ships (a plug-in's
    # functions are its own CLI's business).
    shipped = {
        f"{fn.family}.{fn.name}"
        for k in registry.kinds()
        if k.origin is not None and k.origin.distribution == "cellctl"
        for fn in kind_menu(k.name)
    }
    table = {**{m: m.replace(".", " ") for m in shipped}, **CLI_OF_METHOD}
    missing = [
        m.name
        for m in METHODS.values()
        if m.acts
        and (m.name in shipped or ("." in m.name and m.name.split(".")[0] not in ("robot", "mill")))
        and table.get(m.name) not in commands
    ]
    assert not missing, f"API actions with no CLI command: {missing}"
    unknown = [m for m in CLI_OF_METHOD if m not in METHODS]
    assert not unknown, f"CLI commands for methods the API does not have: {unknown}"


def _walk(command: click.Command, path: str) -> list[tuple[str, click.Command]]:
    found = [(path, command)]
    if isinstance(command, click.Group):
        for name, sub in subcommands(command).items():
            found += _walk(sub, f"{path} {name}")
    return found


def test_every_option_has_help() -> None:
    bare = [
        f"{path} {param.opts[0]}"
        for path, command in _walk(main, "cellctl")
        for param in command.get_params(click.Context(command, info_name=path))
        if isinstance(param, click.Option)
        and not param.hidden
        and not param.help
        and param.name not in ("help", "version")
    ]
    assert not bare, "options without a description:\n" + "\n".join(bare)


def test_no_summary_is_cut_mid_sentence() -> None:
    """Every group's help at 80 columns, as a user sees it: no summary ends in "..."."""
    cut = []
    for path, command in _walk(main, "cellctl"):
        if not isinstance(command, click.Group):
            continue
        # In-process: click sizes help by $COLUMNS as the installed command does.
        shown = (
            CliRunner().invoke(main, [*path.split()[1:], "--help"], env={"COLUMNS": "80"}).output
        )
        listing = shown.split("Commands:", 1)[-1] if "Commands:" in shown else ""
        cut += [f"{path}: {line.strip()}" for line in listing.splitlines() if line.endswith("...")]
    assert not cut, "summaries cut mid-sentence in group help:\n" + "\n".join(cut)


def test_a_summary_keeps_whole_clauses_outside_parentheses() -> None:
    long = "Draw PROGRAM's toolpath (XY view, Z profile, block boundaries) to an SVG or PNG."
    assert clause_summary(long, 60) == "Draw PROGRAM's toolpath"
    assert clause_summary(
        "Emergency stop: stop the robot, halt the mills, raise an alarm.", 50
    ) == ("Emergency stop: stop the robot, halt the mills")
    assert clause_summary("Short and whole.", 60) == "Short and whole"


# -- the dashboard's column of the parity table --------------------------------------------------

DASHBOARD_STATIC = ROOT / "src" / "cellctl" / "ui" / "dashboard" / "static"
#: Where a dashboard control declares its API method, once per control: data-method="..." in
#: the markup, "data-method": "..." in a script that builds one (a selector such as
#: [data-method="cell.pause"] only finds a control, it declares none).
DECLARED = {
    ".html": re.compile(r'\sdata-method="([^"]*)"'),
    ".js": re.compile(r'"data-method":\s*"([^"]*)"'),
}


def dashboard_actions() -> dict[str, list[str]]:
    """The API methods the dashboard's controls call, each with the files declaring it."""
    found: dict[str, list[str]] = {}
    for path in sorted(DASHBOARD_STATIC.iterdir()):
        pattern = DECLARED.get(path.suffix)
        if pattern is not None:
            for method in pattern.findall(path.read_text(encoding="utf-8")):
                found.setdefault(method, []).append(path.name)
    return found


def test_every_acting_api_method_has_a_dashboard_control() -> None:
    offered = dashboard_actions()
    # By-hand machine functions (an engineer's, on a machine out of automatic service, with
    # the machine's own menu and parameters) are the console's and the CLI's; every other
    # action of the API is the dashboard's too.
    by_hand = {f"{fn.family}.{fn.name}" for fn in functions()}
    wanted = {m.name for m in METHODS.values() if m.acts and m.name not in by_hand}
    missing = sorted(wanted - set(offered))
    assert not missing, f"API actions with no dashboard control: {missing}"
    unknown = {m: files for m, files in offered.items() if m not in METHODS}
    assert not unknown, f"dashboard controls for methods the API does not have: {unknown}"
    reads = sorted(m for m in offered if m in METHODS and not METHODS[m].acts)
    assert not reads, f"dashboard controls for methods that change nothing: {reads}"
    # ... and the page may call each of them (POST /dashboard/call refuses any other).
    refused = sorted(set(offered) - DASHBOARD_METHODS)
    assert not refused, f"dashboard controls that /dashboard/call refuses: {refused}"


def test_every_acting_api_method_is_in_the_console() -> None:
    """The console column of the parity test: the console's declared actions against the
    API's method table, and each declared place against the menus the console shows."""
    from cellctl.ui.console.actions import console_actions
    from cellctl.ui.console.app import SERVICE_LABELS
    from cellctl.ui.console.cellmenu import CellActions

    declared = console_actions()
    missing = [m.name for m in METHODS.values() if m.acts and m.name not in declared]
    assert not missing, f"API actions the console lacks: {missing}"
    unknown = [m for m in declared if m not in METHODS]
    assert not unknown, f"console actions the API does not have: {unknown}"

    class Host:  # what the CELL menu reads of a console attached to a controller
        def __init__(self, paused: bool) -> None:
            self.directory = Path(".")
            self.mode = "attached"
            self.snapshot = {"cell": {"paused": paused}}

    labels = {
        e.label
        for paused in (False, True)
        for e in CellActions(Host(paused)).entries()  # type: ignore[arg-type]
    }
    labels |= set(SERVICE_LABELS.values())  # a machine menu's s, by its state
    # A machine function's place is its kind's menu, the list the machine menus are built of.
    machine = {(fn.family.upper(), fn.label) for k in registry.kinds() for fn in kind_menu(k.name)}
    misplaced = [
        m
        for m, place in declared.items()
        if not (place[0] in ("CELL", "MACHINE") and place[1] in labels) and place not in machine
    ]
    assert not misplaced, f"console actions declared where no menu entry is: {misplaced}"
