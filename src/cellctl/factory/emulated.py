"""A factory without hardware: a private Mosquitto, N emulated cells, their cell directories
and a ``factory.toml``, all in one directory (``cellctl emulate factory``, the factory demo,
the tests and ``bench/factory_throughput.py``).

::

    async with EmulatedFactory(Path("plant"), cells=3, time_scale=200) as plant:
        plant.cell_dirs      # [plant/cell1, plant/cell2, plant/cell3]: run each: cellctl run
        plant.directory      # plant/factory.toml: cellctl factory --dir plant run
        plant.cells[0].runs_per_part()   # what the emulated mills of cell1 cut

    # cell1 emulates examples/cell-tending (its machines, programs, part types), cell2 the
    # example cell: a template per cell, in order; the cells past them the example cell.
    EmulatedFactory(Path("plant"), cells=2, templates=[Path("examples/cell-tending")])

Each cell's ``cell.toml`` names the cell ``cellN`` and takes its orders from the broker
(``[mailbox] url = "mqtt://127.0.0.1:PORT/cellctl/cellN"``, its own 0600 credentials in
``mqtt.toml``). The broker lets each cell read only its orders and write only its reports,
state and status (:mod:`cellctl.factory.broker`).
"""

from __future__ import annotations

import re
import shutil
import sys
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from types import TracebackType
from typing import Self

from cellctl.clock import current_clock
from cellctl.emulators.cell import EmulatedCell, check_cell_dir
from cellctl.emulators.header import first_line
from cellctl.emulators.serve import CELL_TIME_SCALE
from cellctl.errors import UsageError
from cellctl.factory.broker import FACTORY_USER, MosquittoBroker
from cellctl.factory.config import FACTORY_FILE

#: The first line of a factory.toml an emulated factory writes: a factory.toml without it is
#: a real factory's, which an emulation never overwrites (:func:`check_factory_dir`).
EMULATED_FACTORY_HEADER = (
    "# Emulated factory of {cells} cells (time scale {scale:g}); written by cellctl emulate "
    "factory."
)
_EMULATED_FACTORY = re.compile(r"#\s*Emulated factory of [0-9]+ cells \(time scale [0-9.eE+-]+\)")


def check_factory_dir(directory: Path) -> None:
    """UsageError if ``directory`` holds a factory.toml an emulated factory did not write, or a
    cell directory (``directory/NAME/cell.toml``) an emulated cell did not write: a real
    factory or cell, which emulating there (or the factory demo's clearing) would overwrite.
    Reads only."""
    toml = directory / FACTORY_FILE
    real = _EMULATED_FACTORY.match(first_line(toml)) is None
    if (toml.exists() or toml.is_symlink()) and real:
        raise UsageError(
            f"{toml} was not written by cellctl emulate factory (its first line is not "
            "'# Emulated factory of N cells (time scale ...)'): emulating here would "
            f"overwrite it and its cells. Use another directory, or delete {toml} first"
        )
    if directory.is_dir():
        for child in sorted(directory.iterdir()):
            if child.is_dir() and not child.is_symlink():
                check_cell_dir(child)


#: The topic prefix of cell ``name``.
PREFIX = "cellctl/{name}"
#: Attempts in a row to start the broker again when it dies (killed, crashed).
BROKER_RESTARTS = 3


def _tell(text: str) -> None:
    """One line on stderr, timed: what happened to the broker, between the cells' lines."""
    stamp = datetime.fromtimestamp(current_clock().now()).strftime("%H:%M:%S")
    print(f"{stamp} {text}", file=sys.stderr, flush=True)


def _copy_private(source: Path, target: Path) -> None:
    shutil.copyfile(source, target)
    target.chmod(0o600)


