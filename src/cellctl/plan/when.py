"""Times and durations as a planner types them, resolved against the plan's start.

::

    parse_duration("8h")                     # 28800.0; also "90m", "1h30m", "2d", "1d 4h"
    resolve_when("FRI 18:00", start)         # the next Friday 18:00 after start (local time)
    resolve_when("18:00", start)             # the next 18:00 after start (today or tomorrow)
    resolve_when("2026-11-27T18:00", start)  # that date and time (local unless it says a zone)

Every function raises :class:`~cellctl.errors.UsageError` with the text it could not read;
times are unix seconds, read and written as local wall time.
"""

from __future__ import annotations

import math
import re
from datetime import datetime, timedelta
from typing import Final

from cellctl.errors import UsageError

#: The longest a plan may look ahead (and the latest a time may lie after its start): a month.
MAX_HORIZON_S: Final = 31 * 86400.0
#: The planned controller's poll period, s (the cell's own if that is longer): how often
#: it looks at idle machines. The looks are most of a plan's work (bench/plan_shift.py's
#: 8-hour shift: 11.7 s of CPU at 5 s, 5.3 s at 15 s), and they move little: a step's end
#: is seen by the step itself, and that shift's makespan moved 0.1 s from 5 s to 15 s; a
#: 2-part plan's finish times stay within seconds of the cell's own 0.5 s
#: (tests/test_plan_engine.py). A fault in a plan is noticed up to a poll period later.
#: ``--poll 0.5`` plays the cell's own rate, many times slower.
PLAN_POLL_S: Final = 15.0
#: The longest poll period a plan takes, s.
MAX_POLL_S: Final = 600.0
#: Day names a time may start with (three letters or the whole word, any case).
DAYS: Final = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
_FULL_DAYS: Final = ("monday", "tuesday", "wednesday", "thursday", "friday", "saturday", "sunday")

#: A duration's number: digits, and up to 6 decimals (a number of days or seconds alike).
_NUMBER = r"\d{1,12}(?:\.\d{1,6})?"
_DURATION = re.compile(
    rf"^\s*(?:(?P<d>{_NUMBER})\s*d)?\s*(?:(?P<h>{_NUMBER})\s*h)?"
    rf"\s*(?:(?P<m>{_NUMBER})\s*m(?:in)?)?\s*(?:(?P<s>{_NUMBER})\s*s)?\s*$",
    re.IGNORECASE,
)
_UNITS: Final = {"d": 86400.0, "h": 3600.0, "m": 60.0, "s": 1.0}
#: A duration as typed, piece by piece: what stands before a unit, and the unit's letters.
_PIECE = re.compile(r"\s*([^\sA-Za-z]*)\s*([A-Za-z]*)")
#: What to write, for the messages.
DURATION_FORMS: Final = "write a number and a unit, e.g. 8h, 90m, 1h30m, 2d"
#: ``[DAY ]HH:MM`` (``FRI 18:00``, ``friday 6:30``, ``18:00``).
_DAY_TIME = re.compile(r"^\s*(?:(?P<day>[A-Za-z]{3,9})\s+)?(?P<h>\d{1,2}):(?P<m>\d{2})\s*$")
#: What to write, for the messages.
WHEN_FORMS: Final = "HH:MM, DAY HH:MM (FRI 18:00) or a date and time (2026-11-27T18:00)"


def parse_duration(text: str) -> float:
    """``8h``, ``90m``, ``1h30m``, ``2d``, ``45s``, ``1d 4h`` -> seconds (more than 0, at
    most a month). Refused with what was typed, how to write one, and what is wrong in it
    (``duration '9999..h': write a number and a unit, e.g. ... ('9999..' is not a number)``)."""
    shown = _shown(text)
    found = _DURATION.match(text)
    if found is None or not any(found.groupdict().values()):
        raise UsageError(f"duration {shown}: {DURATION_FORMS}{_wrong_in(text)}")
    seconds = sum(float(v) * _UNITS[k] for k, v in found.groupdict().items() if v)
    if seconds <= 0:
        raise UsageError(f"duration {shown}: must be more than 0")
    if seconds > MAX_HORIZON_S:
        raise UsageError(f"duration {shown}: a plan looks at most 31 days ahead")
    return seconds


