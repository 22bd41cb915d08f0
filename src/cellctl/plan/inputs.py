"""A plan's inputs saved beside its output, so ``cellctl plan --replay DIR/inputs.json`` plays
the same plan again::

    save_inputs(inputs, policies, out)          # out/inputs.json and out/cell/ (the config)
    inputs, policies = load_inputs(out / "inputs.json")

``inputs.json`` holds the seed, the window, the orders (with their due times and where their
parts under way are), the fault windows, the machines out of service and the parts held at
the start, and names the copy of the cell's configuration beside it (``cell/``: cell.toml
and the programs it names; no journal, mailbox, machine state or token). Times are unix
seconds; ``*_text`` fields repeat them as local time for people and are ignored on reading.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, Final

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.cell.config import load_cell
from cellctl.emulators.celltoml import real_cell_toml
from cellctl.errors import CellctlError, UsageError
from cellctl.files import read_file, write_output
from cellctl.mailbox.base import MAX_QTY
from cellctl.plan.engine import FaultWindow, HeldPart, PartAt, PlanInputs, PlanOrder
from cellctl.plan.when import MAX_HORIZON_S, MAX_POLL_S

#: The file's format name and version.
FORMAT: Final = "cellctl-plan-inputs/1"
INPUTS_FILE: Final = "inputs.json"
CELL_COPY: Final = "cell"
#: The largest inputs file read, bytes.
MAX_BYTES: Final = 5_000_000

_Text = Annotated[str, Field(min_length=1, max_length=100)]
_Time = Annotated[float, Field(ge=0, le=1e11, allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class _At(_Model):
    location: _Text
    route_index: Annotated[int, Field(ge=0, le=1000)] = 0
    # Missing in files saved before plans took a cut up mid-way: none done.
    done_s: Annotated[float, Field(ge=0, le=1e7, allow_inf_nan=False)] = 0.0


class _Order(_Model):
    order_id: _Text
    part_type: _Text
    qty: Annotated[int, Field(ge=1, le=MAX_QTY)]
    priority: Annotated[int, Field(ge=-1_000_000, le=1_000_000)] = 0
    due: _Time | None = None
    # Missing in files saved before plans took parts up where they are: none under way.
    under_way: Annotated[list[_At], Field(max_length=MAX_QTY)] = []


class _Fault(_Model):
    machine: _Text
    fault: _Text
    start: _Time
    end: _Time | None = None
    arg: Annotated[str, Field(max_length=100)] | None = None


class _Held(_Model):
    order_id: _Text
    part_type: _Text
    location: _Text
    route_index: Annotated[int, Field(ge=0, le=1000)] = 0


class InputsFile(_Model):
    """``inputs.json``'s schema."""

    model_config = ConfigDict(extra="ignore", frozen=True, defer_build=True)
    format: str = Field(pattern=f"^{FORMAT}$")
    cell_dir: Annotated[str, Field(min_length=1, max_length=4096)]
    start: _Time
    until: _Time
    policies: Annotated[list[_Text], Field(min_length=1, max_length=10)]
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] = 0
    # Missing in files saved before plans had their own: the cell's period (0), as played then.
    poll_period: Annotated[float, Field(ge=0, le=MAX_POLL_S, allow_inf_nan=False)] = 0.0
    orders: Annotated[list[_Order], Field(max_length=10_000)] = []
    faults: Annotated[list[_Fault], Field(max_length=100)] = []
    out_of_service: Annotated[list[_Text], Field(max_length=100)] = []
    held: Annotated[list[_Held], Field(max_length=10_000)] = []


def _local(stamp: float | None) -> str | None:
    return None if stamp is None else datetime.fromtimestamp(stamp).isoformat(timespec="seconds")


def inputs_dict(
    inputs: PlanInputs, policies: tuple[str, ...], cell_dir: str = CELL_COPY
) -> dict[str, Any]:
    """``inputs`` as ``inputs.json`` holds them (``cell_dir`` relative to the file)."""
    return {
        "format": FORMAT,
        "cell_dir": cell_dir,
        "start": inputs.start,
        "start_text": _local(inputs.start),
        "until": inputs.until,
        "until_text": _local(inputs.until),
        "policies": list(policies),
        "seed": inputs.seed,
        "poll_period": inputs.poll_period,
        "orders": [asdict(o) | {"due_text": _local(o.due)} for o in inputs.orders],
        "faults": [
            asdict(f) | {"start_text": _local(f.start), "end_text": _local(f.end)}
            for f in inputs.faults
        ],
        "out_of_service": list(inputs.out_of_service),
        "held": [asdict(h) for h in inputs.held],
    }


