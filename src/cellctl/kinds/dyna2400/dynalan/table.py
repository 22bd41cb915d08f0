"""The DYNALAN statement table: every fact about the language, once.

The parser, the validator, the toolpath and the mill emulator all read this module, so a
correction to the language (a keyword, a limit, a default) is a one-line change here.

Each :class:`StatementSpec` says how a statement is spelled (``syntax``, for people, and ``head``
/ ``body``, for the parser), where the knowledge comes from (``origin``), and which named fields
it carries. Limits that depend on units are given in inches and scaled by :func:`scale`.

Origins:

- ``SOURCE``: shown in the 1988 thesis (appendix C) or its C listing.
- ``DOCUMENTED``: the spec's "DYNALAN as documented elsewhere" (a CAM post and user reports).
- ``PROJECT``: the project's own convention where both are silent (the canned cycles' syntax,
  the clearance plane, hole lines holding two axis words, ...).
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass, field

# --- wire framing -------------------------------------------------------------------------------
CR = 0x0D
LF = 0x0A
CTRL_Z = 0x1A  # end of a transmission
DC1 = 0x11  # in-band readiness: the controller's RTS went high (project's fallback)
DC3 = 0x13  # in-band readiness: the controller's RTS went low (project's fallback)
ENQ = 0x05  # in-band readiness: the host asks for the current level (project's fallback)
LINE_END = b"\r\n"  # what cellctl sends; the controller accepts CR LF, LF CR or LF

# --- memory and blocks --------------------------------------------------------------------------
MEMORY_LINES = 1000  # numbered lines 000-999 held by the controller
BLOCK_MAX_LINES = 900  # lines in one program-execute block, the closing pair included
BLOCK_END_LINE = 900  # the blank line that closes a block; `SKIP TO 900` jumps to it
BLOCK_BODY_MAX = BLOCK_MAX_LINES - 2  # statements left once `SKIP TO 900` / `900` are counted
LOAD_MAX_LINES = 900  # program load (no execution): at most this many lines
LINE_NUMBER_DIGITS = 3

# --- limits and defaults (inches; see scale()) ----------------------------------------------------
MM_PER_INCH = 25.4
FEED_MIN = 0.1  # in/min
FEED_MAX = 32.0  # in/min
FEED_DEFAULT = 8.0  # in/min (203.2 mm/min)
RAPID_RATE = 50.0  # in/min for GOf/GRf, Z>C and cycle positioning (assumed)
SPINDLE_MAX_RPM = 10_000
TOOL_MAX = 99
PROGRAM_NUMBER_MIN = 1
PROGRAM_NUMBER_MAX = 99
REPEAT_MAX = 99
ARC_MAX_DEGREES = 180.0  # one GR A move sweeps at most this much (exactly 180 is allowed)
TOOL_DIAMETER_DEFAULT = 0.125  # in, the source's setup program
CLEARANCE_Z = 0.0  # in, Z>C goes here: the top of the default Z travel (assumed)
STEP_OVER = 0.6  # pocket cycles step over this fraction of the tool diameter (assumed)
DECIMALS = {"INS": 4, "MM": 2}  # more decimals than this draws a warning (assumed)
SETUP_AXES = frozenset("zcxyu")  # letters allowed after SETUP >
COMMENT_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 .,=_-")
AXES = ("X", "Y", "Z")
RUNAWAY_STEPS = 2_000_000  # executing more statements than this in one block is a loop
NUMBER_MAX = 1_000_000  # largest magnitude a number may have (assumed): keeps arithmetic finite
INTEGER_DIGITS_MAX = 9  # a whole number (tool, RPM, REPEAT count ...) has at most this many digits
PASSES_MAX = 100_000  # passes, rings, rows or pecks one statement may make (project's cap)
STATEMENT_POINTS_MAX = 200_000  # points of motion one statement may make (project's cap)
TOOLPATH_POINTS_MAX = 250_000  # points of motion a program's toolpath may hold (project's cap)
TOOLPATH_STEPS_MAX = 500_000  # statements a toolpath executes at most, REPEATs unrolled (project's)


class Units(enum.Enum):
    """Program units, as written after START."""

    INS = "INS"
    MM = "MM"

    @property
    def per_inch(self) -> float:
        """How many of these units make one inch."""
        return 1.0 if self is Units.INS else MM_PER_INCH

    @property
    def length_name(self) -> str:
        return "in" if self is Units.INS else "mm"


def scale(value_in_inches: float, units: Units) -> float:
    """An inch limit in ``units`` (the metric limits are the inch limits times 25.4)."""
    return value_in_inches * units.per_inch


@dataclass(frozen=True)
class Travel:
    """Axis travel relative to the reference zero, in inches (configurable per machine)."""

    x_min: float = 0.0
    x_max: float = 8.0
    y_min: float = 0.0
    y_max: float = 6.0
    z_min: float = -4.0
    z_max: float = 0.0

    def limits(self, axis: str, units: Units) -> tuple[float, float]:
        """``(low, high)`` of ``axis`` ("X", "Y" or "Z") in ``units``."""
        low, high = {
            "X": (self.x_min, self.x_max),
            "Y": (self.y_min, self.y_max),
            "Z": (self.z_min, self.z_max),
        }[axis]
        return scale(low, units), scale(high, units)


class Origin(enum.Enum):
    SOURCE = "source"
    DOCUMENTED = "documented"
    PROJECT = "project"


class Kind(enum.Enum):
    """Every statement DYNALAN has (one member per table row)."""

    BLANK = "blank"
    COMMENT = "comment"
    START = "START"
    SETUP = "SETUP"
    TOOL = "TOOL"
    TD = "TD"
    FEED = "FR"
    GO = "GO"
    GR = "GR"
    GO_FAST = "GOf"
    GR_FAST = "GRf"
    ARC = "GR A"
    AXIS = "axis"
    CLEARANCE = "Z>C"
    ZERO_AT = "ZERO AT"
    REF_COORD = ">REF COORD"
    SPINDLE_ON = "SPINDLE ON"
    SPINDLE_OFF = "SPINDLE OFF"
    SPINDLE_SPEED = "SP="
    COOLANT_ON = "COOLANT ON"
    COOLANT_OFF = "COOLANT OFF"
    DWELL = "DWELL"
    DRILL = "DRIL"
    DRILL_TOP = "ZH="
    DRILL_BOTTOM = "ZD="
    REPEAT = "REPEAT"
    REPEAT_END = "REPEAT END"
    SKIP = "SKIP TO"
    HALT = "HALT"
    END = "END"
    MILL = "MILL"
    FRAME = "FRAME"
    RFRAME = "RFRAME"
    RPOCKET = "RPOCKET"
    CPOCKET = "CPOCKET"
    ARCFRAME = "ARCFRAME"


class FieldType(enum.Enum):
    NUMBER = "number"  # decimal, optional sign, e.g. 1.000, .5, -0.25
    INTEGER = "integer"  # digits only
    LINE = "line"  # three-digit line number
    WORD = "word"  # free text checked by the statement's own rule


@dataclass(frozen=True)
class StatementSpec:
    """One row of the table. ``head`` finds the statement; ``body`` must then match it whole.

    Named groups of ``body`` are the statement's fields; ``fields`` gives each one's type.
    ``params`` lists the ``KEY= value`` parameters of a canned cycle (required, then optional).
    """

    kind: Kind
    syntax: str
    origin: Origin
    summary: str
    head: re.Pattern[str]
    body: re.Pattern[str] | None = None
    fields: dict[str, FieldType] = field(default_factory=dict)
    required: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()
    moves: bool = False  # produces motion (travel is checked)
    opens_axis_lines: bool = False  # axis-only lines may follow (continuations, centre, holes)


def _re(text: str) -> re.Pattern[str]:
    return re.compile(text)


_N = r"(?P<{}>\S+)"  # a number slot: any token; the field type checks its spelling


def _cycle(
    kind: Kind, syntax: str, summary: str, required: tuple[str, ...], optional: tuple[str, ...]
) -> StatementSpec:
    return StatementSpec(
        kind,
        syntax,
        Origin.PROJECT,
        summary,
        head=_re(rf"{kind.value}(?=\s|$)"),
        required=required,
        optional=optional,
        moves=True,
    )


#: The statements, in the order the parser tries their heads (longer keywords first).
STATEMENTS: tuple[StatementSpec, ...] = (
    StatementSpec(
        Kind.COMMENT,
        "; TEXT",
        Origin.DOCUMENTED,
        "comment: A-Z 0-9 space . , = _ - only",
        head=_re(r";"),
        body=_re(r";(?P<text>.*)"),
        fields={"text": FieldType.WORD},
    ),
    StatementSpec(
        Kind.START,
        "START INS nn | START MM nn",
        Origin.SOURCE,
        "program start, units and program number 01-99; line 000 when present",
        head=_re(r"START(?=\s|$)"),
        body=_re(r"START\s+(?P<units>\S+)\s+(?P<program>\S+)"),
        fields={"units": FieldType.WORD, "program": FieldType.INTEGER},
    ),
    StatementSpec(
        Kind.SETUP,
        "SETUP >zcxyu",
        Origin.SOURCE,
        "stop for the operator to jog to the reference zero and press NEXT",
        head=_re(r"SETUP(?=\s|>|$)"),
        body=_re(r"SETUP\s*>\s*(?P<axes>\S+)"),
        fields={"axes": FieldType.WORD},
    ),
    StatementSpec(
        Kind.TOOL,
        "TOOL n",
        Origin.DOCUMENTED,
        "tool number, at most 99",
        head=_re(r"TOOL(?=\s|$)"),
        body=_re(r"TOOL\s+" + _N.format("tool")),
        fields={"tool": FieldType.INTEGER},
    ),
    StatementSpec(
        Kind.TD,
        "TD = d",
        Origin.SOURCE,
        "tool diameter",
        head=_re(r"TD(?=\s|=|$)"),
        body=_re(r"TD\s*=\s*" + _N.format("diameter")),
        fields={"diameter": FieldType.NUMBER},
    ),
    StatementSpec(
        Kind.FEED,
        "FR XYZ = v | FR XY = v | FR Z = v (also F XYZ = v)",
        Origin.SOURCE,
        "feed rate of the named axes, 0.1-32.0 in/min (2.54-812.8 mm/min)",
        head=_re(r"FR?(?=\s)"),
        body=_re(r"FR?\s+(?P<axes>[A-Z]+)\s*=\s*" + _N.format("rate")),
        fields={"axes": FieldType.WORD, "rate": FieldType.NUMBER},
    ),
    StatementSpec(
        Kind.ZERO_AT,
        "ZERO AT / X cx / Y cy",
        Origin.DOCUMENTED,
        "local zero at the centre given on the axis lines that follow",
        head=_re(r"ZERO(?=\s|$)"),
        body=_re(r"ZERO\s+AT"),
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.REF_COORD,
        ">REF COORD",
        Origin.DOCUMENTED,
        "back to reference coordinates",
        head=_re(r">"),
        body=_re(r">\s*REF\s+COORD"),
    ),
    StatementSpec(
        Kind.CLEARANCE,
        "Z>C",
        Origin.DOCUMENTED,
        "rapid Z to the clearance plane",
        head=_re(r"Z\s*>"),
        body=_re(r"Z\s*>\s*C"),
        moves=True,
    ),
    StatementSpec(
        Kind.DRILL_TOP,
        "ZH= top",
        Origin.DOCUMENTED,
        "drill cycle: Z of the hole tops (rapid plane)",
        head=_re(r"ZH(?=\s|=|$)"),
        body=_re(r"ZH\s*=\s*" + _N.format("z")),
        fields={"z": FieldType.NUMBER},
    ),
    StatementSpec(
        Kind.DRILL_BOTTOM,
        "ZD= bottom",
        Origin.DOCUMENTED,
        "drill cycle: Z of the hole bottoms; X/Y hole lines follow",
        head=_re(r"ZD(?=\s|=|$)"),
        body=_re(r"ZD\s*=\s*" + _N.format("z")),
        fields={"z": FieldType.NUMBER},
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.DRILL,
        "DRIL PECK= p",
        Origin.DOCUMENTED,
        "drill cycle (the source's 'drill'): peck depth, 0 for one plunge",
        head=_re(r"DRIL(?=\s|$)"),
        body=_re(r"DRIL\s+PECK\s*=\s*" + _N.format("peck")),
        fields={"peck": FieldType.NUMBER},
    ),
    StatementSpec(
        Kind.SPINDLE_ON,
        "SPINDLE ON",
        Origin.DOCUMENTED,
        "spindle on",
        head=_re(r"SPINDLE\s+ON(?=\s|$)"),
        body=_re(r"SPINDLE\s+ON"),
    ),
    StatementSpec(
        Kind.SPINDLE_OFF,
        "SPINDLE OFF",
        Origin.DOCUMENTED,
        "spindle off",
        head=_re(r"SPINDLE(?=\s|$)"),
        body=_re(r"SPINDLE\s+OFF"),
    ),
    StatementSpec(
        Kind.SPINDLE_SPEED,
        "SP= n RPM",
        Origin.DOCUMENTED,
        "spindle speed, 0-10,000 RPM",
        head=_re(r"SP(?=\s|=)"),
        body=_re(r"SP\s*=\s*" + _N.format("rpm") + r"(?:\s+RPM)?"),
        fields={"rpm": FieldType.INTEGER},
    ),
    StatementSpec(
        Kind.COOLANT_ON,
        "COOLANT ON",
        Origin.DOCUMENTED,
        "coolant on",
        head=_re(r"COOLANT\s+ON(?=\s|$)"),
        body=_re(r"COOLANT\s+ON"),
    ),
    StatementSpec(
        Kind.COOLANT_OFF,
        "COOLANT OFF",
        Origin.DOCUMENTED,
        "coolant off",
        head=_re(r"COOLANT(?=\s|$)"),
        body=_re(r"COOLANT\s+OFF"),
    ),
    StatementSpec(
        Kind.DWELL,
        "DWELL s",
        Origin.DOCUMENTED,
        "wait s seconds",
        head=_re(r"DWELL(?=\s|$)"),
        body=_re(r"DWELL\s+" + _N.format("seconds")),
        fields={"seconds": FieldType.NUMBER},
        moves=True,
    ),
    StatementSpec(
        Kind.REPEAT_END,
        "REPEAT END",
        Origin.DOCUMENTED,
        "end of the innermost REPEAT",
        head=_re(r"REPEAT\s+END(?=\s|$)"),
        body=_re(r"REPEAT\s+END"),
    ),
    StatementSpec(
        Kind.REPEAT,
        "REPEAT nn",
        Origin.DOCUMENTED,
        "run the lines up to the matching REPEAT END nn times (1-99)",
        head=_re(r"REPEAT(?=\s|$)"),
        body=_re(r"REPEAT\s+" + _N.format("count")),
        fields={"count": FieldType.INTEGER},
    ),
    StatementSpec(
        Kind.SKIP,
        "SKIP TO nnn",
        Origin.SOURCE,
        "jump forward to line nnn of this block; SKIP TO 900 ends the block",
        head=_re(r"SKIP(?=\s|$)"),
        body=_re(r"SKIP\s+TO\s+" + _N.format("target")),
        fields={"target": FieldType.LINE},
    ),
    StatementSpec(
        Kind.HALT,
        "HALT",
        Origin.DOCUMENTED,
        "stop the program",
        head=_re(r"HALT(?=\s|$)"),
        body=_re(r"HALT"),
    ),
    StatementSpec(
        Kind.END,
        "END",
        Origin.SOURCE,
        "end of program execute mode: the controller returns to manual",
        head=_re(r"END(?=\s|$)"),
        body=_re(r"END"),
    ),
    _cycle(
        Kind.MILL,
        "MILL X= x Y= y ZD= z [DP= p]",
        "slot from here to (x, y) down to ZD in passes of DP; returns to the start",
        ("X", "Y", "ZD"),
        ("DP",),
    ),
    _cycle(
        Kind.RFRAME,
        "RFRAME XL= a YL= b ZD= z [DP= p]",
        "rectangular frame: outside profile of an a x b boss whose corner is here",
        ("XL", "YL", "ZD"),
        ("DP",),
    ),
    _cycle(
        Kind.FRAME,
        "FRAME XL= a YL= b ZD= z [DP= p]",
        "tool centre round the a x b rectangle whose corner is here (no cutter offset)",
        ("XL", "YL", "ZD"),
        ("DP",),
    ),
    _cycle(
        Kind.RPOCKET,
        "RPOCKET XL= a YL= b ZD= z [DP= p]",
        "rectangular pocket a x b whose corner is here, cleared in zig-zag passes",
        ("XL", "YL", "ZD"),
        ("DP",),
    ),
    _cycle(
        Kind.CPOCKET,
        "CPOCKET R= r ZD= z [DP= p]",
        "circular pocket of radius r centred here, cleared in rings",
        ("R", "ZD"),
        ("DP",),
    ),
    _cycle(
        Kind.ARCFRAME,
        "ARCFRAME R= r A= deg [AS= start] ZD= z [DP= p]",
        "arc slot of radius r about here from angle AS sweeping A degrees (up to 360)",
        ("R", "A", "ZD"),
        ("AS", "DP"),
    ),
    # Motion last: their heads are short and would shadow the keywords above.
    StatementSpec(
        Kind.GO_FAST,
        "GOf X v",
        Origin.DOCUMENTED,
        "absolute positioning at the rapid rate",
        head=_re(r"GOf(?=\s|$)"),
        moves=True,
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.GR_FAST,
        "GRf X v",
        Origin.DOCUMENTED,
        "incremental positioning at the rapid rate",
        head=_re(r"GRf(?=\s|$)"),
        moves=True,
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.GO,
        "GO X v (or Y, Z)",
        Origin.SOURCE,
        "absolute move at the feed rate, one axis word a line",
        head=_re(r"GO(?=\s|$)"),
        moves=True,
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.ARC,
        "GR A deg",
        Origin.DOCUMENTED,
        "arc about the local zero, + counter-clockwise, at most 180 degrees",
        head=_re(r"GR\s+A(?=\s|$)"),
        body=_re(r"GR\s+A\s+" + _N.format("degrees")),
        fields={"degrees": FieldType.NUMBER},
        moves=True,
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.GR,
        "GR X v (or Y, Z)",
        Origin.SOURCE,
        "incremental move at the feed rate, one axis word a line",
        head=_re(r"GR(?=\s|$)"),
        moves=True,
        opens_axis_lines=True,
    ),
    StatementSpec(
        Kind.AXIS,
        "  X v (or Y, Z)",
        Origin.SOURCE,
        "axis-only line: continuation of a move, a ZERO AT centre, or a drill hole",
        head=_re(r"[XYZ](?=\s|$)"),
        moves=True,
    ),
)

SPECS: dict[Kind, StatementSpec] = {spec.kind: spec for spec in STATEMENTS}

#: Statements built from axis words (`GO X 1.0`, `  Y 2.0`), parsed by the axis-word rule.
AXIS_WORD_KINDS = frozenset({Kind.GO, Kind.GR, Kind.GO_FAST, Kind.GR_FAST, Kind.AXIS})
#: Canned cycles (the project's syntax: `NAME KEY= v ...`).
CYCLE_KINDS = frozenset(
    {Kind.MILL, Kind.FRAME, Kind.RFRAME, Kind.RPOCKET, Kind.CPOCKET, Kind.ARCFRAME}
)
#: Statements after which axis-only lines continue the same motion type.
MOTION_KINDS = frozenset({Kind.GO, Kind.GR, Kind.GO_FAST, Kind.GR_FAST, Kind.ARC})
#: Statements that leave the axis-line context as it is.
NEUTRAL_KINDS = frozenset({Kind.COMMENT, Kind.BLANK})

NUMBER_RE = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)")
INTEGER_RE = re.compile(r"\d+")
LINE_NUMBER_RE = re.compile(r"\d{3}")