def _shown(text: str) -> str:
    """``text`` quoted for a message, at most 40 characters of it."""
    return repr(text) if len(text) <= 40 else repr(text[:40]) + "..."


def _wrong_in(text: str) -> str:
    """What is wrong in ``text``, which is no duration, in a few words and parentheses
    (empty if it is nothing at all)."""
    pieces = [(n, u) for n, u in _PIECE.findall(text[:200]) if n or u]
    for number, unit in pieces:
        if not number:
            return f" (no number before {unit[:20]})"
        if not re.fullmatch(_NUMBER, number):
            if re.fullmatch(r"\d+(?:\.\d+)?", number):
                return f" ({number[:20]}: too many digits)"
            return f" ({_shown(number)} is not a number)"
        if not unit:
            return f" (no unit after {number}: d, h, m or s)"
        if unit.lower() not in ("d", "h", "m", "min", "s"):
            return f" ({_shown(unit)} is no unit: d, h, m or s)"
    return " (each unit once, the largest first: 1d 4h, 1h30m)" if pieces else ""


def _day_index(name: str) -> int:
    low = name.lower()
    for i, (short, full) in enumerate(zip(DAYS, _FULL_DAYS, strict=True)):
        if low in (short, full):
            return i
    raise UsageError(f"{name!r} is not a day (MON TUE WED THU FRI SAT SUN)")


def _local(stamp: float) -> datetime:
    try:
        return datetime.fromtimestamp(stamp)
    except (OverflowError, OSError, ValueError):
        raise UsageError(f"time {stamp!r} is out of range") from None


def _stamp(moment: datetime, text: str) -> float:
    """The unix time of the local wall time ``moment``; one the clocks skip (spring
    forward: 02:30 when they go from 02:00 to 03:00) is the next that exists, the instant
    they go forward (03:00), never an hour later or a day (:func:`skipped`)."""
    try:
        stamp = moment.timestamp()
        if _local(stamp) == moment:
            return stamp
        # In the gap: fold=1 reads it with the offset after the change, fold=0 with the one
        # before; the change lies between. The first second whose wall time is not before
        # ``moment`` (wall time only grows over a spring forward).
        low, high = sorted((moment.replace(fold=1).timestamp(), stamp))
        low, high = math.floor(low), math.ceil(high)
        while low < high:
            mid = (low + high) // 2
            if _local(mid) < moment:
                low = mid + 1
            else:
                high = mid
        return float(low)
    except (OverflowError, OSError, ValueError):
        raise UsageError(f"time {text!r} is out of range") from None


def skipped(text: str, stamp: float) -> str:
    """What a message adds for ``text`` read as ``stamp``: if the clocks skipped the wall
    time it names (a spring forward: it was read as the next that exists), ``" (no 02:30
    that day: the clocks go forward)"``; else ""."""
    found = _DAY_TIME.match(text)
    if found is None:
        try:
            moment = datetime.fromisoformat(text.strip())
        except ValueError:
            return ""
        if moment.tzinfo is not None:
            return ""
        hour, minute = moment.hour, moment.minute
    else:
        hour, minute = int(found["h"]), int(found["m"])
    local = _local(stamp)
    if (local.hour, local.minute) == (hour, minute):
        return ""
    return f" (no {hour:02d}:{minute:02d} that day: the clocks go forward)"


def resolve_when(text: str, start: float, *, inclusive: bool = False, due: bool = False) -> float:
    """The time ``text`` names, seen from ``start`` (unix s): ``[DAY ]HH:MM`` is the next such
    local time after ``start`` (at or after it with ``inclusive``); a date and time is itself.
    Refused if it lies before ``start`` or more than :data:`MAX_HORIZON_S` after it, but for
    an order's ``due`` time: an order may be overdue already, or due past the plan's end."""
    if not isinstance(text, str) or not text.strip():
        raise UsageError(f"time {text!r}: write {WHEN_FORMS}")
    found = _DAY_TIME.match(text)
    if found is not None:
        hour, minute = int(found["h"]), int(found["m"])
        if hour > 23 or minute > 59:
            raise UsageError(f"time {text!r}: hours 0-23, minutes 0-59")
        origin = _local(start)
        moment = origin.replace(hour=hour, minute=minute, second=0, microsecond=0)
        if found["day"]:
            moment += timedelta(days=(_day_index(found["day"]) - origin.weekday()) % 7)
            step = timedelta(days=7)
        else:
            step = timedelta(days=1)
        if moment < origin or (moment == origin and not inclusive):
            moment += step
        stamp = _stamp(moment, text)
    else:
        try:
            moment = datetime.fromisoformat(text.strip())
        except ValueError:
            raise UsageError(f"time {text!r}: write {WHEN_FORMS}") from None
        if moment.tzinfo is not None:
            moment = moment.astimezone().replace(tzinfo=None)
        stamp = _stamp(moment, text)
        if due:
            return stamp
        if stamp < start or (stamp == start and not inclusive):
            raise UsageError(f"time {text!r} is not after the plan's start ({when_text(start)})")
    if stamp - start > MAX_HORIZON_S and not due:
        raise UsageError(f"time {text!r}: a plan looks at most 31 days ahead of its start")
    return stamp


