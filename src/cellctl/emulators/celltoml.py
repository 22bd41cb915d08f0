"""An emulated cell's cell.toml and the real cell's: the deadlines the emulation scales (with
a note of the real value), and the way back::

    real_cell_toml(emulated_text)   # the real cell's cell.toml: scale, options, notes undone
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import replace

from cellctl.link.settings import LineSettings

#: ``[cell]`` deadlines for the machines' work, scaled in the emulated cell's cell.toml.
CELL_DEADLINES = ("transfer_timeout", "interlock_timeout", "pallet_timeout")
#: The note after a scaled deadline: the real cell's value, which :func:`real_cell_toml`
#: reads back (the scaled one is floored at ``MIN_DEADLINE_S``: it cannot be undone).
DEADLINE_NOTE = "  # s (the real cell's {real:g} s, scaled)"
_DEADLINE_NOTE = re.compile(r"#\s*s \(the real cell's ([0-9.eE+-]+) s, scaled\)")


def is_options(section: str) -> bool:
    """True for a machine's ``[machines.NAME.options]`` table."""
    return section.startswith("machines.") and section.endswith(".options")


def real_cell_toml(text: str) -> str:
    """The real cell's cell.toml from an emulated cell's (``text``): what the emulation
    wrote undone -- the ``[cell] time_scale`` gone, each deadline it scaled back at the real
    cell's value (from its note, :data:`DEADLINE_NOTE`; else the value times the scale), and
    the machines' ``[options]`` tables gone (the emulated machines' speed and ports). Links
    stay as written. A file without ``[cell] time_scale`` is a real cell's: returned as is.
    """
    raw = tomllib.loads(text)
    cell = raw.get("cell", {})
    if "time_scale" not in cell:
        return text
    scale = float(cell["time_scale"])
    out: list[str] = []
    section = ""
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("# Emulated cell (time scale") and not section:
            continue
        if stripped.startswith("["):
            section = stripped.strip("[] ")
        if is_options(section):
            continue
        key = stripped.split("=", 1)[0].strip() if "=" in stripped else ""
        if section == "cell" and key == "time_scale":
            continue
        if section == "cell" and key in CELL_DEADLINES:
            note = _DEADLINE_NOTE.search(line)
            real = float(note.group(1)) if note else float(cell[key]) * scale
            line = f"{key} = {real:g}"
        elif section.startswith("machines.") and key == "line":
            # Characters as much faster as the machines: the real line's rate, back.
            settings = LineSettings.parse(raw["machines"][section.split(".", 1)[1]]["line"])
            line = f'line = "{replace(settings, baudrate=round(settings.baudrate / scale))}"'
        out.append(line)
    while out and not out[-1].strip():
        out.pop()  # the blank line before the options tables that went
    while out and not out[0].strip():
        out.pop(0)  # the blank line after the emulation's header
    return "\n".join(out) + "\n"


__all__ = ["CELL_DEADLINES", "DEADLINE_NOTE", "is_options", "real_cell_toml"]
