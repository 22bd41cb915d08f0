"""What the UR's declaration needs without its driver: its options (``cell.toml``) and its
line (the registry reads these at start; the driver is imported when a robot is opened)."""

from __future__ import annotations

import shlex
from typing import Literal
from urllib.parse import parse_qsl, urlsplit

from pydantic import BaseModel, ConfigDict, Field

from cellctl.errors import UsageError

#: The line a UR's links are described with (TCP: its settings pace nothing).
UR_LINE = "115200,8N1"

#: The link schemes a UR's Dashboard Server is reached by: TCP, or an emulator in the same
#: event loop (a plan's cell).
UR_SCHEMES = ("socket", "mem")


def interface_url(dashboard_url: str, interface: str, port: int) -> str:
    """Where the UR's ``interface`` (``rtde``, ``secondary``) is, beside its Dashboard Server
    at ``dashboard_url``: the same host at ``port``, or for ``mem://NAME`` (an emulator in
    the same event loop) ``mem://NAME.interface``."""
    parts = urlsplit(dashboard_url)
    if parts.scheme == "mem":
        return f"mem://{mem_interface(parts.netloc, interface)}"
    return f"socket://{parts.hostname or '127.0.0.1'}:{port}"


#: The UR's interfaces beside its Dashboard Server, as people name them, by option.
INTERFACE_PORTS = {"rtde_port": "RTDE", "secondary_port": "secondary interface"}


def link_ports(url: str) -> tuple[str, dict[str, int]]:
    """The Dashboard Server's URL without its query, and the interface ports the query
    gives: ``socket://HOST:17120?rtde_port=17121&secondary_port=17122`` (how ``--link``
    reaches a UR whose RTDE and secondary interface are not at 30004 and 30002).

    UsageError, before anything opens, for a key that is no port option, a port that is
    no number 1-65535, a key given twice, or a query on ``mem://``."""
    parts = urlsplit(url)
    if not parts.query:
        return url, {}
    if parts.scheme == "mem":
        raise UsageError(f"{url}: a mem:// UR takes no ports (its interfaces are beside it)")
    ports: dict[str, int] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key not in INTERFACE_PORTS:
            raise UsageError(
                f"{url}: {key!r} is not a UR link setting "
                f"(the link URL takes {' and '.join(f'{k}=PORT' for k in INTERFACE_PORTS)})"
            )
        if key in ports:
            raise UsageError(f"{url}: {key} given twice")
        if not (value.isascii() and value.isdigit()) or not 1 <= int(value) <= 65535:
            raise UsageError(f"{url}: {key} is a port 1-65535, not {value!r}")
        ports[key] = int(value)
    return parts._replace(query="").geturl(), ports


def drive_command(dashboard_url: str, secondary_port: int, rtde_port: int) -> str:
    """The shell command that drives a UR whose Dashboard Server is at ``dashboard_url``
    and whose other interfaces are at these ports (the link URL names those not at the
    defaults; quoted for a POSIX shell)."""
    usual = UrOptions()
    query = "&".join(
        f"{key}={port}"
        for key, port, default in (
            ("rtde_port", rtde_port, usual.rtde_port),
            ("secondary_port", secondary_port, usual.secondary_port),
        )
        if port != default
    )
    link = f"{dashboard_url}?{query}" if query else dashboard_url
    return f"cellctl robot --kind ur --link {shlex.quote(link)}"


def mem_interface(name: str, interface: str) -> str:
    """The ``mem://`` name of the UR's ``interface`` beside its Dashboard Server at ``name``
    (what its emulator listens at, and :func:`interface_url` opens)."""
    return f"{name}.{interface}"


class UrOptions(BaseModel):
    """A UR's options (``[machines.NAME] options``)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    model: Literal["UR3e", "UR5e", "UR10e", "UR16e"] = "UR5e"
    """The arm: its reach is what the URScript check holds poses to."""
    secondary_port: int = Field(default=30002, ge=1, le=65535)
    """The secondary client interface's port (URScript programs); at `--link`:
    `?secondary_port=PORT` on the link URL."""
    rtde_port: int = Field(default=30004, ge=1, le=65535)
    """RTDE's port; at `--link`: `?rtde_port=PORT` on the link URL."""
    rtde_frequency: float = Field(default=125.0, gt=0, le=500)
    """RTDE output frequency, Hz (CB3: at most 125)."""
    reply_timeout: float = Field(default=5.0, gt=0, le=120)
    """Seconds the Dashboard Server may take to answer a line."""
    state_timeout: float = Field(default=1.0, gt=0, le=60)
    """Seconds without an RTDE package before the robot counts as not answering."""
    power_on_timeout: float = Field(default=60.0, gt=0, le=600)
    """Seconds from ``power on`` to robot mode IDLE."""
    brake_release_timeout: float = Field(default=30.0, gt=0, le=600)
    """Seconds from ``brake release`` to robot mode RUNNING."""
    start_timeout: float = Field(default=5.0, gt=0, le=120)
    """Seconds for a URScript program sent on the secondary interface to show it runs."""
    end_register: int | None = Field(default=24, ge=0, le=47)
    """Output integer register a cell's URScript program sets when it ends (the driver adds
    the line); None: its end is seen by the RTDE runtime state alone."""
