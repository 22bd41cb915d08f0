"""The ``cellctl`` command line: ``cellctl --help`` lists the commands.

A command's module is imported when the command is used (``cellctl orders`` never imports
the controller or the API server): each is named here with its summary for the help."""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
from collections.abc import Iterator
from typing import Any, NoReturn

import click

from cellctl import __version__
from cellctl.ui.common import (
    Lazy,
    LazyGroup,
    accept_cell,
    interrupted,
    kind_commands,
    sigterm_interrupts,
)

#: The exit status when the output's reader is gone (``cellctl plan | head``): what a shell
#: shows for git and coreutils there (128 + SIGPIPE, ``seq 1 100000 | head -1`` is 141), so
#: ``set -o pipefail`` reads cellctl as it reads them: the output was cut, nothing failed.
OUTPUT_GONE_EXIT = 128 + signal.SIGPIPE

#: The built-in top-level commands: name -> where it is and its summary in ``cellctl --help``
#: (tests/test_cli_startup.py checks each summary against the command's own help).
COMMANDS = {
    "alarm": Lazy(
        "cellctl.ui.orders_cli:alarm",
        "The cell's alarms: list, acknowledge, shelve, unshelve, clear",
    ),
    "audit": Lazy(
        "cellctl.ui.token_cli:audit_command", "Who did what to the cell, when, and how it ended"
    ),
    "cancel": Lazy(
        "cellctl.ui.orders_cli:cancel", "Cancel order ORDER if no part of it has started"
    ),
    "cell": Lazy("cellctl.ui.cell_cli:cell_group", "The cell as a whole: its cell.toml"),
    "console": Lazy(
        "cellctl.ui.console.command:console_command", "The operator console: the source's menus"
    ),
    "dashboard": Lazy(
        "cellctl.ui.dashboard.command:dashboard_command",
        "Open the running cell's dashboard in a browser",
    ),
    "demo": Lazy("cellctl.ui.demo:demo", "Start an emulated cell (or a factory of them)"),
    "emulate": Lazy(
        "cellctl.ui.emulate_cli:emulate", "Emulated machines that speak the real bytes: serve one"
    ),
    "estop": Lazy(
        "cellctl.ui.service_cli:estop",
        "Emergency stop: stop the robot, halt the mills, raise an alarm",
    ),
    "examples": Lazy(
        "cellctl.ui.examples_cli:examples_group",
        "List the examples that ship with cellctl, or copy them",
    ),
    "factory": Lazy("cellctl.ui.factory_cli:factory", "The system controller"),
    "kinds": Lazy(
        "cellctl.ui.kinds_cli:kinds_command",
        "List the machine kinds installed: family, maker and model",
    ),
    "machine": Lazy(
        "cellctl.ui.service_cli:machine",
        "A machine of the running cell: take it out of automatic service",
    ),
    "opcua": Lazy(
        "cellctl.ui.opcua_cli:opcua_group", "The cell's OPC UA server ([opcua] in cell.toml)"
    ),
    "orders": Lazy(
        "cellctl.ui.orders_cli:orders",
        "List orders and their state, highest priority first, then oldest",
    ),
    "part": Lazy("cellctl.ui.orders_cli:part", "The cell's parts: list them"),
    "pause": Lazy(
        "cellctl.ui.service_cli:pause", "Let the steps in flight finish and start no new one"
    ),
    "plan": Lazy(
        "cellctl.ui.plan_cli:plan_command",
        "What the cell finishes, and when: per order against its due time",
    ),
    "program": Lazy(
        "cellctl.ui.program_cli:program_group",
        "A program file of any machine kind: check it, draw its toolpath",
    ),
    "plc": Lazy(
        "cellctl.ui.plc_cli:plc", "The cell PLC over Modbus/TCP: sensors (inputs) and actuators"
    ),
    "report": Lazy("cellctl.ui.report_cli:report", "Figures from the journal: `report shift`"),
    "reports": Lazy("cellctl.ui.orders_cli:reports", "List the reports the cell posted"),
    "resume": Lazy(
        "cellctl.ui.service_cli:resume",
        "Start dispatching again after a pause or an emergency stop",
    ),
    "run": Lazy("cellctl.ui.cell_cli:run_command", "Run the cell controller in the foreground"),
    "service": Lazy(
        "cellctl.ui.service_cli:service_group",
        "The cell's controller (`cellctl run`) as a systemd service",
    ),
    "submit": Lazy("cellctl.ui.orders_cli:submit", "Post an order for QTY parts of type PART"),
    "token": Lazy(
        "cellctl.ui.token_cli:token_group", "The control API's tokens: each with a name and a role"
    ),
    "traffic": Lazy(
        "cellctl.ui.service_cli:traffic", "The last bytes on machine NAME's link, both ways"
    ),
}


