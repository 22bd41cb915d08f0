"""The shop directory: one directory per machine, what it may read and what it punched::

    SHOP/
      dnc.toml                      the machines (see :mod:`.config`)
      mill1/
        programs/O1234.nc           programs the control may ask for (the file name starts
                                    with its O-number; any ending; O1234.nc, named by the
                                    number alone, wins over "O1234 bracket.nc"; two files
                                    otherwise are refused as ambiguous)
        received/O1234_20261125T205811Z.nc
                                    every program the control punched, with its UTC time;
                                    never overwritten: a second one of that second gets _2
        sent/O1234_20261125T210000Z.nc
                                    an exact copy of every program sent (what diff compares)
        log                         one line per transfer: time, what, program, characters

::

    store = ShopStore(Path("SHOP"))
    path = store.program("mill1", 1234)              # programs/O1234.nc (or the one O1234*),
                                                     # UsageError if none, or if ambiguous
    kept = store.keep_received("mill1", 1234, text)  # received/O1234_<time>.nc (0600)
    store.log("mill1", "received O1234 (58 chars)")

Files are written 0600 under directories 0700 (programs of a shop are its own). A program is
written to a temporary name and linked into place, so a reader never sees half a file and an
existing one is never replaced.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.files import read_file, reason
from cellctl.kinds.iso_cnc.options import DRIP_MAX_BYTES, read_capped
from cellctl.kinds.iso_cnc.tape import not_iso_code, o_number, skipped_leader, unframe

PROGRAMS = "programs"
RECEIVED = "received"
SENT = "sent"
LOG = "log"
#: A machine's name is a directory's: letters, digits, ``_ . -``, not starting with a dot.
MACHINE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
#: A program file in ``programs/``: its name starts with the O-number (``O1234``, ``O1234.nc``,
#: ``O1234 bracket.nc``); ``:`` is Fanuc's other way of writing O, not usable in a file name.
PROGRAM_FILE = re.compile(r"[Oo](\d{1,8})(?:$|[^0-9])")
#: A program file named by its O-number alone (``O1234.nc``, ``O1234``): it wins over the
#: others of that number (``O1234 bracket.nc``); two such files are refused as ambiguous.
EXACT_PROGRAM_FILE = re.compile(r"[Oo]\d{1,8}(?:\.[^.]*)?")
#: A kept copy's name: ``O1234_20261125T205811Z`` and ``_2`` ... when that second is taken.
KEPT_FILE = re.compile(r"O(\d{1,8})_(\d{8}T\d{6}Z)(?:_(\d+))?\.nc")
#: The largest program file read: what cellctl drip-feeds at most (a drip-feed streams).
MAX_PROGRAM_BYTES = DRIP_MAX_BYTES
#: Copies of one time stamp tried before giving up (a control punching 1000 programs a second).
MAX_SAME_SECOND = 1000


def check_machine_name(name: str) -> str:
    """``name`` if it can be a machine's directory; UsageError saying why not."""
    if not MACHINE_NAME.fullmatch(name):
        raise UsageError(
            f"machine name {name!r} cannot be a directory name: use letters, digits, _ . - "
            "(at most 64, not starting with a dot)"
        )
    return name


def o_name(number: int) -> str:
    """A program number as the control writes it: at least 4 digits (``O0012``)."""
    return f"O{number:04d}"


def as_given(number: int, given: str = "") -> str:
    """Program ``number`` as the user wrote it (``O1`` for ``O1``, ``1`` or ``:1``), never
    padded into a number they did not write (``O0001``); without ``given``, ``O1``."""
    digits = given.strip().lstrip("Oo:")
    return f"O{digits}" if digits.isdigit() else f"O{number}"


def check_program_range(machine: str, number: int, digits: int, given: str = "") -> None:
    """Refuse (UsageError) program ``number`` when machine's control, whose O-numbers
    have ``digits`` digits, cannot hold it: O0 (no control numbers a program 0), or O99999
    on a 4-digit control. Said before the file is looked for: a file of that number would be
    refused too. ``given``: the number as the user wrote it (``O0``, ``0``), said back so,
    never padded into a number they did not write (``O0000``)."""
    high = 10**digits - 1
    if not 1 <= number <= high:
        shown = as_given(number, given)
        raise UsageError(
            f"{shown} is out of range for {machine}: its control takes programs "
            f"O1 to O{high} ({digits} digits, options.o_digits)"
        )


@dataclass(frozen=True)
class Kept:
    """A kept copy of a program (received or sent): its file, number and UTC time stamp."""

    path: Path
    number: int
    stamp: str
    """``20261125T205811Z`` (then ``_2`` ... in the file name when one second had several)."""
    serial: int


def _stamp(now: float) -> str:
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now))


def _private_dir(path: Path) -> Path:
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"cannot create {path}: {e.strerror}") from None
    if not path.is_dir():
        raise UsageError(f"{path} should be a directory and is not one")
    return path


def write_new(path: Path, data: bytes) -> bool:
    """Write ``data`` to ``path`` (0600) if no file has that name; False if one has.

    Written under a temporary name, then hard-linked into place: the link fails on an
    existing name, so nothing is ever overwritten and nobody reads half a file.
    """
    temp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(temp, path)
        except FileExistsError:
            return False
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temp)


