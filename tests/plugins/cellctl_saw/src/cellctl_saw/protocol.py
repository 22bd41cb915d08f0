"""The Kerf 100's line protocol and its cut lists: codecs only, no I/O.

The saw talks ASCII at 9600,8N1, one command a line and one reply a line, each ended by CR LF:

=============  ==================  ===================================================
command        reply               what it does
=============  ==================  ===================================================
``ID``         ``KERF 100 V1``     who is there
``ST``         ``ST s d n a``      state ``s`` (:class:`SawState`), ``d`` cuts done of
                                   ``n`` loaded, alarm ``a`` (:data:`ALARMS`, 0: none)
``HOME``       ``OK``              drive the carriage to its home switch (state 0 -> 1)
``CLEAR``      ``OK``              empty the cut list
``CUT L F``    ``OK``              add a cut: ``L`` mm of bar at feed ``F`` mm/min
``RUN``        ``OK``              cut the list, one after the other (state 2)
``STOP``       ``OK``              stop the blade; the cut list stays
``RESET``      ``OK``              clear an alarm (state 0: home it again)
=============  ==================  ===================================================

A refusal is ``ERR c TEXT`` (:data:`ERRORS`). A cut takes ``L / F`` minutes.

A cut list (``.cut``) is one statement a line, ``#`` starts a comment::

    HOME              # a setup: home the carriage
    CUT 120 300       # a program: 120 mm at 300 mm/min
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from cellctl.errors import DeviceError, ProtocolError
from cellctl.kinds import Condition
from cellctl.kinds.kind import MachineState

EOL = b"\r\n"
IDENT = "KERF 100 V1"
#: The longest cut the carriage can measure, mm, and the blade's fastest feed, mm/min.
MAX_LENGTH_MM = 3000.0
MAX_FEED_MM_MIN = 2000.0
#: Machine time the carriage takes to find its home switch, s.
HOME_S = 2.0


class SawState(MachineState):
    """The state numbers ``ST`` answers."""

    NOT_HOMED = 0, "not homed"
    IDLE = 1, "idle"
    CUTTING = 2, "cutting"
    ALARM = 3, "alarm"


CONDITIONS = {
    SawState.NOT_HOMED: Condition.NOT_READY,
    SawState.IDLE: Condition.IDLE,
    SawState.CUTTING: Condition.BUSY,
    SawState.ALARM: Condition.ALARM,
}

#: Alarm codes ``ST`` carries.
ALARMS = {0: "", 1: "blade jammed", 2: "home switch not found"}
#: Refusal codes of ``ERR c TEXT``.
ERRORS = {
    1: "NOT HOMED",
    2: "BUSY",
    3: "BAD CUT",
    4: "NO CUTS",
    5: "ALARM",
    6: "HOME SWITCH",
    9: "UNKNOWN COMMAND",
}


def command(*words: object) -> bytes:
    """One command line: ``command("CUT", 120, 300)`` -> ``b"CUT 120 300\\r\\n"``."""
    return " ".join(_number(w) if isinstance(w, float) else str(w) for w in words).encode() + EOL


def _number(value: float) -> str:
    return f"{value:g}"


@dataclass(frozen=True)
class SawStatus:
    """What ``ST`` answers, as the mill family reads it (a ``families.MillReading``)."""

    state: int
    done: int = 0
    loaded: int = 0
    alarm: int = 0

    @property
    def ready(self) -> bool:
        return self.state == SawState.IDLE

    @property
    def set_up(self) -> bool:
        return self.state == SawState.IDLE

    @property
    def takes_work(self) -> bool:
        return self.state == SawState.IDLE

    @property
    def awaiting_operator(self) -> bool:
        return False  # homing is the saw's own: no operator step follows a setup

    @property
    def waiting_for(self) -> str | None:
        return ALARMS.get(self.alarm) or None

    @property
    def shown(self) -> str:
        words = SawState.words(self.state)
        if self.alarm:
            words += f", {ALARMS.get(self.alarm, f'alarm {self.alarm}')}"
        if self.state == SawState.CUTTING:
            words += f", cut {min(self.done + 1, self.loaded)} of {self.loaded}"
        return words

    @property
    def kind_condition(self) -> Condition:
        return CONDITIONS.get(self.state, Condition.NOT_READY)  # type: ignore[call-overload]

    def __str__(self) -> str:
        return self.shown


_ST = re.compile(rb"ST (\d) (\d{1,4}) (\d{1,4}) (\d{1,2})")
_ERR = re.compile(rb"ERR (\d{1,2}) ([ -~]{0,40})")


def parse_reply(raw: bytes) -> str:
    """An ``OK``/``ID`` reply line's text; DeviceError for ``ERR``; ProtocolError otherwise."""
    line = raw.removesuffix(EOL)
    if (m := _ERR.fullmatch(line)) is not None:
        code = int(m.group(1))
        raise DeviceError(code, ERRORS.get(code, "ERROR"), detail=m.group(2).decode())
    if line == b"OK" or line == IDENT.encode():
        return line.decode()
    raise ProtocolError("the saw answered something that is not a reply", raw)


