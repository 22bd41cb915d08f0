"""The systemd unit that runs a cell's controller as a service (``cellctl service install``).

::

    unit = ServiceUnit.for_cell(Path("/srv/lab"), user=None)   # user: the directory's owner
    unit.name                 # "cellctl-lab.service"
    unit.text()               # the unit file: restart on failure, the cell's user, hardening
    parse_unit(unit.text())   # {"Service": {"User": ["cell"], ...}, ...}

The controller runs as the cell's user, with the filesystem read-only but for the cell
directory (``ProtectSystem=strict``, ``ReadWritePaths=``), no new privileges, a private /tmp,
and of the devices only serial ports (``DeviceAllow=``, group ``dialout``). Paths go into the
unit as they are: one that would need quoting there (a space, a quote, ``%``, ``$``, a control
character) is refused, so no value can add a line or a word to the unit.
"""

from __future__ import annotations

import grp
import os
import pwd
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from cellctl.cell.config import load_cell
from cellctl.errors import UsageError

#: Where root installs the unit when no --output is given.
SYSTEM_UNIT_DIR = Path("/etc/systemd/system")
#: The group that owns serial ports on Debian and its kin.
SERIAL_GROUP = "dialout"
#: Device classes the controller may open (/proc/devices names): serial ports on the board, on
#: USB and USB CDC-ACM; ``pts`` for an emulated robot's pty (``cellctl emulate cell``).
SERIAL_DEVICES = ("char-ttyS", "char-ttyUSB", "char-ttyACM", "char-pts")
#: Trees ``ProtectHome=`` hides; a cell or a cellctl inside one makes it read-only instead.
HOME_TREES = (Path("/home"), Path("/root"), Path("/run/user"))
#: Trees ``PrivateTmp=`` replaces with the service's own.
TMP_TREES = (Path("/tmp"), Path("/var/tmp"))
#: Characters a path may have in the unit as it is (nothing systemd unquotes or expands).
PLAIN_PATH = re.compile(r"/[A-Za-z0-9_./:@+,=~-]*")
#: How long the controller has after SIGTERM: it lets the steps in flight finish first.
STOP_TIMEOUT_S = 120


def _plain(path: Path, what: str) -> str:
    text = str(path)
    if not PLAIN_PATH.fullmatch(text):
        raise UsageError(
            f"{what} {text!r}: a systemd unit here takes absolute paths of letters, digits and "
            "_ . / : @ + , = ~ - only (no spaces, quotes, % or $): move the directory, or link "
            "it from such a path"
        )
    return text


def _description(name: str) -> str:
    """``name`` as a one-line Description (control characters out, ``%`` not a specifier)."""
    flat = "".join(c if c.isprintable() else " " for c in name).strip()
    return " ".join(flat.split()).replace("%", "%%")