def _strip_text(data: Any) -> Any:
    """Drop the ``*_text`` fields (for people) before the schema reads the rest."""
    if isinstance(data, dict):
        return {k: _strip_text(v) for k, v in data.items() if not str(k).endswith("_text")}
    if isinstance(data, list):
        return [_strip_text(v) for v in data]
    return data


def _order(found: _Order) -> PlanOrder:
    under_way = tuple(PartAt(**at.model_dump()) for at in found.under_way)
    return PlanOrder(**(found.model_dump() | {"under_way": under_way}))


def parse_inputs(data: Any, base: Path) -> tuple[PlanInputs, tuple[str, ...]]:
    """The inputs and policies ``data`` (``inputs.json``'s content) holds; ``cell_dir``
    relative to ``base``."""
    try:
        found = InputsFile.model_validate(_strip_text(data))
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(x) for x in first["loc"]) or "the file"
        raise UsageError(f"plan inputs: {where}: {first['msg']}") from None
    if not found.start < found.until <= found.start + MAX_HORIZON_S:
        raise UsageError("plan inputs: until must be after start, at most 31 days")
    if not found.orders:  # as the command line says it: a plan of no orders plays nothing
        raise UsageError("plan inputs: orders: nothing to plan (the list is empty)")
    inputs = PlanInputs(
        cell_dir=base / found.cell_dir,
        orders=tuple(_order(o) for o in found.orders),
        start=found.start,
        until=found.until,
        faults=tuple(FaultWindow(**f.model_dump()) for f in found.faults),
        policy=found.policies[0],
        seed=found.seed,
        poll_period=found.poll_period,
        out_of_service=tuple(found.out_of_service),
        held=tuple(HeldPart(**h.model_dump()) for h in found.held),
    )
    return inputs, tuple(found.policies)


def load_inputs(path: Path) -> tuple[PlanInputs, tuple[str, ...]]:
    """Read ``inputs.json`` (see module docstring); the cell copy beside it."""
    try:
        data = read_file(path, limit=MAX_BYTES)
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file") from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None
    if len(data) > MAX_BYTES:
        raise UsageError(f"{path}: larger than {MAX_BYTES} bytes: not plan inputs")
    try:
        found = json.loads(data)
    except (ValueError, RecursionError):
        raise UsageError(f"{path}: not JSON") from None
    inputs, policies = parse_inputs(found, path.parent)
    cell = inputs.cell_dir
    if not (cell / "cell.toml").is_file():
        what = "has no cell.toml" if cell.is_dir() else "is missing"
        raise UsageError(
            f"{path}: the cell directory it names, {cell}, {what}: a replay plays the copy "
            f"of the cell's configuration `cellctl plan --out` saved beside its inputs "
            f"({CELL_COPY}/): put it back (or name another in its cell_dir), or plan again "
            "with --out"
        )
    return inputs, policies


def config_files(cell_dir: Path) -> list[Path]:
    """The files of a cell's configuration, relative to it: cell.toml and the programs it
    names inside the directory (the robot's transfers, the mills' setups, the routes')."""
    raw = load_cell(cell_dir).raw  # checked: every file it names exists
    base = cell_dir.resolve()
    named: list[Path] = [Path("cell.toml")]
    texts = list(raw.get("robot_programs", {}).values())
    texts += [m.get("setup") for m in raw.get("machines", {}).values()]
    texts += [s.get("program") for p in raw.get("parts", {}).values() for s in p.get("route", [])]
    for text in texts:
        if not isinstance(text, str):
            continue
        full = (cell_dir / text).resolve()
        if full.is_relative_to(base):
            named.append(full.relative_to(base))
    return list(dict.fromkeys(named))


#: The file a plan writes into its copy of the cell's configuration: what marks the
#: directory as the plan's own (replaced by the next plan written there).
COPY_MARK: Final = ".cellctl-plan-copy"
#: What a cell holds and a plan's copy never does (its journal, mailbox, machine state).
_CELL_OWN = ("journal.sqlite3", "mailbox.sqlite3", "state")


def _beside_inputs(target: Path) -> bool:
    """True if ``target``'s directory holds a plan's ``inputs.json`` naming ``target`` as
    its cell copy (a plan written before copies were marked)."""
    try:
        data = json.loads(read_file(target.parent / INPUTS_FILE, limit=MAX_BYTES))
    except (OSError, ValueError, RecursionError):
        return False
    return (
        isinstance(data, dict)
        and data.get("format") == FORMAT
        and data.get("cell_dir") == target.name
    )


