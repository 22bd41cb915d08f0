"""How long a Dyna 2400 takes to cut a program: the DYNALAN machine model, once.

The mill emulator runs the same toolpath (:func:`~cellctl.kinds.dyna2400.dynalan.build_toolpath`);
the cell's physical bound asks this :class:`CutModel` for each program's cut time and its
characters on the line, without running anything. Pure: no I/O but reading the programs.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

from cellctl.files import read_text
from cellctl.kinds.dyna2400 import dynalan


class CutModel:
    """The mill kind's :class:`~cellctl.kinds.families.MillModel`."""

    def __init__(self, config: dynalan.MachineConfig | None = None) -> None:
        self.config = config or dynalan.MachineConfig()

    def cut_times(self, setup: Path | None, programs: Sequence[Path]) -> list[tuple[float, int]]:
        """Each program's least cut time (machine s) and its characters on the line."""
        state = dynalan.MachineState.initial(dynalan.Units.INS)
        if setup is not None:
            self._run(setup, state)
        state.position = (0.0, 0.0, 0.0)  # the operator jogs to the reference zero
        after_setup = state.copy()
        ends = []
        for path in programs:
            s = after_setup.copy()
            self._run(path, s)
            ends.append(s)
        out = []
        for path in programs:
            blocks = dynalan.split_program(_parse(path))
            chars = sum(len(b.wire()) + 1 for b in blocks)  # each block ends with Ctrl-Z
            cut = min(
                dynalan.build_toolpath(blocks, s.copy(), self.config).machining_seconds
                for s in itertools.chain([after_setup], ends)
            )
            out.append((cut, chars))
        return out

    def _run(self, path: Path, state: dynalan.MachineState) -> None:
        dynalan.build_toolpath(dynalan.split_program(_parse(path)), state, self.config)


def _parse(path: Path) -> dynalan.Program:
    return dynalan.parse_program(read_text(path, "ascii", "replace"), name=path.name)
