"""The ``cellctl`` command line: ``cellctl --help`` lists the commands."""

from __future__ import annotations

import click

from cellctl import __version__
from cellctl.kinds import registry
from cellctl.ui.cell_cli import cell_group, emulate_cell, run_command
from cellctl.ui.common import CellctlGroup, accept_cell_anywhere, summarize_commands
from cellctl.ui.console import console_command
from cellctl.ui.dashboard import dashboard_command
from cellctl.ui.demo import demo
from cellctl.ui.emulate_cli import emulate
from cellctl.ui.factory_cli import emulate_factory, factory
from cellctl.ui.factory_plan_cli import factory_plan
from cellctl.ui.kinds_cli import kinds_command
from cellctl.ui.opcua_cli import opcua_group
from cellctl.ui.orders_cli import alarm, cancel, orders, part, reports, submit
from cellctl.ui.plan_cli import plan_command
from cellctl.ui.plc_cli import plc
from cellctl.ui.report_cli import report
from cellctl.ui.service_cli import estop, machine, pause, resume, service_group, traffic
from cellctl.ui.token_cli import audit_command, token_group


@click.group(
    cls=CellctlGroup,
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


main.add_command(emulate)
main.add_command(kinds_command)
# Commands the installed kinds contribute (``cellctl robot``, ``cellctl emulate mill`` ...).
_groups: dict[str, click.Group] = {"": main, "emulate": emulate}
for _kind in registry.kinds():
    try:
        _contributed = _kind.commands() if _kind.commands is not None else []
    except Exception as _e:  # a plug-in's CLI that fails to load: skipped, by name
        registry.log.warning("machine kind %s: its commands skipped: %s", _kind.name, _e)
        continue
    for _group, _command in _contributed:
        # A group another kind contributed (``robot``) takes this kind's commands too.
        _target = _groups.get(_group) or main.commands.get(_group)
        if not isinstance(_target, click.Group):
            registry.log.warning("machine kind %s: no command group %r", _kind.name, _group)
            continue
        _target.add_command(_command)
main.add_command(submit)
main.add_command(orders)
main.add_command(cancel)
main.add_command(reports)
main.add_command(report)
main.add_command(plan_command)
main.add_command(alarm)
main.add_command(part)
main.add_command(plc)
main.add_command(cell_group)
main.add_command(run_command)
main.add_command(demo)
main.add_command(console_command)
main.add_command(dashboard_command)
main.add_command(opcua_group)
main.add_command(token_group)
main.add_command(audit_command)
main.add_command(factory)
factory.add_command(factory_plan)
emulate.add_command(emulate_cell)
emulate.add_command(emulate_factory)
for command in (pause, resume, estop, machine, traffic, service_group):
    main.add_command(command)
# Last, once every command is in: `--cell` after a command's name too, and summaries that
# read whole in a group's help at 80 columns.
accept_cell_anywhere(main)
summarize_commands(main)
