"""Line settings of a serial link: baud, data bits, parity, stop bits, RTS/CTS.

``LineSettings.parse("4800,7E2")`` reads the compact form used in ``cell.toml`` and on the
command line; ``str(settings)`` writes it back. ``char_time`` is how long one character takes
on the wire, which drivers add to their deadlines and emulators use to pace the line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

from cellctl.errors import UsageError

PARITIES = {"N": "none", "E": "even", "O": "odd", "M": "mark", "S": "space"}

#: The highest baud rate a line may have: 1 Gbaud. No serial line comes near it (UARTs and USB
#: adapters stop at a few Mbaud, Linux's highest standard rate is 4,000,000); it is not that
#: limit because an emulated cell runs its lines as much faster as its machines (4800 baud at
#: time scale 1000 is 4,800,000 in its cell.toml, and ``mem://`` stands for a 100 Mbit/s
#: network), and it stays well under what the OS call can carry (pyserial hands Linux a
#: custom rate as a signed 32-bit int: 2,147,483,647; above it came an OverflowError).
MAX_BAUDRATE = 1_000_000_000

_COMPACT = re.compile(
    r"^\s*(\d+)\s*[,:/ ]\s*([5-8])([NEOMSneoms])(1|1\.5|2)\s*(,\s*(?i:rtscts))?\s*$"
)
_XONXOFF = re.compile(r",\s*(xon|xoff|software)", re.IGNORECASE)


@dataclass(frozen=True)
class LineSettings:
    """How characters are framed on the line. The default is the robot's 4800 7E2."""

    baudrate: int = 4800
    bytesize: int = 7
    parity: str = "E"
    stopbits: float = 2
    rtscts: bool = False
    _char_time: float = field(init=False, repr=False, compare=False, default=0.0)

    def __post_init__(self) -> None:
        if self.baudrate <= 0:
            raise UsageError(f"baud rate must be positive, not {self.baudrate}")
        if self.baudrate > MAX_BAUDRATE:
            raise UsageError(
                f"baud rate {self.baudrate} is beyond any serial line: at most {MAX_BAUDRATE:,}"
            )
        if self.bytesize not in (5, 6, 7, 8):
            raise UsageError(f"data bits must be 5 to 8, not {self.bytesize}")
        if self.parity not in PARITIES:
            raise UsageError(f"parity must be one of {''.join(PARITIES)}, not {self.parity!r}")
        if self.stopbits not in (1, 1.5, 2):
            raise UsageError(f"stop bits must be 1, 1.5 or 2, not {self.stopbits}")
        # Every reply deadline adds wire time: work it out once (kept out of eq, hash, repr and
        # the constructor: replace() recomputes it).
        object.__setattr__(self, "_char_time", self.bits_per_char / self.baudrate)

    @property
    def bits_per_char(self) -> float:
        """Start bit + data bits + parity bit + stop bits."""
        return 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits

    @property
    def char_time(self) -> float:
        """Seconds one character takes on the wire (11/4800 s at 4800 7E2)."""
        return self._char_time

    @property
    def chars_per_second(self) -> float:
        """The line rate: the most characters per second the line can carry."""
        return self.baudrate / self.bits_per_char

    def wire_time(self, nbytes: int) -> float:
        """Seconds ``nbytes`` characters take on the wire."""
        return nbytes * self._char_time

    def with_(self, **changes: object) -> LineSettings:
        """A copy with some fields changed, e.g. ``s.with_(rtscts=True)``."""
        return replace(self, **changes)  # type: ignore[arg-type]

    @classmethod
    def parse(cls, text: str) -> LineSettings:
        """Read ``"4800,7E2"``, ``"2400,8N1"`` or ``"9600,8N1,rtscts"``."""
        m = _COMPACT.match(text)
        if not m and _XONXOFF.search(text):
            raise UsageError(
                f"line settings {text!r}: Xon/Xoff flow control stays off, as the bytes are "
                "protocol (the robot's Xon, Xoff and Ack): write baud,bits parity stop like "
                "4800,7E2 (optionally ,rtscts)"
            )
        if not m:
            raise UsageError(
                f"line settings {text!r} not understood: write baud,bits parity stop "
                "like 4800,7E2 (optionally ,rtscts)"
            )
        digits = m.group(1).lstrip("0") or "0"
        if len(digits) > len(str(MAX_BAUDRATE)):  # said before int() meets 5,000 digits
            shown = digits if len(digits) <= 20 else f"{digits[:20]}... ({len(digits)} digits)"
            raise UsageError(
                f"baud rate {shown} is beyond any serial line: at most {MAX_BAUDRATE:,}"
            )
        stop = float(m.group(4))
        return cls(
            baudrate=int(digits),
            bytesize=int(m.group(2)),
            parity=m.group(3).upper(),
            stopbits=int(stop) if stop.is_integer() else stop,
            rtscts=bool(m.group(5)),
        )

    def __str__(self) -> str:
        stop = int(self.stopbits) if float(self.stopbits).is_integer() else self.stopbits
        text = f"{self.baudrate},{self.bytesize}{self.parity}{stop}"
        return text + (",rtscts" if self.rtscts else "")


ROBOT_LINE = LineSettings(4800, 7, "E", 2)
"""The IBM 7545/7547 controller's line: 4800 baud, 7 data bits, even parity, 2 stop bits."""

MILL_LINE = LineSettings(4800, 7, "E", 2)
"""The Dyna 2400 line as the source's cell controller set it (other shops use 2400,8N1)."""

ETHERNET_LINE = LineSettings(100_000_000, 8, "N", 1)
"""A ``mem://`` line standing for a 100 Mbit/s network (the in-process Modbus/TCP PLC): its
characters take a tenth of a microsecond, nothing next to a PLC's scan."""
