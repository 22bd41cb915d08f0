"""Reading ``cell.toml`` and collecting its problems, each with its TOML path and line.

:func:`cellctl.cell.config.check_cell` reads the file with :func:`_load_toml`, validates each
table with :func:`_checked` into a :class:`_Problems`, and returns the problems' messages
(``[machines.cnc1] kind: ... (line 12)``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from cellctl.cell.configschema import _PER_ENTRY
from cellctl.errors import UsageError
from cellctl.files import read_text


def _load_toml(directory: Path) -> tuple[dict[str, Any], str]:
    import tomllib

    path = directory / "cell.toml"
    try:
        text = read_text(path)
        return tomllib.loads(text), text
    except FileNotFoundError:
        raise UsageError(
            f"{path}: no such file (create it, or run 'cellctl emulate cell')"
        ) from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise UsageError(f"{path}: not UTF-8 text: {e.reason}") from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None


def require_cell_file(directory: Path) -> None:
    """Refuse (UsageError, in :func:`~cellctl.cell.config.load_cell`'s words) a directory
    with no cell.toml that reads as TOML: before anything is made there."""
    _load_toml(directory)


class _Problems:
    """Problems found so far, each with its TOML path and, where found, its line."""

    def __init__(self, text: str) -> None:
        self.lines = text.splitlines()
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def at(self, loc: tuple[str | int, ...], message: str) -> None:
        self.items.append(f"{_path(loc)}: {message}{self._line(loc)}")

    def schema(self, loc: tuple[str | int, ...], error: ValidationError) -> None:
        for item in error.errors(include_url=False):
            where = loc + tuple(item["loc"])
            self.at(where, _message(item))

    def _line(self, loc: tuple[str | int, ...]) -> str:
        keys = [k for k in loc if isinstance(k, str)]
        if not keys:
            return ""
        found = None
        for depth in range(len(keys), 0, -1):
            header = _header(keys[:depth])
            start = next((i for i, t in enumerate(self.lines) if _header_of(t) == header), None)
            if start is None:
                continue
            found = start
            rest = keys[depth:]
            if rest:
                key = re.compile(rf"^\s*\"?{re.escape(rest[0])}\"?\s*=")
                for i in range(start + 1, len(self.lines)):
                    if _header_of(self.lines[i]) is not None:
                        break
                    if key.match(self.lines[i]):
                        found = i
                        break
            break
        return f" (line {found + 1})" if found is not None else ""


def _header(keys: list[str]) -> str:
    return ".".join(keys)


def _header_of(line: str) -> str | None:
    match = re.match(r"^\s*\[+\s*([^\]]+?)\s*\]+\s*(?:#.*)?$", line)
    if match is None:
        return None
    return ".".join(part.strip().strip("\"'") for part in match.group(1).split("."))


def _path(loc: tuple[str | int, ...]) -> str:
    """``("machines", "cnc1", "kind")`` → ``[machines.cnc1] kind``."""
    depth = 2 if loc and loc[0] in _PER_ENTRY else 1
    table = ".".join(str(k) for k in loc[:depth])
    rest = ""
    for key in loc[depth:]:
        rest += f"[{key + 1}]" if isinstance(key, int) else (f".{key}" if rest else key)
    return f"[{table}] {rest}".rstrip() if rest else f"[{table}]"


def _message(item: Any) -> str:
    kind = item["type"]
    if kind == "missing":
        return "missing"
    if kind == "extra_forbidden":
        return "unknown key"
    shown = repr(item.get("input"))
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    if kind == "literal_error":
        return f"{shown} is not {item['ctx']['expected']}"
    message = str(item["msg"])
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
    if kind == "value_error" and shown in message:
        return message  # our own validator named the value: said once
    return f"{message}, not {shown}"


def _checked(
    model: type[_T], data: Any, loc: tuple[str | int, ...], problems: _Problems
) -> _T | None:
    try:
        return model.model_validate(data)
    except ValidationError as e:
        problems.schema(loc, e)
        return None


_T = TypeVar("_T", bound=BaseModel)


def _entries(raw: dict[str, Any], key: str, problems: _Problems) -> dict[str, Any]:
    """A table of tables (``[machines]``, ``[parts]``...), or {} after reporting it is not one."""
    value = raw.get(key, {})
    if not isinstance(value, dict):
        problems.at((key,), f"must be a table, not {type(value).__name__}")
        return {}
    return value
