"""The "one clock" rule as a ratchet: no new direct reading of time in src/cellctl.

Time is read and waited on through :mod:`cellctl.clock` (docs/clock.md). A direct call
(``time.time()``, ``time.monotonic()``, ``time.sleep()``, ``asyncio.sleep()``, ``loop.time()``,
``get_running_loop().time()``, ``datetime.now()`` ...) is counted per file, and no file may
have more than ``tests/direct_time_allowlist.txt`` allows: the count each file had when the
clock came. The list only shrinks: a file that needs fewer lowers its entry (the second test
says so). Every module takes its clock now; what is left is an exception with its reason.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src" / "cellctl"
ALLOWLIST = Path(__file__).resolve().parent / "direct_time_allowlist.txt"
#: The one module that reads the real clock: the clock itself.
EXEMPT = {"src/cellctl/clock.py"}

#: time.<name>(...) calls that read or wait on the real clock.
TIME_CALLS = {
    "time",
    "time_ns",
    "monotonic",
    "monotonic_ns",
    "perf_counter",
    "perf_counter_ns",
    "sleep",
    "localtime",
    "gmtime",
    "ctime",
    "strftime",
}
#: datetime.<name>() / date.<name>() calls that read the wall clock.
DATETIME_CALLS = {"now", "utcnow", "today"}


def _name_of(node: ast.expr) -> str:
    """The last name of ``a.b.c`` (``c``), of ``f()`` (``f``); "" otherwise."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Call):
        return _name_of(node.func)
    return ""


def _reads_time(call: ast.Call) -> str | None:
    """What ``call`` reads, if it is a direct reading of time (else None)."""
    func = call.func
    if isinstance(func, ast.Name):
        return None
    if not isinstance(func, ast.Attribute):
        return None
    owner = _name_of(func.value)
    attr = func.attr
    if isinstance(func.value, ast.Name) and owner == "time" and attr in TIME_CALLS:
        # time.strftime(fmt, t) / time.localtime(t) format a given time: only their
        # argument-less forms read the clock.
        if attr in ("localtime", "gmtime", "ctime") and call.args:
            return None
        if attr == "strftime" and len(call.args) > 1:
            return None
        return f"time.{attr}"
    if owner == "asyncio" and attr == "sleep":
        return "asyncio.sleep"
    if (
        attr == "time"
        and not call.args
        and (owner.endswith("loop") or owner in ("get_running_loop", "get_event_loop"))
    ):
        return f"{owner}.time"
    if attr in DATETIME_CALLS and owner in ("datetime", "date"):
        return f"{owner}.{attr}"
    return None


def _imported_clock_names(tree: ast.Module) -> int:
    """``from time import monotonic`` and the like: a direct reading in another spelling."""
    count = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "time":
            count += sum(1 for alias in node.names if alias.name in TIME_CALLS)
    return count


