"""What the OPC UA server shows of each machine, worked out from the cell's status: pure
functions of the control API's answers (``cell.status``, ``steps.list``, ``parts.list``).

::

    steps = StepBook()
    steps.add(dispatcher_answer_of_steps_list)
    status = access.status()          # the cell's status model, read by field
    values = machine_values("cnc1", status.machines["cnc1"], status.alarms, last, counts)

The enumerations mirror those of OPC 40501-1 (Machine Tools) and OPC 10000-200 (Industrial
Automation: stacklights) by name and value, in cellctl's own namespace.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from cellctl.kinds import Condition, registry
from cellctl.service.status import AlarmInfo, MachineStatus, StepInfo

#: OPC 40501-1 MachineOperationMode.
OPERATION_MODES = ("Manual", "Automatic", "Setup", "AutoWithManualIntervention", "Service", "Other")
#: OPC 10000-200 SignalColor.
SIGNAL_COLORS = ("Off", "Red", "Green", "Blue", "Yellow", "Purple", "Cyan", "White")
#: cellctl's machine condition (:class:`~cellctl.kinds.Condition`), by name.
MACHINE_CONDITIONS = ("Offline", "NotReady", "Idle", "Busy", "Alarm", "OutOfService")
#: OPC 40501-1 ChannelState.
CHANNEL_STATES = ("Active", "Interrupted", "Reset")
#: The states of OPC 40501-1's ProductionProgramStateMachine, as an enumeration.
PROGRAM_STATES = ("Initializing", "Running", "Ended", "Interrupted", "Aborted")
#: Identification per machine kind: manufacturer and model, as each kind declares them.
IDENTIFICATION: dict[str, tuple[str, str]] = {k.name: (k.maker, k.model) for k in registry.kinds()}
#: Progress phases before the program runs (the program is being prepared).
PREPARING = ("waiting", "downloading")


@dataclass(frozen=True)
class StepSeen:
    """One journal step as the server keeps it."""

    id: int
    part_id: str
    machine: str
    program: str
    state: str
    started: float


class StepBook:
    """The journal's steps, read once whole and then from the earliest one still in flight:
    each machine's last step, the parts it worked on, each part's last step."""

    def __init__(self) -> None:
        self.steps: dict[int, StepSeen] = {}

    def add(self, rows: Iterable[dict[str, Any]]) -> None:
        """Steps from ``steps.list`` (or the journal), new or with a new state."""
        for r in rows:
            step = StepSeen(
                int(r["id"]),
                str(r["part_id"]),
                str(r["machine"]),
                str(r["program"]),
                str(r["state"]),
                float(r["started"]),
            )
            self.steps[step.id] = step

    def since(self) -> float | None:
        """Where the next ``steps.list`` starts: the earliest step in flight, else the last."""
        if not self.steps:
            return None
        open_steps = [s.started for s in self.steps.values() if s.state == "started"]
        return min(open_steps) if open_steps else max(s.started for s in self.steps.values())

    def last_of_machine(self, machine: str) -> StepSeen | None:
        found = [s for s in self.steps.values() if s.machine == machine]
        return max(found, key=lambda s: s.id) if found else None

    def parts_through(self, part_ids: Iterable[str]) -> Counter[str]:
        """Of ``part_ids``, how many each machine worked on (a step of the part there, once a
        part): the parts made good on it, given the parts done (the journal's, as the shift
        report counts good parts), a step redone or released as done counting once."""
        wanted = set(part_ids)
        worked = {(s.machine, s.part_id) for s in self.steps.values() if s.part_id in wanted}
        return Counter(machine for machine, _ in worked)

    def machine_of_parts(self, part_ids: Iterable[str]) -> Counter[str]:
        """Parts counted by the machine of their last step (where it was last worked on)."""
        last: dict[str, StepSeen] = {}
        for s in self.steps.values():
            if s.part_id not in last or s.id > last[s.part_id].id:
                last[s.part_id] = s
        return Counter(last[p].machine for p in part_ids if p in last)


def operation_mode(view: MachineStatus) -> int:
    """Manual while the operator drives it, Service while out of automatic service,
    Automatic otherwise."""
    if view.manual:
        return OPERATION_MODES.index("Manual")
    if not view.in_service:
        return OPERATION_MODES.index("Service")
    return OPERATION_MODES.index("Automatic")


def stacklight(view: MachineStatus, alarms: int) -> int:
    """Red: an active alarm, or the machine in alarm or offline; yellow: out of automatic
    service, driven by hand, or not ready; green: in automatic service, idle or busy."""
    if alarms or view.condition in (Condition.ALARM, Condition.OFFLINE):
        return SIGNAL_COLORS.index("Red")
    if view.manual or view.condition in (Condition.OUT_OF_SERVICE, Condition.NOT_READY):
        return SIGNAL_COLORS.index("Yellow")
    return SIGNAL_COLORS.index("Green")


def condition_value(condition: Condition) -> int:
    """The machine's condition as the ``MachineCondition`` enumeration's value."""
    return list(Condition).index(condition)


def program_state(view: MachineStatus, last: StepSeen | None) -> int:
    """Running (or Initializing while the program is prepared) during a step; after it, Ended
    or Aborted (a failed or interrupted step is never resumed: its part is held)."""
    if view.step is not None or (last is not None and last.state == "started"):
        preparing = view.progress is not None and view.progress.phase in PREPARING
        return PROGRAM_STATES.index("Initializing" if preparing else "Running")
    if last is None or last.state == "finished":
        return PROGRAM_STATES.index("Ended")
    return PROGRAM_STATES.index("Aborted")


def machine_values(
    name: str,
    view: MachineStatus,
    alarms: list[AlarmInfo],
    last: StepSeen | None,
    counts: tuple[int, int, int],
) -> dict[str, Any]:
    """The machine's variables by path (``Monitoring/MachineState`` ...) from its status."""
    mine = sum(1 for a in alarms if a.machine == name)
    busy = view.step is not None
    step = view.step
    good, held, scrapped = counts
    return {
        "Monitoring/MachineState": view.state,
        "Monitoring/Condition": condition_value(view.condition),
        "Monitoring/OperationMode": operation_mode(view),
        "Monitoring/StacklightColour": stacklight(view, mine),
        "Monitoring/InService": view.in_service,
        "Monitoring/OutOfServiceReason": view.out_reason,
        "Monitoring/Channel/ChannelState": CHANNEL_STATES.index("Active" if busy else "Reset"),
        "Monitoring/Channel/ProgramState": program_state(view, last),
        "Monitoring/Channel/CurrentStep": _step_text(step),
        "Production/ActiveProgram/Name": last.program if last is not None else "",
        "Production/ActiveProgram/PartId": last.part_id if last is not None else "",
        "Production/ActiveProgram/State": program_state(view, last),
        "Production/ActiveProgram/Progress": (
            100.0 * view.progress.fraction if busy and view.progress is not None else 0.0
        ),
        "Production/PartCounts/Good": good,
        "Production/PartCounts/Held": held,
        "Production/PartCounts/Scrapped": scrapped,
        "Notification/ActiveAlarms": mine,
    }


def _step_text(step: StepInfo | None) -> str:
    """The step in flight for a reader: what, program, part (made from the fields)."""
    if step is None:
        return ""
    return " ".join(x for x in (step.what.value, step.program, step.part_id) if x)
