"""The dialect's tables (RS-274, Fanuc M series), no I/O: each address letter's meaning and
range, the G codes' modal groups, the M codes' groups. Read by the G-code check
(:mod:`cellctl.kinds.iso_cnc.gcode`, which re-exports them) and the motion model."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WordRule:
    """One address letter: what it means, its range, and whether it is a whole number."""

    meaning: str
    low: float
    high: float
    whole: bool = False


_AXIS = 99999.999
#: The address letters a Fanuc M-series control reads (mm; inch programs are smaller).
WORDS: dict[str, WordRule] = {
    "A": WordRule("rotary axis about X, deg", -_AXIS, _AXIS),
    "B": WordRule("rotary axis about Y, deg", -_AXIS, _AXIS),
    "C": WordRule("rotary axis about Z, deg", -_AXIS, _AXIS),
    "D": WordRule("cutter radius offset number", 0, 400, True),
    "E": WordRule("thread lead", 0, _AXIS),
    "F": WordRule("feed, mm/min (G94) or mm/rev (G95)", 0, 240000),
    "G": WordRule("preparatory function", 0, 999.9),
    "H": WordRule("tool length offset number", 0, 400, True),
    "I": WordRule("arc centre X offset", -_AXIS, _AXIS),
    "J": WordRule("arc centre Y offset", -_AXIS, _AXIS),
    "K": WordRule("arc centre Z offset", -_AXIS, _AXIS),
    "L": WordRule("repeat count", 0, 9999, True),
    "M": WordRule("miscellaneous function", 0, 999, True),
    "N": WordRule("sequence number", 0, 99999, True),
    "O": WordRule("program number", 1, 99999999, True),
    "P": WordRule("dwell (ms) or subprogram number", 0, 99999999),
    "Q": WordRule("peck depth", -_AXIS, _AXIS),
    "R": WordRule("arc radius or R plane", -_AXIS, _AXIS),
    "S": WordRule("spindle speed, rpm", 0, 99999),
    "T": WordRule("tool number", 0, 99999999, True),
    "U": WordRule("additional axis parallel to X", -_AXIS, _AXIS),
    "V": WordRule("additional axis parallel to Y", -_AXIS, _AXIS),
    "W": WordRule("additional axis parallel to Z", -_AXIS, _AXIS),
    "X": WordRule("X axis", -_AXIS, _AXIS),
    "Y": WordRule("Y axis", -_AXIS, _AXIS),
    "Z": WordRule("Z axis", -_AXIS, _AXIS),
}

#: G code -> its group (Fanuc M series; 0 is one-shot). Codes not here are refused.
G_GROUPS: dict[float, int] = {
    **dict.fromkeys((4, 9, 10, 11, 27, 28, 29, 30, 31, 52, 53, 92), 0),
    **dict.fromkeys((0, 1, 2, 3, 33), 1),
    **dict.fromkeys((17, 18, 19), 2),
    **dict.fromkeys((90, 91), 3),
    **dict.fromkeys((94, 95), 5),
    **dict.fromkeys((20, 21), 6),
    **dict.fromkeys((40, 41, 42), 7),
    **dict.fromkeys((43, 44, 49), 8),
    **dict.fromkeys((73, 74, 76, 80, 81, 82, 83, 84, 85, 86, 87, 88, 89), 9),
    **dict.fromkeys((98, 99), 10),
    **dict.fromkeys((66, 67), 12),
    **dict.fromkeys((54, 55, 56, 57, 58, 59), 14),
    **dict.fromkeys((61, 62, 63, 64), 15),
    **dict.fromkeys((68, 69), 16),
    **dict.fromkeys((15, 16), 17),
    **dict.fromkeys((50, 51), 11),
}
#: M code -> its group: two of one group in a block is an error (others pass unchecked).
M_GROUPS: dict[int, str] = {
    **dict.fromkeys((0, 1, 2, 30, 60, 98, 99), "program stop"),
    **dict.fromkeys((3, 4, 5, 19), "spindle"),
    **dict.fromkeys((7, 9), "coolant"),
}
#: Codes that end a program.
PROGRAM_ENDS = frozenset({2, 30, 99})
ARCS = (2.0, 3.0)
FEED_MOVES = (1.0, 2.0, 3.0)