def parse_start(text: str | None, now: float) -> float:
    """``--start``: ``None`` or ``now`` is ``now``; else a time as :func:`resolve_when` reads
    it, at or after ``now`` (a date and time may also lie in the past: a plan from then)."""
    if text is None or text.strip().lower() == "now":
        return now
    if _DAY_TIME.match(text) is not None:
        return resolve_when(text, now, inclusive=True)
    try:
        moment = datetime.fromisoformat(text.strip())
    except ValueError:
        raise UsageError(f"start {text!r}: write now, {WHEN_FORMS}") from None
    if moment.tzinfo is not None:
        moment = moment.astimezone().replace(tzinfo=None)
    if not 1971 <= moment.year <= 9998:
        raise UsageError(f"start {text!r} is out of range")
    return _stamp(moment, text)


def when_text(stamp: float, *, date: bool = False, day: bool = False) -> str:
    """A time as the report prints it, to the nearest second (as :func:`span_text` rounds):
    ``Fri 18:00:00``; ``day``: with the day of the month (``Fri 04 18:00:00``: a plan of a
    week or more has each weekday twice); ``date``: with the whole date."""
    moment = _local(round(stamp))
    fmt = "%a %Y-%m-%d %H:%M:%S" if date else "%a %d %H:%M:%S" if day else "%a %H:%M:%S"
    return moment.strftime(fmt)


def span_text(seconds: float) -> str:
    """A span as the report prints it: ``2:05:09``, ``1 d 2:05:09``, ``12.3 s``."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    s = round(seconds)
    days, s = divmod(s, 86400)
    clock = f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
    return f"{days} d {clock}" if days else clock


def late_text(seconds: float) -> str:
    """How late an order is, as the plan's table says it: always ``H:MM:SS`` (``0:00:42``,
    ``1:00:00``, ``1 d 2:05:09``), whole seconds rounded up: late at all is never "0"."""
    s = max(1, math.ceil(seconds - 1e-6))
    days, s = divmod(s, 86400)
    clock = f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
    return f"{days} d {clock}" if days else clock


def parse_poll(given: object) -> float:
    """A plan's poll period in seconds, as typed (``"0.5"``) or given (``5.0``): more than 0
    and at most :data:`MAX_POLL_S` (UsageError in words otherwise; anything but a number or
    its text, a list or ``true`` as an API peer may send, is refused by its type)."""
    if isinstance(given, int | float | str) and not isinstance(given, bool):
        try:
            seconds = float(given)
        except (ValueError, OverflowError):  # not a number; an integer past any float
            seconds = float("nan")
        # The text shown is bounded: what a peer sent may be megabytes long (an integer of
        # thousands of digits has no text at all).
        if isinstance(given, int) and given.bit_length() > 128:
            shown = "(a number of more than 38 digits)"
        else:
            text = str(given)
            shown = repr(given) if len(text) <= 40 else repr(text[:40]) + "..."
    else:
        # Never its repr: a list nested thousands deep has none (RecursionError).
        words = {bool: "true or false", list: "a list", dict: "an object", type(None): "null"}
        shown, seconds = f"({words.get(type(given), type(given).__name__)})", float("nan")
    if not 0 < seconds <= MAX_POLL_S:  # NaN fails it too
        raise UsageError(f"poll {shown}: seconds, more than 0 and at most {MAX_POLL_S:g}")
    return seconds
