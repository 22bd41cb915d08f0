"""What the control API's client and server agree on, and nothing heavier: the socket's file
name, JSON-RPC's codes, who calls, and the typed error an error object describes. A command
that only asks a running controller imports this, not the server or the cell's access::

    error = error_from_object({"code": -32002, "message": "...", "data": {"type": "UsageError"}})
    raise error                                  # UsageError, as the server raised it
"""

from __future__ import annotations

import getpass
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

from cellctl import errors as errors_module
from cellctl.errors import CellctlError, ProtocolError, UsageError

#: The API's Unix socket, in the cell's directory.
SOCKET_FILE = "api.sock"

#: JSON-RPC 2.0's own error codes.
PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603
#: A typed cellctl error: -32000 minus the CLI's exit code for it (UsageError -32002 ...).
APP_ERROR_BASE = -32000
#: A call refused for the server's load, not for what it asks: too many calls in flight on
#: one connection or for one token, or the server stopping. Send it again once an answer
#: came (``data.reason`` says which: ``connection``, ``token`` or ``stopping``).
SERVER_BUSY = -32010


def login_name() -> str:
    """The user running this process, as the audit trail names them (``local:NAME``,
    ``factory:NAME``); "unknown" when the system cannot say."""
    try:
        return getpass.getuser() or "unknown"
    except (KeyError, OSError):
        return "unknown"


@dataclass(frozen=True)
class Caller:
    """Who calls: ``who`` as the audit trail names it (``token:ann``, ``opcua:bob``) and
    the role their token or user holds."""

    who: str
    role: str


#: Who makes the call being run (the dispatcher sets it): a method's handler names them where
#: the journal keeps who did it (an alarm acknowledged, shelved, cleared).
CALLER: ContextVar[Caller | None] = ContextVar("cellctl_caller", default=None)


def caller_name(default: str = "operator") -> str:
    """Who makes the call being run (``token:olga``, ``local:ann``), ``default`` outside one."""
    caller = CALLER.get()
    return caller.who if caller is not None else default


def caller_label() -> str:
    """Who makes the call being run and their role, as the journal keeps who paused or
    resumed the cell (``token:eve (engineer)``); "" outside a call."""
    caller = CALLER.get()
    return "" if caller is None else f"{caller.who} ({caller.role})"


def error_from_object(obj: Any) -> CellctlError:
    """The typed error a JSON-RPC error object describes (for clients)."""
    if not isinstance(obj, dict):
        return errors_module.ProtocolError(f"the API answered a malformed error: {obj!r}")
    message = str(obj.get("message", "error"))
    found = obj.get("data")
    data: dict[str, Any] = found if isinstance(found, dict) else {}
    kind = getattr(errors_module, str(data.get("type", "")), None)
    code = obj.get("code")
    if not (isinstance(kind, type) and issubclass(kind, CellctlError)) and isinstance(code, int):
        # A kind's own error (a mill's "refused", say): its family by the code's exit code.
        by_exit = {exit: k for k, exit in errors_module.EXIT_CODES.items()}
        kind = by_exit.get(APP_ERROR_BASE - code)
    if kind is errors_module.DeviceError:
        return errors_module.DeviceError(
            int(data.get("device_code", 0)),
            str(data.get("device_message", message)),
            detail=str(data.get("detail", "")),
        )
    if isinstance(kind, type) and issubclass(kind, ProtocolError):
        # The message already shows the raw bytes: keep them as bytes, not twice in the text.
        return kind(message.split(" (raw: ")[0], bytes.fromhex(str(data.get("raw", ""))))
    if isinstance(kind, type) and issubclass(kind, CellctlError):
        return kind(message)
    if obj.get("code") in (METHOD_NOT_FOUND, INVALID_PARAMS, INVALID_REQUEST):
        return UsageError(message)
    return CellctlError(message)
