"""How a machine function's outcome reads in the console's result pane: the source's
message first, then its details, each fact once::

    app.say(result_lines("robot", fn, result), "green")
"""

from __future__ import annotations

from typing import Any

from cellctl.service.functions import MachineFunction


def result_lines(name: str, fn: MachineFunction, result: dict[str, Any]) -> list[str]:
    """A function's outcome as the console shows it: the source's message, then details."""
    message = str(result.get("message", ""))
    lines = [f"{name}: {fn.label}: {message}"]
    # A detail that says the message again (``robot state: 1 (...)`` under ``robot state 1
    # (...)``) is left out: each fact once.
    said = {_plain(message), _plain(f"{name}: {message}")}
    details = [str(x) for x in result.get("lines", []) if _plain(str(x)) not in said]
    partitions = result.get("partitions")
    if isinstance(partitions, dict):
        details = [d for d in details if not d.startswith("partition ")]
        details.append(
            "partitions: "
            + "  ".join(f"{n} {f'Full ({p})' if p else 'Empty'}" for n, p in partitions.items())
        )
    if "text" in result and fn.name == "upload":
        details.append(str(result["text"])[:200])
    return lines + details + [str(x) for x in result.get("after", [])]


def _plain(text: str) -> str:
    """A line without its punctuation and case, to find one that says another again."""
    return " ".join("".join(c for c in text.lower() if c.isalnum() or c.isspace()).split())