class ShopStore:
    """The shop directory (see module docstring)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def machine(self, name: str) -> Path:
        """``SHOP/<name>``, created (with programs/, received/, sent/) if missing."""
        base = _private_dir(self.root / check_machine_name(name))
        for sub in (PROGRAMS, RECEIVED, SENT):
            _private_dir(base / sub)
        return base

    def folder(self, name: str, sub: str) -> Path:
        """``SHOP/<name>/<sub>`` for a read: nothing is created (a read of a machine that
        has none yet finds nothing)."""
        return self.root / check_machine_name(name) / sub

    def _listing(self, name: str, sub: str) -> list[Path]:
        try:
            return sorted(self.folder(name, sub).iterdir())
        except (FileNotFoundError, NotADirectoryError):
            return []
        except OSError as e:
            raise UsageError(f"cannot read {self.folder(name, sub)}: {e.strerror}") from None

    # -- programs the control may read -------------------------------------------------------

    def programs(self, name: str) -> dict[int, list[Path]]:
        """The machine's program files by O-number, each number's files in name order."""
        found: dict[int, list[Path]] = {}
        for path in self._listing(name, PROGRAMS):
            match = PROGRAM_FILE.match(path.name)
            if match and path.is_file():
                found.setdefault(int(match.group(1)), []).append(path)
        return found

    def program(self, name: str, number: int, digits: int | None = None, given: str = "") -> Path:
        """The file of program ``number`` in the machine's programs/: the one named exactly
        by its number (``O1234.nc``, ``O1234``) if there is one, else the only file whose name
        starts with it (``O1234 bracket.nc``). UsageError naming where it was looked for when
        there is none, and naming the files when more than one could be meant (``O1234
        bracket.nc`` and ``O1234 copy.nc``; ``O1234.nc`` and ``O1234.tap``): which one the
        control should get cannot be guessed. With ``digits`` (the control's ``o_digits``),
        a number the control cannot hold is refused first (:func:`check_program_range`,
        ``given`` the number as the user wrote it)."""
        if digits is not None:
            check_program_range(name, number, digits, given)
        files = self.programs(name).get(number, [])
        exact = [path for path in files if EXACT_PROGRAM_FILE.fullmatch(path.name)]
        chosen = exact or files
        if len(chosen) == 1:
            return chosen[0]
        where = self.folder(name, PROGRAMS)
        said = as_given(number, given)
        if not chosen:
            raise UsageError(f"no program {said} in {where} (a file named {said}.nc)")
        names = ", ".join(repr(path.name) for path in chosen)
        # Several named by the number alone (O1234.nc and O1234.tap), or none and several
        # that start with it: which one is meant cannot be guessed either way.
        why = "are each named by it alone" if exact else f"start with it and none is {said}.nc"
        raise UsageError(
            f"{said} is ambiguous in {where}: {len(chosen)} files could be it "
            f"({names}) and they {why}: rename all but one, or give the file itself"
        )

    def resolve(
        self, name: str, program: str, digits: int | None = None, *, shop_only: bool = False
    ) -> Path:
        """What ``cellctl dnc send MACHINE PROGRAM`` means by PROGRAM: an existing file, else
        an O-number (``O1234`` or ``1234``) in the machine's programs/ (within ``digits``,
        the control's ``o_digits``, when given). ``shop_only`` (a program named through the
        server's API, by a client that may not see this host's files): a file only in a
        machine's programs/, received/ or sent/ under the shop (``..`` and symlinks
        followed), anything else refused unread: the shop's tokens and state are no program."""
        path = Path(program)
        if path.is_file():
            if shop_only and not self.a_program_file(path):
                raise UsageError(
                    f"{program}: not in the shop's programs ({self.root}/MACHINE/{PROGRAMS}, "
                    f"{RECEIVED} or {SENT}): name a program of the machine's {PROGRAMS}/ "
                    "(like O1234), or send the file's text"
                )
            return path
        match = re.fullmatch(r"[Oo]?(\d{1,8})", program)
        if match is None:
            raise UsageError(f"{program}: {_no_program_file(path)}")
        return self.program(name, int(match.group(1)), digits, program)

    def a_program_file(self, path: Path) -> bool:
        """True if ``path`` (links followed) lies in a machine's programs/, received/ or
        sent/ folder of this shop."""
        try:
            parts = path.resolve().relative_to(self.root.resolve()).parts
        except ValueError:
            return False
        return len(parts) >= 3 and parts[1] in (PROGRAMS, RECEIVED, SENT)

    # -- kept copies ------------------------------------------------------------------------

    def _keep(self, name: str, sub: str, number: int, data: bytes, now: float | None) -> Kept:
        folder = self.machine(name) / sub
        stamp = _stamp(current_clock().now() if now is None else now)
        for serial in range(1, MAX_SAME_SECOND + 1):
            suffix = "" if serial == 1 else f"_{serial}"
            path = folder / f"O{number:04d}_{stamp}{suffix}.nc"
            if write_new(path, data):
                return Kept(path, number, stamp, serial)
        raise UsageError(f"{folder}: {MAX_SAME_SECOND} copies of {o_name(number)} at {stamp}")

    def keep_received(self, name: str, number: int, data: bytes, now: float | None = None) -> Kept:
        """Keep a punched program beside the older ones (never replacing one)."""
        return self._keep(name, RECEIVED, number, data, now)

    def keep_sent(self, name: str, number: int, data: bytes, now: float | None = None) -> Kept:
        """Keep an exact copy of a program sent (what ``dnc diff`` compares with)."""
        return self._keep(name, SENT, number, data, now)

    def _kept(self, name: str, sub: str, number: int | None) -> list[Kept]:
        out = []
        for path in self._listing(name, sub):
            match = KEPT_FILE.fullmatch(path.name)
            if match is None or (number is not None and int(match.group(1)) != number):
                continue
            out.append(Kept(path, int(match.group(1)), match.group(2), int(match.group(3) or 1)))
        return sorted(out, key=lambda k: (k.stamp, k.serial, k.number))

    def received(self, name: str, number: int | None = None) -> list[Kept]:
        """The received copies (of program ``number``), oldest first."""
        return self._kept(name, RECEIVED, number)

    def sent(self, name: str, number: int | None = None) -> list[Kept]:
        """The sent copies (of program ``number``), oldest first."""
        return self._kept(name, SENT, number)

    # -- the log ----------------------------------------------------------------------------

    def log(self, name: str, text: str, now: float | None = None) -> None:
        """Add a line to ``SHOP/<name>/log``: UTC time, then ``text`` (one line)."""
        when = time.strftime(
            "%Y-%m-%dT%H:%M:%SZ", time.gmtime(current_clock().now() if now is None else now)
        )
        line = f"{when} {' '.join(text.split())}\n"
        path = self.machine(name) / LOG
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW, 0o600)
        except OSError as e:  # a link put in its place is never followed
            raise UsageError(f"cannot write the log {path}: {e.strerror}") from None
        with os.fdopen(fd, "a", encoding="utf-8") as f:
            f.write(line)

    def log_lines(self, name: str, last: int = 50) -> list[str]:
        """The last ``last`` lines of the machine's log."""
        try:
            text = self.folder(name, LOG).read_text(encoding="utf-8", errors="replace")
        except (FileNotFoundError, NotADirectoryError):
            return []
        except OSError as e:
            raise UsageError(
                f"cannot read the log {self.folder(name, LOG)}: {e.strerror}"
            ) from None
        return text.splitlines()[-last:]


