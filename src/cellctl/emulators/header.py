"""The mark of a cell.toml ``cellctl emulate cell`` wrote: its first line.

A cell.toml without it is a cell's own, which an emulation never overwrites
(:func:`cellctl.emulators.cell.check_cell_dir`); with it, its time scale is known
(``cellctl run``'s live view says it). No imports beyond the standard library: the run
command reads it without loading the emulators.
"""

from __future__ import annotations

import re
from pathlib import Path

#: The first line of the cell.toml an emulated cell writes.
EMULATED_HEADER = "# Emulated cell (time scale {scale:g}); written by cellctl emulate cell."
_EMULATED_HEADER = re.compile(r"#\s*Emulated cell \(time scale ([0-9.eE+-]+)\)")


def written_by_emulation(toml: Path) -> bool:
    """True if ``toml`` is a cell.toml an emulated cell wrote (its first line
    :data:`EMULATED_HEADER`), False for any other file, or one that cannot be read."""
    return emulated_scale(toml) is not None


def emulated_scale(toml: Path) -> str | None:
    """The time scale (as written: ``"100"``) of a cell.toml an emulated cell wrote; None for
    any other file, or one that cannot be read."""
    found = _EMULATED_HEADER.match(first_line(toml))
    return found.group(1) if found else None


def first_line(path: Path) -> str:
    """The first line of ``path`` (at most 200 characters, stripped); "" if it cannot be read."""
    try:
        with path.open(encoding="utf-8", errors="replace") as f:
            return f.readline(200).strip()
    except OSError:
        return ""