def _taken_uncalled(tree: ast.Module) -> list[tuple[int, str]]:
    """``f = loop.time`` or ``clock=time.monotonic``: a reading of time taken as a value, to
    be called elsewhere (another spelling of a direct reading)."""
    called = {id(node.func) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or id(node) in called:
            continue
        owner = _name_of(node.value)
        if isinstance(node.value, ast.Name) and owner == "time" and node.attr in TIME_CALLS:
            found.append((node.lineno, f"time.{node.attr} (uncalled)"))
        elif node.attr == "time" and owner.endswith("loop"):
            found.append((node.lineno, f"{owner}.time (uncalled)"))
    return found


def direct_time(path: Path) -> list[tuple[int, str]]:
    """(line, what) of every direct reading of time in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found = [
        (node.lineno, what)
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and (what := _reads_time(node)) is not None
    ]
    found += _taken_uncalled(tree)
    found += [(0, "from time import ...")] * _imported_clock_names(tree)
    return sorted(found)


@functools.cache
def scan() -> dict[str, list[tuple[int, str]]]:
    """Every file of src/cellctl with a direct reading of time, by repository path (read once
    per process: two tests ask)."""
    result: dict[str, list[tuple[int, str]]] = {}
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel in EXEMPT:
            continue
        found = direct_time(path)
        if found:
            result[rel] = found
    return result


def allowlist() -> dict[str, int]:
    """``path count`` per line; ``#`` comments and blank lines ignored."""
    allowed: dict[str, int] = {}
    for number, raw in enumerate(ALLOWLIST.read_text(encoding="utf-8").splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        path, _, count = line.rpartition(" ")
        assert path and count.isdecimal(), f"{ALLOWLIST.name}:{number}: write PATH COUNT"
        assert path.strip() not in allowed, f"{ALLOWLIST.name}:{number}: {path} twice"
        allowed[path.strip()] = int(count)
    return allowed


def test_no_file_reads_time_more_often_than_the_allowlist_allows() -> None:
    allowed = allowlist()
    over = []
    for path, found in scan().items():
        limit = allowed.get(path, 0)
        if len(found) > limit:
            where = ", ".join(f"{what} at line {line}" for line, what in found)
            over.append(f"{path}: {len(found)} direct readings of time, {limit} allowed ({where})")
    assert not over, (
        "read the time through a Clock, not directly (docs/clock.md): clock = current_clock() "
        "(cellctl.clock) or one handed in, then clock.monotonic(), clock.now(), "
        "await clock.sleep(s), async with clock.timeout(s), clock.call_at(when, ...):\n"
        + "\n".join(over)
    )


def test_the_allowlist_only_shrinks() -> None:
    found = {path: len(hits) for path, hits in scan().items()}
    loose = [
        f"{path} {found.get(path, 0)}   (the list says {count})"
        for path, count in sorted(allowlist().items())
        if found.get(path, 0) < count
    ]
    assert not loose, (
        f"these files read the time directly less often now: lower (or remove, at 0) their "
        f"entries in tests/{ALLOWLIST.name} so that the count cannot creep back:\n"
        + "\n".join(loose)
    )


def test_every_exception_says_why() -> None:
    # Every module takes its clock now: what is left on the list is an exception, with its
    # reason beside it (``PATH COUNT  # why``).
    bare = [
        raw
        for raw in ALLOWLIST.read_text(encoding="utf-8").splitlines()
        if raw.strip() and not raw.lstrip().startswith("#") and not raw.partition("#")[2].strip()
    ]
    assert not bare, f"say why beside each entry of {ALLOWLIST.name}: " + "; ".join(bare)


def test_the_scan_sees_every_spelling() -> None:
    # The scan itself, on a sample of each spelling (and of what it must leave alone).
    sample = ast.parse(
        "import asyncio, time\n"
        "from time import monotonic\n"
        "time.time(); time.monotonic(); time.sleep(1); asyncio.sleep(1)\n"
        "loop.time(); self._loop.time(); asyncio.get_running_loop().time()\n"
        "datetime.now(); datetime.datetime.now(tz); dt.date.today()\n"
        "time.strftime('%H'); time.localtime()\n"
        "time.strftime('%H', t); time.localtime(t); clock.monotonic(); self.time()\n"
    )
    hits = [
        what
        for node in ast.walk(sample)
        if isinstance(node, ast.Call) and (what := _reads_time(node)) is not None
    ]
    assert sorted(hits) == sorted(
        [
            "time.time",
            "time.monotonic",
            "time.sleep",
            "asyncio.sleep",
            "loop.time",
            "_loop.time",
            "get_running_loop.time",
            "datetime.now",
            "datetime.now",
            "date.today",
            "time.strftime",
            "time.localtime",
        ]
    )
    assert _imported_clock_names(sample) == 1
    # Taken as a value, to be called elsewhere: read too; called, or a clock's, left alone.
    taken = ast.parse(
        "now = self.link._loop.time\nClock(monotonic=time.monotonic)\n"
        "t = loop.time(); f = clock.monotonic; g = self.time; time.time()\n"
    )
    assert sorted(what for _, what in _taken_uncalled(taken)) == [
        "_loop.time (uncalled)",
        "time.monotonic (uncalled)",
    ]