def _no_program_file(path: Path) -> str:
    """Why ``path`` (no regular file, not an O-number) is no program: nothing is there, or
    what it is (a directory, a device) in the words of every reader of a file (read_file
    refuses it by its type, before opening it)."""
    if not path.exists():
        return "no such file, and not a program number like O1234"
    try:
        read_file(path, limit=0)
    except OSError as e:
        return reason(e)
    return "not a regular file"  # it turned into one meanwhile: a race, said as it was


def read_program_file(path: Path) -> bytes:
    """A program file's bytes; UsageError (before any byte goes out) when it cannot be read,
    is too large or is not text."""
    try:
        data = read_capped(path, MAX_PROGRAM_BYTES)
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file") from None
    except OSError as e:
        if e.errno == errno.EFBIG:
            raise UsageError(
                f"{path}: more than {MAX_PROGRAM_BYTES} bytes, the most cellctl sends (its "
                "cap, not the control's)"
            ) from None
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None
    refusal = not_iso_code(str(path), data)
    if refusal is not None:
        raise UsageError(refusal)
    return data


def program_chars(data: bytes) -> int:
    """The characters of a program file that the control stores: its blocks, each ended by
    LF, without ``%`` framing, leader, CR or NUL (what ``dnc check`` and a read-in's message
    count as the program; its tape on the line has the leader, ``%`` and trailer too)."""
    return len(unframe(data))


def check_program_number(name: str, data: bytes) -> None:
    """Refuse (UsageError, before a byte goes out) a program file whose name says one
    O-number and whose text another (``O1234.nc`` holding ``O1001``): the control would
    store it as O1001, over whatever O1001 it has, while the log and a request say O1234.
    Refused too: text above the tape's opening ``%`` (a stray ``%`` mid-file), which the
    control would skip, sending the rest alone."""
    skipped = skipped_leader(data)
    if skipped is not None:
        line, text = skipped
        raise UsageError(
            f"{name}: line {line}: {text[:40]!r} comes before the tape's opening %, and the "
            "control skips all of it as leader: remove that % or what is above it"
        )
    named = PROGRAM_FILE.match(Path(name).name)
    if named is None:
        return  # a file not named by its number (surface.nc): its text decides
    said = o_number(unframe(data))
    if said is not None and said != int(named.group(1)):
        raise UsageError(  # the name's number as written in it (O0, never O0000)
            f"{name}: its name says O{named.group(1)} but its text is "
            f"{o_name(said)} (the control would store it as {o_name(said)}): rename the file "
            "or correct its O block"
        )