def parse_status(raw: bytes) -> SawStatus:
    """An ``ST`` reply; ProtocolError (with the bytes) when it is not one."""
    line = raw.removesuffix(EOL)
    if (m := _ERR.fullmatch(line)) is not None:
        parse_reply(raw)
    m = _ST.fullmatch(line)
    if m is None:
        raise ProtocolError("the saw's status is not ST s d n a", raw)
    state, done, loaded, alarm = (int(g) for g in m.groups())
    return SawStatus(state, done, loaded, alarm)


def status_line(status: SawStatus) -> bytes:
    """The ``ST`` reply for ``status`` (the emulator's side)."""
    return command("ST", status.state, status.done, status.loaded, status.alarm)


# -- cut lists -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Cut:
    length_mm: float
    feed_mm_min: float

    @property
    def seconds(self) -> float:
        """Machine time of this cut."""
        return self.length_mm / self.feed_mm_min * 60.0


@dataclass(frozen=True)
class CutList:
    """A parsed ``.cut`` file: its statements and every problem, ``name:line: text``."""

    home: bool
    cuts: tuple[Cut, ...]
    problems: tuple[str, ...]
    lines: int

    @property
    def seconds(self) -> float:
        return sum(c.seconds for c in self.cuts)


def parse_cut_list(
    text: str,
    name: str,
    *,
    setup: bool | None = None,
    max_length_mm: float = MAX_LENGTH_MM,
) -> CutList:
    """Parse and check a cut list. ``setup``: True for a setup (``HOME`` only), False for a
    program (``CUT`` lines only), None for either."""
    home = False
    cuts: list[Cut] = []
    problems: list[str] = []
    lines = text.splitlines()
    for number, line in enumerate(lines, start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{name}:{number}"
        verb = words[0].upper()
        if verb == "HOME" and len(words) == 1:
            home = True
        elif verb == "CUT" and len(words) == 3:
            try:
                cut = Cut(float(words[1]), float(words[2]))
            except ValueError:
                problems.append(f"{where}: CUT takes two numbers, LENGTH_MM FEED_MM_MIN")
                continue
            if not 0 < cut.length_mm <= max_length_mm:
                problems.append(f"{where}: length must be 0 to {max_length_mm:g} mm")
            elif not 0 < cut.feed_mm_min <= MAX_FEED_MM_MIN:
                problems.append(f"{where}: feed must be 0 to {MAX_FEED_MM_MIN:g} mm/min")
            else:
                cuts.append(cut)
        else:
            problems.append(f"{where}: not a statement: {line.strip()[:40]!r} (HOME, CUT L F)")
    if setup is True and (cuts or not home):
        problems.append(f"{name}: a setup is HOME and nothing else")
    if setup is False and (home or not cuts):
        problems.append(f"{name}: a program is one or more CUT lines and nothing else")
    return CutList(home, tuple(cuts), tuple(problems), len(lines))
