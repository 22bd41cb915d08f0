"""Naming a fault by its cause (cellctl.cell.causes): the words every sighting shares."""

from __future__ import annotations

import pytest

from cellctl.cell.causes import (
    LINK_CLOSED,
    Blamed,
    Cause,
    blame,
    door_cause,
    link_cause,
    read_cause,
    status_cause,
)
from cellctl.errors import DeviceError, LinkClosed, LinkTimeout, SignalTimeout
from cellctl.kinds.ibm7545.records import MachineStatus


def test_a_link_fault_is_named_the_same_whoever_sees_it() -> None:
    assert link_cause("robot", "robot", LinkClosed("pty: the other end closed the link")) == Cause(
        "robot", "link", LINK_CLOSED
    )
    assert link_cause("plc", "PLC", LinkTimeout("no valid answer")) == Cause(
        "plc", "link", "PLC not answering"
    )
    assert link_cause("plc", "PLC", TimeoutError()) == Cause("plc", "link", "PLC not answering")


def test_a_machine_that_answered_is_no_link_fault() -> None:
    assert link_cause("plc", "PLC", SignalTimeout("door of CNC 1 did not close")) is None
    assert link_cause("robot", "robot", DeviceError(48, "improper startup sequence")) is None


def test_a_status_cause_is_in_the_sources_words() -> None:
    assert status_cause("robot", MachineStatus(64, 0)) == Cause("robot", "status", "power failure")
    assert status_cause("robot", MachineStatus(128, 0)).text == "servo error"


def test_blame_hands_a_link_fault_or_a_stuck_signal_to_the_machine_behind_it() -> None:
    with pytest.raises(Blamed) as caught, blame("plc", "PLC"):
        raise LinkClosed("PLC at modbus://127.0.0.1:1 closed the connection")
    assert caught.value.cause == Cause("plc", "link", LINK_CLOSED)
    with pytest.raises(Blamed) as caught, blame("plc", "PLC"):
        raise SignalTimeout("door of CNC 2 did not leave its closed position within 0.25 s")
    assert caught.value.cause == Cause(
        "plc", "interlock", "door of CNC 2 did not leave its closed position within 0.25 s"
    )
    assert "door of CNC 2" in str(caught.value)


def test_blame_lets_other_failures_through_unchanged() -> None:
    error = DeviceError(16, "record format error")
    with pytest.raises(DeviceError) as caught, blame("plc", "PLC"):
        raise error
    assert caught.value is error
    inner = Blamed(Cause("robot", "status", "servo error"), error)
    with pytest.raises(Blamed) as again, blame("plc", "PLC"):
        raise inner
    assert again.value is inner


def test_a_failed_look_names_the_link_or_says_what_failed() -> None:
    assert read_cause("plc", "PLC", TimeoutError()) == Cause("plc", "link", "PLC not answering")
    error = DeviceError(2, "Illegal Data Address")
    assert read_cause("plc", "PLC", error) == Cause("plc", "link", f"PLC failed: {error}")


def test_a_door_short_of_its_end_position_is_named_as_an_interlock_wait_names_it() -> None:
    half_open = {"door_open_1": True, "door_closed_1": False, "door_open_2": False}
    assert door_cause(half_open, [1, 2], True, 120) == Cause(
        "plc", "interlock", "door of CNC 2 did not open within 120 s"
    )
    assert door_cause(half_open, [1], True, 120) is None
    assert door_cause({"door_closed_1": False}, [1], False, 2.5) == Cause(
        "plc", "interlock", "door of CNC 1 did not close within 2.5 s"
    )
    assert door_cause(half_open, [], True, 120) is None