def _foreign(target: Path) -> list[str]:
    """What in the directory ``target`` a plan's copy would not hold (relative names, a
    directory with a slash): links, a cell's own files, files its cell.toml does not name."""
    try:
        allowed = {str(p) for p in config_files(target)} | {COPY_MARK}
    except (CellctlError, OSError, ValueError):
        allowed = {COPY_MARK, "cell.toml"}  # not a cell a plan wrote: the rest is not its copy
    found: list[str] = []
    for root, dirs, files in os.walk(target):  # links to directories are not followed
        here = Path(root)
        for name in sorted(dirs):
            rel = (here / name).relative_to(target)
            if (here / name).is_symlink():
                found.append(str(rel))
            elif str(rel) in _CELL_OWN:
                found.append(f"{rel}/")
        dirs[:] = sorted(d for d in dirs if f"{(here / d).relative_to(target)}/" not in found)
        for name in sorted(files):
            rel = (here / name).relative_to(target)
            if str(rel) not in allowed or (here / name).is_symlink():
                found.append(str(rel))
    return found


def check_copy_target(target: Path) -> None:
    """Refuse (:class:`UsageError`, saying what is in the way and the way out) ``target`` as
    the place of a plan's copy of a cell's configuration unless it is missing, an empty
    directory or a plan's own copy (marked :data:`COPY_MARK`, or beside the plan's
    ``inputs.json`` that names it) holding only what such a copy holds: a symbolic link,
    a file, or a directory with a journal, a mailbox, machine state or any other file (a
    real cell, an operator's notes) is never removed or written through."""
    way_out = "give --out a directory of its own, or move it away"
    if target.is_symlink():
        raise UsageError(
            f"{target}: a symbolic link (to {os.readlink(target)}): a plan writes its copy of "
            f"the cell's configuration through no link: {way_out}"
        )
    if not target.exists():
        return
    if not target.is_dir():
        raise UsageError(f"{target}: in the way of the plan's cell copy (remove it)")
    if not any(target.iterdir()):
        return
    own = (target / COPY_MARK).is_file() or _beside_inputs(target)
    foreign = _foreign(target)
    if own and not foreign:
        return
    shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
    what = f"it holds {shown}" if foreign else f"no {COPY_MARK} in it, no plan's {INPUTS_FILE}"
    raise UsageError(
        f"{target}: not a plan's copy of a cell's configuration ({what}), and a plan "
        f"replaces only its own: {way_out}"
    )


def copy_config(cell_dir: Path, target: Path) -> Path:
    """Copy the cell's configuration (:func:`config_files`) into ``target``, its cell.toml
    as the real cell's (:func:`plan_cell_toml`), marked as a plan's copy (:data:`COPY_MARK`).
    A plan's own earlier copy there is replaced; anything else there is refused
    (:func:`check_copy_target`), and nothing is written through a link. A replay into its
    own directory keeps the copy it plays from."""
    if target.resolve() == cell_dir.resolve() and not target.is_symlink():
        return target
    check_copy_target(target)
    files = config_files(cell_dir)
    if target.exists():
        shutil.rmtree(target)
    for rel in files:
        (target / rel).parent.mkdir(parents=True, exist_ok=True)
        data = read_file(cell_dir / rel)
        if rel == Path("cell.toml"):
            data = plan_cell_toml(data.decode("utf-8")).encode("utf-8")
        write_output(target / rel, data)
    write_output(target / COPY_MARK, "a plan's copy of a cell's configuration (cellctl plan)\n")
    return target


#: The tables of a cell.toml a plan leaves out (what a plan does not serve).
NOT_PLAYED = ("mailbox", "opcua")


def plan_cell_toml(text: str) -> str:
    """A cell's cell.toml as a plan plays it: the real cell's (an emulated cell's emulation
    undone, :func:`~cellctl.emulators.celltoml.real_cell_toml`: a plan plays the machines' real
    times, its emulators their own options), without the tables of what a plan does not
    serve: ``[mailbox]`` (a plan's orders are its own: no broker, no credentials to copy) and
    ``[opcua]`` (no server, no users file to copy)."""
    out: list[str] = []
    section = ""
    for line in real_cell_toml(text).splitlines():
        stripped = line.strip()
        if stripped.startswith("["):
            section = stripped.strip("[] ").split(".")[0].strip()
        if section not in NOT_PLAYED:
            out.append(line)
    return "\n".join(out) + "\n"


def save_inputs(inputs: PlanInputs, policies: tuple[str, ...], out: Path) -> Path:
    """Write ``out/inputs.json`` and the configuration's copy ``out/cell/``."""
    out.mkdir(parents=True, exist_ok=True)
    copy_config(inputs.cell_dir, out / CELL_COPY)
    path = out / INPUTS_FILE
    write_output(path, json.dumps(inputs_dict(inputs, policies), indent=1) + "\n")
    return path
