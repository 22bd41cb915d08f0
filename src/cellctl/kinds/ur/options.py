"""What the UR's declaration needs without its driver: its options (``cell.toml``) and its
line (the registry reads these at start; the driver is imported when a robot is opened)."""

from __future__ import annotations

from typing import Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field

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
    """The secondary client interface's port (URScript programs)."""
    rtde_port: int = Field(default=30004, ge=1, le=65535)
    """RTDE's port."""
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
