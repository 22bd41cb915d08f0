"""What the OPC UA server shows of each machine, worked out from the cell's status: pure
functions of the control API's answers (``cell.status``, ``steps.list``, ``parts.list``).

::

    steps = StepBook()
    steps.add(dispatcher_answer_of_steps_list)
    values = machine_values("cnc1", status["machines"]["cnc1"], status["alarms"], steps, held)

The enumerations mirror those of OPC 40501-1 (Machine Tools) and OPC 10000-200 (Industrial
Automation: stacklights) by name and value, in cellctl's own namespace.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from cellctl.kinds import registry

#: OPC 40501-1 MachineOperationMode.
OPERATION_MODES = ("Manual", "Automatic", "Setup", "AutoWithManualIntervention", "Service", "Other")
#: OPC 10000-200 SignalColor.
SIGNAL_COLORS = ("Off", "Red", "Green", "Blue", "Yellow", "Purple", "Cyan", "White")
#: OPC 40501-1 ChannelState.
CHANNEL_STATES = ("Active", "Interrupted", "Reset")
#: The states of OPC 40501-1's ProductionProgramStateMachine, as an enumeration.
PROGRAM_STATES = ("Initializing", "Running", "Ended", "Interrupted", "Aborted")
#: Identification per machine kind: manufacturer and model, as each kind declares them.
IDENTIFICATION: dict[str, tuple[str, str]] = {k.name: (k.maker, k.model) for k in registry.kinds()}
#: Machine states that mean it is not working as it should (the stacklight shows red).
FAULT_WORDS = ("error", "not answering", "emergency", "power failure")
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
    each machine's last step and its finished count, each part's last step."""

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

    def finished(self) -> Counter[str]:
        """Steps each machine finished."""
        return Counter(s.machine for s in self.steps.values() if s.state == "finished")

    def machine_of_parts(self, part_ids: Iterable[str]) -> Counter[str]:
        """Parts counted by the machine of their last step (where it was last worked on)."""
        last: dict[str, StepSeen] = {}
        for s in self.steps.values():
            if s.part_id not in last or s.id > last[s.part_id].id:
                last[s.part_id] = s
        return Counter(last[p].machine for p in part_ids if p in last)


def operation_mode(view: dict[str, Any]) -> int:
    """Manual while the operator drives it, Service while out of automatic service,
    Automatic otherwise."""
    if view.get("manual"):
        return OPERATION_MODES.index("Manual")
    if not view.get("in_service", True):
        return OPERATION_MODES.index("Service")
    return OPERATION_MODES.index("Automatic")


def stacklight(view: dict[str, Any], alarms: int) -> int:
    """Red: an active alarm or a fault; yellow: out of automatic service or driven by hand;
    green: in automatic service."""
    state = str(view.get("state", "")).lower()
    if alarms or any(word in state for word in FAULT_WORDS):
        return SIGNAL_COLORS.index("Red")
    if view.get("manual") or not view.get("in_service", True):
        return SIGNAL_COLORS.index("Yellow")
    return SIGNAL_COLORS.index("Green")


def program_state(view: dict[str, Any], last: StepSeen | None) -> int:
    """Running (or Initializing while the program is prepared) during a step; after it, Ended
    or Aborted (a failed or interrupted step is never resumed: its part is held)."""
    if view.get("step") or (last is not None and last.state == "started"):
        progress = view.get("progress") or {}
        preparing = progress.get("phase") in PREPARING
        return PROGRAM_STATES.index("Initializing" if preparing else "Running")
    if last is None or last.state == "finished":
        return PROGRAM_STATES.index("Ended")
    return PROGRAM_STATES.index("Aborted")


def machine_values(
    name: str,
    view: dict[str, Any],
    alarms: list[dict[str, Any]],
    last: StepSeen | None,
    counts: tuple[int, int, int],
) -> dict[str, Any]:
    """The machine's variables by path (``Monitoring/MachineState`` ...) from its status."""
    mine = sum(1 for a in alarms if a.get("machine") == name)
    progress = view.get("progress") or {}
    busy = bool(view.get("step"))
    total = progress.get("total") or 0
    good, held, scrapped = counts
    return {
        "Monitoring/MachineState": str(view.get("state", "")),
        "Monitoring/OperationMode": operation_mode(view),
        "Monitoring/StacklightColour": stacklight(view, mine),
        "Monitoring/InService": bool(view.get("in_service", True)),
        "Monitoring/OutOfServiceReason": str(view.get("out_reason", "")),
        "Monitoring/Channel/ChannelState": CHANNEL_STATES.index("Active" if busy else "Reset"),
        "Monitoring/Channel/ProgramState": program_state(view, last),
        "Monitoring/Channel/CurrentStep": str(view.get("step", "")),
        "Production/ActiveProgram/Name": last.program if last is not None else "",
        "Production/ActiveProgram/PartId": last.part_id if last is not None else "",
        "Production/ActiveProgram/State": program_state(view, last),
        "Production/ActiveProgram/Progress": (
            100.0 * float(progress.get("done", 0)) / float(total) if busy and total else 0.0
        ),
        "Production/PartCounts/Good": good,
        "Production/PartCounts/Held": held,
        "Production/PartCounts/Scrapped": scrapped,
        "Notification/ActiveAlarms": mine,
    }
