"""A client reads an API error as the typed error it was: a kind's own error (a mill's
"refused", not a class of cellctl.errors) by its family, from the JSON-RPC code the server
gives every typed error (-32000 minus its exit code), so a command exits as the README says."""

from __future__ import annotations

from cellctl.errors import DeviceError, MachineInUse, UsageError, exit_code
from cellctl.service.rpc import error_from_object


def test_a_kinds_own_device_error_exits_5_not_1() -> None:
    error = error_from_object(
        {
            "code": -32005,
            "message": "ENDLOAD refused by the host's state (state 3): a block is executing",
            "data": {"type": "MillRefused", "device_code": 2, "device_message": "refused"},
        }
    )
    assert isinstance(error, DeviceError) and exit_code(error) == 5
    assert error.code == 2


def test_each_typed_code_gives_its_family() -> None:
    busy = error_from_object({"code": -32006, "message": "cnc1 is in use", "data": {"type": "X"}})
    assert isinstance(busy, MachineInUse) and str(busy) == "cnc1 is in use"
    refused = error_from_object({"code": -32002, "message": "no such part"})
    assert isinstance(refused, UsageError) and exit_code(refused) == 2
    # A code no typed error has: a plain error, exit 1.
    other = error_from_object({"code": -32603, "message": "internal error"})
    assert type(other).__name__ == "CellctlError" and exit_code(other) == 1
