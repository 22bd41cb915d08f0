"""Every machine's condition: the kinds' states mapped once, and the controller's view on top."""

from __future__ import annotations

from cellctl.cell.model import MachineView
from cellctl.errors import DeviceError, LinkTimeout
from cellctl.kinds import Condition, LastError
from cellctl.kinds.dyna2400.driver import MillStatus
from cellctl.kinds.ibm7545.driver import robot_condition


def test_robot_states_map_to_conditions() -> None:
    assert [robot_condition(s) for s in (0, 1, 2)] == [
        Condition.NOT_READY,
        Condition.IDLE,
        Condition.BUSY,
    ]
    assert robot_condition(1, ok=False) is Condition.ALARM


def test_mill_states_map_to_conditions() -> None:
    shown = {s: MillStatus(s, ready=True).kind_condition for s in range(5)}
    assert shown == {
        0: Condition.NOT_READY,
        1: Condition.NOT_READY,
        2: Condition.IDLE,
        3: Condition.BUSY,
        4: Condition.BUSY,
    }
    # Initialized, but its operator has not set the reference zero (CTS low): not ready.
    assert MillStatus(2, ready=False).kind_condition is Condition.NOT_READY


def test_a_view_shows_service_steps_and_errors() -> None:
    view = MachineView("cnc1", "mill")
    assert view.condition is Condition.OFFLINE
    view.show("Initialized", Condition.IDLE)
    view.step = "rough (p1)"
    assert view.condition is Condition.BUSY
    view.in_service = False
    assert view.condition is Condition.OUT_OF_SERVICE
    view.in_service = True
    view.step = ""
    refused = DeviceError(2, "Machine executing program")
    view.show("error", Condition.ALARM, LastError.of(refused))
    assert view.error == LastError(str(refused), 2)
    view.show("still", Condition.ALARM)  # a later look without an error keeps the last one
    assert view.error is not None and view.error.code == 2
    view.show("not answering", Condition.OFFLINE, LastError.of(LinkTimeout("no answer")))
    assert view.error == LastError("no answer", None)
    view.show("Initialized", Condition.IDLE)  # seen well again
    assert view.error is None
