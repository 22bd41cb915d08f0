"""A machine's manual functions, as a kind declares them: the source's menus plus the
tool-kit's extras. The CLI, the control API and the console all run them::

    fn = MachineFunction("mill", "status", "STATUS", 4, "State, CTS.", NoParams, run_status,
                         observes=True)
    params = fn.check({})                              # refused here: no byte went out
    result = await fn.run(driver, params, progress)    # {"message": ..., ...}

Parameters are checked (and programs parsed, by ``prepare``) before a driver is touched.
Results are JSON-ready dicts with a ``message`` in the source's words.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from cellctl.errors import UsageError, printable

Progress = Callable[[dict[str, Any]], None]
"""Called with a JSON-ready dict as a download goes on."""

#: The largest program text a caller may send (a DYNALAN program of ~100,000 lines).
MAX_PROGRAM_CHARS = 4_000_000


class InvalidParams(UsageError):
    """Parameters that do not fit their schema (a JSON-RPC -32602): the message names the
    field and says why."""


#: How many of a validation's problems a message lists.
SHOWN_PROBLEMS = 5
#: How much of a field's name a message shows (a peer picks the names).
SHOWN_NAME = 60


#: A parameter's free text (a reason, a name, an id): printable, as order ids are
#: (:data:`cellctl.errors.NOT_PRINTABLE`). A program's text is not one: it has lines.
PrintableText = Annotated[str, AfterValidator(printable)]


class Params(BaseModel):
    """Base of the functions' parameters: unknown keys are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class NoParams(Params):
    pass


class ProgramParams(Params):
    program: PrintableText = Field(min_length=1, max_length=255, description="The file's name.")
    text: str = Field(max_length=MAX_PROGRAM_CHARS, description="The file's contents.")


class UploadParams(Params):
    timeout: float = Field(default=120.0, gt=0, le=3600)


Runner = Callable[[Any, Any, Progress | None], Awaitable[dict[str, Any]]]


@dataclass(frozen=True)
class MachineFunction:
    """One function of a machine family: its menu key, its parameters, how it runs."""

    family: str  # "robot" or "mill"
    name: str
    label: str  # as the source's menu shows it
    menu: int | None  # the source's menu number; None for the tool-kit's extras
    doc: str
    params: type[Params]
    runner: Runner
    observes: bool = False
    """Only reads the machine: allowed while it is in automatic service."""
    prepare: Callable[[Any], Any] | None = None
    """Parses what the parameters carry (a program's text) before a driver is touched."""

    def check(self, raw: dict[str, Any] | None) -> Any:
        """Validated parameters (programs parsed): UsageError, with the reason, otherwise."""
        try:
            params = self.params.model_validate(raw or {})
        except ValidationError as e:
            raise InvalidParams(f"{self.family} {self.name}: {describe(e)}") from None
        return _prepare(self, params)

    async def run(self, driver: Any, params: Any, progress: Progress | None = None) -> Any:
        """Run on ``driver`` with parameters from :meth:`check`."""
        return await self.runner(driver, params, progress)


def describe(error: ValidationError) -> str:
    """A pydantic error in one line: ``partition: partition must be 1 to 5 ...``."""
    parts = []
    problems = error.errors(include_url=False, include_input=False)
    for item in problems[:SHOWN_PROBLEMS]:
        where = ".".join(str(x) for x in item["loc"]) or "parameters"
        if len(where) > SHOWN_NAME:
            where = where[:SHOWN_NAME] + "…"
        message = str(item["msg"]).removeprefix("Value error, ")
        parts.append(f"{where}: {message}")
    if len(problems) > SHOWN_PROBLEMS:
        parts.append(f"and {len(problems) - SHOWN_PROBLEMS} more")
    return "; ".join(parts)


@dataclass(frozen=True)
class Prepared:
    """Checked parameters plus what was parsed from them."""

    params: Any
    parsed: Any = None


def _prepare(fn: MachineFunction, params: Params) -> Prepared:
    if fn.prepare is None:
        return Prepared(params)
    return Prepared(params, fn.prepare(params))


def ok(message: str, **data: Any) -> dict[str, Any]:
    """A function's result: the source's ``message`` and data."""
    return {"message": message, **data}
