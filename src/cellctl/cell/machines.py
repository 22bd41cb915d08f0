"""One place builds a machine's driver from its config: the controller and the standalone
service both open machines here, through the machine's kind (its options checked first)::

    robot = await open_machine(m.kind, m.name, m.link, m.line, m.options,
                               store=StateStore(cell_dir), trace=traffic)
"""

from __future__ import annotations

from typing import Any

from cellctl.clock import Clock
from cellctl.drivers.state import StateStore
from cellctl.errors import LinkError, MachineInUse
from cellctl.kinds import registry
from cellctl.kinds.families import StartOutput
from cellctl.kinds.kind import DriverSpec
from cellctl.link import LineSettings, TrafficLog


async def open_machine(
    kind: str,
    name: str,
    url: str,
    settings: LineSettings,
    options: dict[str, Any],
    *,
    store: StateStore | None,
    trace: TrafficLog | None,
    start_output: StartOutput | None = None,
    clock: Clock | None = None,
) -> Any:
    """Open machine ``name`` of ``kind`` on ``url``: its options are checked against the
    kind's model (UsageError naming the field) before anything is opened. ``clock``: what
    its driver times its waits on (None: the running loop's). A link that cannot be opened
    raises its error naming the machine ("cnc2: cannot connect to rfc2217://...")."""
    machine_kind = registry.kind(kind)
    checked = machine_kind.checked_options(options)
    spec = DriverSpec(url, name, settings, checked, store, trace, start_output, clock)
    try:
        return await machine_kind.open(spec)
    except (LinkError, MachineInUse) as e:
        text = str(e)
        if e.args and name != url and not text.startswith(f"{name}:"):
            # The same error (its type and attributes kept), its words naming the machine
            # (not one named by its URL, given with --link): a cell of several machines
            # says which one it could not reach.
            e.args = (f"{name}: {text}", *e.args[1:])
        raise