class EmulatedFactory:
    """See the module docstring; ``poll_period`` (s) replaces the cells' own when given;
    ``templates``: the cell directory cell1, cell2, ... emulate (None or past the list: the
    example cell). The broker is watched: one that dies is said (``say``, default a timed
    line on stderr) and started again, same port, configuration and persistence, up to
    ``broker_restarts`` times in a row (0: not watched); see
    :class:`~cellctl.factory.broker.MosquittoBroker`."""

    def __init__(
        self,
        directory: Path,
        *,
        cells: int = 3,
        time_scale: float = CELL_TIME_SCALE,
        pacing: bool = True,
        poll_period: float | None = None,
        accept_timeout: float = 30.0,
        factory_poll: float = 0.5,
        templates: Sequence[Path | None] = (),
        broker_restarts: int = BROKER_RESTARTS,
        say: Callable[[str], None] = _tell,
    ) -> None:
        if not 1 <= cells <= 32:
            raise ValueError(f"an emulated factory has 1 to 32 cells, not {cells}")
        if len(templates) > cells:
            raise UsageError(f"{len(templates)} cell templates for {cells} cells")
        for template in templates:
            if template is not None and not (template / "cell.toml").is_file():
                raise UsageError(f"{template}: no cell.toml (a cell template is a cell directory)")
        self.directory = Path(directory)
        self.names = [f"cell{i}" for i in range(1, cells + 1)]
        #: The cell directory each cell emulates (None: the example cell).
        self.templates: list[Path | None] = [*templates, *[None] * (cells - len(templates))]
        self.time_scale = time_scale
        self.pacing = pacing
        self.poll_period = poll_period
        self.accept_timeout = accept_timeout
        self.factory_poll = factory_poll
        self.broker = MosquittoBroker(
            self.directory / "broker",
            [(n, PREFIX.format(name=n)) for n in self.names],
            restarts=broker_restarts,
            say=say,
        )
        self.cells: list[EmulatedCell] = []

    @property
    def cell_dirs(self) -> list[Path]:
        return [self.directory / name for name in self.names]

    @property
    def factory_toml(self) -> Path:
        return self.directory / FACTORY_FILE

    async def start(self) -> Path:
        """Start the broker and the cells; write the cell directories and factory.toml.

        A real factory's directory (:func:`check_factory_dir`) is refused before anything
        starts or is written."""
        check_factory_dir(self.directory)
        # Each template's machines first: one that cannot be emulated is refused before
        # anything starts or is written.
        self.cells = [
            EmulatedCell(time_scale=self.time_scale, pacing=self.pacing, template=template)
            for template in self.templates
        ]
        self.directory.mkdir(parents=True, exist_ok=True)
        await self.broker.start()
        try:
            for name, cell_dir, cell in zip(self.names, self.cell_dirs, self.cells, strict=True):
                toml = await cell.start(cell_dir)
                _copy_private(self.broker.credentials(name), cell_dir / "mqtt.toml")
                text = toml.read_text(encoding="utf-8")
                text = re.sub(r'(?m)^name = ".*"$', f'name = "{name}"', text, count=1)
                if self.poll_period is not None:
                    text = re.sub(
                        r"poll_period = [0-9.]+", f"poll_period = {self.poll_period:g}", text
                    )
                url = f"{self.broker.url}/{PREFIX.format(name=name)}"
                text += f'\n[mailbox]\nurl = "{url}"\ncredentials = "mqtt.toml"\n'
                toml.write_text(text, encoding="utf-8")
            _copy_private(
                self.broker.credentials(FACTORY_USER), self.directory / "factory.credentials"
            )
            self.factory_toml.write_text(self._factory_toml(), encoding="utf-8")
        except BaseException:
            await self.close()
            raise
        return self.factory_toml

    def _factory_toml(self) -> str:
        lines = [
            EMULATED_FACTORY_HEADER.format(cells=len(self.names), scale=self.time_scale),
            "[factory]",
            'name = "factory"',
            f"accept_timeout = {self.accept_timeout:g}",
            f"poll_period = {self.factory_poll:g}",
            "",
            "[broker]",
            f'url = "{self.broker.url}"',
            'credentials = "factory.credentials"',
        ]
        for name, template in zip(self.names, self.templates, strict=True):
            lines += ["", f"[cells.{name}]", f'prefix = "{PREFIX.format(name=name)}"']
            if template is not None:
                lines[-1] += f"  # emulates {str(template)!r}"
        return "\n".join(lines) + "\n"

    async def close(self) -> None:
        """Stop the cells' machines and the broker."""
        for cell in self.cells:
            await cell.close()
        await self.broker.stop()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()