def _reader_gone() -> bool:
    """True if standard output or error is a pipe (or socket) whose reader has gone: a
    broken pipe of the command's own (a link, a worker) is an error, not the end of output."""
    for fd in (1, 2):
        try:
            poller = select.poll()
            poller.register(fd, select.POLLOUT)
            events = poller.poll(0)
        except (OSError, ValueError):
            continue
        if any(event & select.POLLERR for _, event in events):
            return True
    return False


def _end_quietly() -> NoReturn:
    """End as git and coreutils do when their reader is gone: no message, status 141.
    Standard output and error go to /dev/null first: the flush at exit would fail again
    (Python's "Exception ignored ... BrokenPipeError", exit status 120)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in (1, 2):
            os.dup2(devnull, fd)
    finally:
        os.close(devnull)
    sys.exit(OUTPUT_GONE_EXIT)


@contextlib.contextmanager
def _output_gone_ends_quietly() -> Iterator[None]:
    """A command whose reader went away (``cellctl plan | head``) ends quietly with
    :data:`OUTPUT_GONE_EXIT`, not with Click's silent status 1 or a traceback."""
    try:
        yield
    except BrokenPipeError:
        if not _reader_gone():
            raise
        _end_quietly()
    except SystemExit as e:
        # Rich's answer to a broken pipe on its console: SystemExit(1), raised as it handles
        # the BrokenPipeError (its output already sent to /dev/null).
        if isinstance(e.__context__, BrokenPipeError):
            _end_quietly()
        raise


@contextlib.contextmanager
def _interrupt_ends_130() -> Iterator[None]:
    """Ctrl-C (or SIGTERM, made one by :func:`~cellctl.ui.common.sigterm_interrupts`) ends
    any command with "interrupted" and 130, as README says: not Click's "Aborted!" and 1.
    A command that ends otherwise on them (``cellctl run``: 0) handles them itself."""
    try:
        yield
    except KeyboardInterrupt:
        interrupted()
    except click.Abort as e:
        # Click's prompts answer Ctrl-C with Abort (and Ctrl-D too: that one stays Click's).
        if isinstance(e.__context__, KeyboardInterrupt):
            interrupted()
        raise


class CellctlCommand(LazyGroup):
    """``cellctl``: the lazy group of every command, which ends quietly when the reader of
    its output goes away, and with "interrupted" and 130 on Ctrl-C or SIGTERM, for every
    command (help and version included)."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        with sigterm_interrupts():
            return super().main(*args, **kwargs)

    def make_context(
        self,
        info_name: str | None,
        args: list[str],
        parent: click.Context | None = None,
        **extra: Any,
    ) -> click.Context:
        with _output_gone_ends_quietly(), _interrupt_ends_130():
            return super().make_context(info_name, args, parent, **extra)

    def invoke(self, ctx: click.Context) -> Any:
        with _output_gone_ends_quietly(), _interrupt_ends_130():
            result = super().invoke(ctx)
            sys.stdout.flush()  # what print() left in the buffer: a broken pipe shows here
            return result


@click.group(
    cls=CellctlCommand,
    lazy=COMMANDS,
    # Commands the installed kinds contribute (``cellctl robot``, ``cellctl mill`` ...).
    more=lambda name: kind_commands("", name),
    # `--cell` after a command's name too (``cellctl orders --cell mycell``).
    prepare=lambda name, command: accept_cell(command, name),
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.option(
    "--cell",
    envvar="CELLCTL_CELL",
    default="cell",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Cell directory: cell.toml, saved machine state, journal.",
)
@click.version_option(__version__, prog_name="cellctl")
def main(cell: str) -> None:
    """cellctl: drive, emulate and run a machining cell of serial-protocol machines."""