def unit_name(cell: Path) -> str:
    """``cellctl-<directory name>.service``, with what a unit name cannot hold as ``-``."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", cell.name).strip("-.") or "cell"
    return f"cellctl-{slug}.service"


def _under_home(path: Path) -> bool:
    return any(path.is_relative_to(tree) for tree in HOME_TREES)


def _under_tmp(path: Path) -> bool:
    return any(path.is_relative_to(tree) for tree in TMP_TREES)


@dataclass(frozen=True)
class ServiceUnit:
    """The unit of one cell; :meth:`for_cell` checks and fills it from the cell directory."""

    cell: Path
    cell_name: str
    user: str
    executable: Path
    name: str
    serial_group: str | None = SERIAL_GROUP

    def __post_init__(self) -> None:
        _plain(self.cell, "cell directory")
        _plain(self.executable, "cellctl")
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.-]*", self.user):
            raise UsageError(f"user {self.user!r}: not a user name systemd takes")
        if not re.fullmatch(r"[A-Za-z0-9_.:-]+\.service", self.name):
            raise UsageError(
                f"unit name {self.name!r}: letters, digits and _ . : -, ending in .service"
            )

    @classmethod
    def for_cell(
        cls,
        cell: Path,
        *,
        user: str | None = None,
        executable: Path | None = None,
        name: str | None = None,
    ) -> ServiceUnit:
        """The unit for the cell in ``cell`` (checked: cell.toml and every program in it).

        ``user``: who runs the controller (default: the directory's owner; root only when
        given); ``executable``: cellctl (default: the one beside the running Python);
        ``name``: the unit's (default: :func:`unit_name`)."""
        cell = cell.absolute()
        config = load_cell(cell)
        if user is None:
            user = _owner(cell)
            if user == "root":
                raise UsageError(
                    f"{cell} belongs to root: give --user NAME, the user the controller runs as "
                    "(the owner of the cell directory; --user root only if you mean it)"
                )
        else:
            try:
                pwd.getpwnam(user)
            except KeyError:
                raise UsageError(f"no user {user!r} on this machine") from None
        group = SERIAL_GROUP if _group_exists(SERIAL_GROUP) else None
        exe = executable or installed_cellctl()
        return cls(cell, config.name, user, exe, name or unit_name(cell), group)

    def text(self) -> str:
        """The unit file."""
        cell = str(self.cell)
        home = "read-only" if _under_home(self.cell) or _under_home(self.executable) else "yes"
        lines = [
            "# Written by `cellctl service install`. To start it now and at every boot:",
            f"#   systemctl daemon-reload && systemctl enable --now {self.name}",
            "[Unit]",
            f"Description=cellctl: the controller of {_description(self.cell_name)} ({cell})",
            # The PLC and the mills' serial device servers are on the network.
            "After=network-online.target",
            "Wants=network-online.target",
            "",
            "[Service]",
            "Type=exec",
            f"User={self.user}",
            f"WorkingDirectory={cell}",
            f"ExecStart={self.executable} --cell {cell} run --no-live",
            "Environment=PYTHONUNBUFFERED=1",
            "Restart=on-failure",
            "RestartSec=5",
            f"TimeoutStopSec={STOP_TIMEOUT_S}",
            "UMask=0077",
            "NoNewPrivileges=yes",
            "ProtectSystem=strict",
            f"ReadWritePaths={cell}",
            # The link locks, shared with the user's shells ("-": none if it is missing).
            "ReadWritePaths=-/run/lock",
            f"ProtectHome={home}",
            "PrivateTmp=yes",
            # A cell under /tmp would be hidden by the private one: bound into it (as is).
            *([f"BindPaths={cell}"] if _under_tmp(self.cell) else []),
            "DevicePolicy=closed",
            *(f"DeviceAllow={device} rw" for device in SERIAL_DEVICES),
            *([f"SupplementaryGroups={self.serial_group}"] if self.serial_group else []),
            "CapabilityBoundingSet=",
            "ProtectKernelTunables=yes",
            "ProtectKernelModules=yes",
            "ProtectKernelLogs=yes",
            "ProtectControlGroups=yes",
            "ProtectClock=yes",
            "ProtectHostname=yes",
            "RestrictNamespaces=yes",
            "RestrictRealtime=yes",
            "RestrictSUIDSGID=yes",
            "LockPersonality=yes",
            "SystemCallArchitectures=native",
            "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK",
            "",
            "[Install]",
            "WantedBy=multi-user.target",
        ]
        return "\n".join(lines) + "\n"


def installed_cellctl() -> Path:
    """The cellctl script beside the running Python (a venv's, pipx's), else on PATH."""
    beside = Path(sys.executable).parent / "cellctl"
    if beside.is_file():
        return beside.absolute()
    import shutil

    found = shutil.which("cellctl")
    if found is None:
        raise UsageError("no cellctl script beside this Python or on PATH: install cellctl")
    return Path(found).absolute()


def _owner(path: Path) -> str:
    uid = path.stat().st_uid
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        raise UsageError(f"{path} belongs to uid {uid}, who has no name: give --user") from None


def _group_exists(name: str) -> bool:
    try:
        grp.getgrnam(name)
    except KeyError:
        return False
    return True


def unit_target(name: str, *, output: Path | None, euid: int | None = None) -> Path:
    """Where ``service install`` writes: ``output``, or the system's unit directory as root."""
    if output is not None:
        return output
    if (os.geteuid() if euid is None else euid) != 0:
        raise UsageError(
            f"only root writes {SYSTEM_UNIT_DIR / name}: give --output FILE or --print "
            "(and copy it there as root)"
        )
    return SYSTEM_UNIT_DIR / name


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """A unit file's sections, each key's values in order (a key may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    pending = ""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = pending + raw.strip()
        pending = ""
        if not line or line[0] in "#;":
            continue
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        key, sep, value = line.partition("=")
        if not sep or current is None:
            raise UsageError(f"unit line {number}: {raw!r} is not KEY=VALUE in a [section]")
        current.setdefault(key.strip(), []).append(value.strip())
    return sections
