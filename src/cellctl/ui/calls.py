"""How a machine command of the CLI runs: through the running controller's API, or straight
to the machine when none runs, with the same output either way.

::

    result = machine_call(ctx, "robot", "status", {})    # a dict: "message", "lines", data
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

import click
from rich.progress import Progress, ProgressColumn

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.files import read_file
from cellctl.link.trace import refuse_trace_on_inputs
from cellctl.ui.common import cell_dir, err_console, machine_ref, run


def state_home() -> Path:
    """Where machines driven by ``--link`` outside a cell keep their host state:
    ``$XDG_STATE_HOME/cellctl`` (default ``~/.local/state/cellctl``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "cellctl"


def read_program(path: Path) -> dict[str, str]:
    """A program file as the API takes it: its name and text (refused if it cannot be read,
    or if the command's ``--trace`` names the same file: the trace would be appended to it)."""
    context = click.get_current_context(silent=True)
    given = (context.find_object(dict) or {}) if context is not None else {}
    refuse_trace_on_inputs(given.get("trace"), [path])
    try:
        data = read_file(path)
    except FileNotFoundError:
        raise UsageError(f"{path}: could not open file: no such file") from None
    except OSError as e:
        raise UsageError(f"{path}: could not open file: {e.strerror}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UsageError(f"{path}: not a text file (byte {e.start + 1} is not UTF-8)") from None
    return {"program": path.name, "text": text}


def machine_call(
    ctx: click.Context,
    family: str,
    function: str,
    params: dict[str, Any],
    progress: Callable[[dict[str, Any]], None] | None = None,
    *,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run ``family.function`` on the machine the command names; print nothing, return the
    result (a refusal or failure exits with its one-line reason)."""
    given = ctx.find_object(dict) or {}
    directory = cell_dir(ctx)

    async def main() -> dict[str, Any]:
        from cellctl.service.client import StandaloneCell, open_cell

        _, ref = machine_ref(ctx, family, function)
        if options:
            ref = dataclasses.replace(ref, options={**ref.options, **options})
        trace = given.get("trace")
        readiness = given.get("readiness")
        if given.get("link"):
            # Imported here: through a running controller's API (below) none of it is needed.
            from cellctl.service.access import LocalCell

            # An ad-hoc link outside any cell keeps its host state per user, not in a
            # ./cell/state/ it would leave behind in whatever directory this runs in.
            home = directory if (directory / "cell.toml").is_file() else state_home()
            cell: Any = StandaloneCell(
                LocalCell(home, {ref.name: ref}, trace=trace, readiness=readiness)
            )
        else:
            cell = await open_cell(directory, {ref.name: ref}, trace=trace, readiness=readiness)
            if cell.mode == "attached" and (trace or readiness or options):
                err_console.print(
                    "note: the running controller holds the link: --trace, --readiness, "
                    "--start-signal and --time-scale do not "
                    f"apply (its traffic: cellctl traffic {ref.name})"
                )
        async with cell:
            result: dict[str, Any] = await cell.call(
                f"{family}.{function}", {"machine": ref.name, **params}, progress
            )
            return result

    return run(main)


def cell_call(ctx: click.Context, method: str, params: dict[str, Any] | None = None) -> Any:
    """Call an API method on the cell: through the running controller, or in this process on
    the cell's files when none runs (the same code either way)."""
    directory = cell_dir(ctx)

    async def main() -> Any:
        from cellctl.service.client import open_cell

        async with await open_cell(directory, {}) as cell:
            return await cell.call(method, params or {})

    return run(main)


class LazyBar:
    """A Rich progress bar drawn only once there is progress to show (a refusal draws none).

    ``update(fields)`` takes the API's progress dicts; ``fields_of`` maps one to the task's
    ``completed``/``total`` and the columns' fields.
    """

    def __init__(
        self,
        columns: tuple[str | ProgressColumn, ...],
        description: str,
        fields_of: Callable[[dict[str, Any], float], dict[str, Any]],
        *,
        tick: float | None = None,
    ) -> None:
        from cellctl.ui.common import console

        self._progress = Progress(*columns, console=console, transient=False)
        self._description = description
        self._fields_of = fields_of
        self._task: Any = None
        self.start = current_clock().monotonic()
        # ``tick``: the last dict is mapped again every ``tick`` s while it says the machine
        # runs (``running``): figures that move with the clock (a cut's estimate) move on.
        self._tick = tick
        self._last: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._ticker: threading.Thread | None = None

    def update(self, data: dict[str, Any]) -> None:
        with self._lock:
            self._last = data
            fields = self._fields_of(data, current_clock().monotonic() - self.start)
            if self._task is None:
                self._progress.start()
                self._task = self._progress.add_task(self._description, **fields)
            else:
                self._progress.update(self._task, **fields)

    def _run_ticks(self) -> None:
        assert self._tick is not None
        while not self._done.wait(self._tick):
            last = self._last
            if last is not None and last.get("running"):
                self.update(last)

    def __enter__(self) -> LazyBar:
        if self._tick is not None:
            self._ticker = threading.Thread(target=self._run_ticks, daemon=True)
            self._ticker.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._done.set()
        if self._ticker is not None:
            self._ticker.join(timeout=5.0)
        if self._task is not None:
            self._progress.stop()
