"""The Kerf 100's options (``[machines.NAME] options`` in cell.toml), beside its declaration:
the registry reads them at every start, the driver only when a saw is opened."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SawOptions(BaseModel):
    """The saw's options (``[machines.NAME] options`` in cell.toml)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    reply_timeout: float = Field(default=2.0, gt=0, le=60)
    """Seconds the saw may take to answer a command."""
    max_length_mm: float = Field(default=3000.0, gt=0, le=3000)
    """The longest cut this saw's bar stock allows, mm (cut lists are checked against it)."""
    cut_margin: float = Field(default=2.0, gt=0, le=10)
    """A run's deadline: its cut time times this, plus ``cut_extra``."""
    cut_extra: float = Field(default=30.0, gt=0, le=3600)
    """Seconds added to a run's deadline."""
    home_timeout: float = Field(default=10.0, gt=0, le=600)
    """Seconds the carriage may take to find its home switch."""
    ready_wait: float = Field(default=1.0, gt=0, le=60)
    """Seconds it may take to show idle after a cut."""
    setup_timeout: float = Field(default=30.0, gt=0, le=3600)
    """Seconds a setup may take (homing: no operator step)."""
    poll: float = Field(default=0.05, gt=0, le=5)
    """Seconds between status reads while it cuts."""
