"""``cellctl dnc``: the DNC server and its hand commands (docs/dnc.md).

::

    cellctl dnc serve --dir SHOP                 # every machine of SHOP/dnc.toml
    cellctl dnc send  mill1 O1234 --dir SHOP     # into the control's memory, with progress
    cellctl dnc drip  mill1 big.nc --dir SHOP    # drip-feed (the control runs as it reads)
    cellctl dnc receive mill1 --dir SHOP         # keep what the control punches
    cellctl dnc stop  mill1 --dir SHOP           # stop the transfer in flight
    cellctl dnc diff  mill1 O1234 --dir SHOP     # the newest received O1234 against the sent
    cellctl dnc check mill1 O1234 --dir SHOP     # refused or not, and its drip-feed forecast
    cellctl dnc status --dir SHOP

When a ``dnc serve`` runs on SHOP, the hand commands go through its control API (its Unix
socket ``SHOP/api.sock`` and token ``SHOP/api-token``); otherwise they open the machine's link
themselves, under the same owner locks (a second opener is refused, naming the holder).
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from rich.progress import BarColumn, Task, TextColumn, TimeRemainingColumn
from rich.text import Text

from cellctl.kinds.iso_cnc.dnc.check_cli import check
from cellctl.kinds.iso_cnc.dnc.hand_cli import call_shop
from cellctl.kinds.iso_cnc.dnc.shopopts import shop_config, shop_options
from cellctl.ui.common import (
    console,
    err_console,
    fail,
    json_option,
    print_json,
    run,
    stop_signals,
)

if TYPE_CHECKING:
    from cellctl.kinds.iso_cnc.dnc.config import ShopConfig
    from cellctl.kinds.iso_cnc.dnc.server import DncServer

# The server, the API and the links are imported by the command that uses them: `cellctl
# --help` and a refused argument load none of them (tests/test_cli_startup.py).


@click.group("dnc")
def dnc() -> None:
    """DNC server for the shop's ISO-code CNC controls (Fanuc / Haas style, RS-232)."""


dnc.add_command(check)


# -- serve -------------------------------------------------------------------------------------


@dnc.command()
@shop_options
@click.pass_context
def serve(ctx: click.Context, shop: Path, use_cell: bool) -> None:
    """Feed every machine: answer remote requests, keep what the controls punch."""
    config = shop_config(ctx, shop, use_cell)
    run(lambda: serve_shop(config))


async def serve_shop(config: ShopConfig, *, stop: asyncio.Event | None = None) -> None:
    """Serve ``config``'s machines and its API until ``stop`` is set (or SIGINT / SIGTERM).

    A machine that cannot be reached is served offline (named, retried). On the stop it says
    at once what it does with the transfers in flight, ends each the clean way (the rest of
    a block and ``%``; each machine's log has it, each caller is told), then closes."""
    from cellctl.cell.owner import acquire_controller_lock
    from cellctl.errors import MachineInUse
    from cellctl.kinds.iso_cnc.dnc.access import DncAccess
    from cellctl.kinds.iso_cnc.dnc.server import DncServer
    from cellctl.service.server import ApiServer
    from cellctl.ui.dashboard.routes import dashboard_routes

    # First: a server refused (its shop served, a link or its listen address someone else's)
    # writes nothing, in this shop or any other: no token, no lock, no machine directory.
    refuse_if_served_elsewhere(config)
    config.root.mkdir(mode=0o700, parents=True, exist_ok=True)
    stop = stop or asyncio.Event()
    try:
        lock = acquire_controller_lock(config.root)
    except MachineInUse as e:  # the cell's words ("the cell in shop") for a shop
        raise MachineInUse(str(e).replace("the cell in", "the shop in", 1)) from None
    with lock:
        server = DncServer(config)
        api = ApiServer(
            DncAccess(server),
            config.root,
            listen=config.listen,
            allow_remote=config.allow_remote,
            extra_routes=dashboard_routes,
        )
        server.listeners.append(api.changed)
        # Ctrl-C, SIGTERM: ours from here, as found again once the finally below begins.
        signals = contextlib.ExitStack()
        signals.enter_context(stop_signals(stop.set))
        served = False
        try:
            await server.start()
            await api.start()
            served = True
            names = ", ".join(sorted(config.machines))
            console.print(f"DNC server: {names}; control API on {api.url}", markup=False)
            for line in server.lines.values():
                if line.status.error:
                    err_console.print(line.status.error, markup=False)
            await stop.wait()
        finally:
            signals.close()
            if served:
                await _stopping(server)
            await api.close()
            await server.close()


def refuse_if_served_elsewhere(config: ShopConfig) -> None:
    """Refuse ``dnc serve`` on ``config`` now, before it writes a file, when what it would
    take is taken: the shop served already, a machine's link held by another owner (another
    shop's server, a ``cellctl dnc send``, a cell), its ``[dnc] listen`` address answered
    by another server. MachineInUse naming the holder; UsageError for the address."""
    import socket

    from cellctl.cell.owner import ALREADY_RUN, controller_lock_path
    from cellctl.drivers.base import refuse_if_link_held
    from cellctl.drivers.state import StateStore
    from cellctl.errors import LinkError, MachineInUse, UsageError
    from cellctl.link.listen import parse_listen
    from cellctl.link.lock import refuse_if_held

    try:  # as acquire_controller_lock would say it, in a shop's words
        refuse_if_held(controller_lock_path(config.root), str(config.root), refusal=ALREADY_RUN)
    except MachineInUse as e:
        raise MachineInUse(str(e).replace("the cell in", "the shop in", 1)) from None
    store = StateStore(config.root)  # only looked at: nothing is created by a look
    for m in config.machines.values():
        try:
            refuse_if_link_held(m.url, m.name, store)
        except LinkError:
            continue  # a host name that does not resolve now: served offline, as any other
    if config.listen is None:
        return
    host, port = parse_listen(config.listen, config.allow_remote, table="dnc")
    probe = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    try:  # bound as the API server binds it, then let go at once
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((host, port))
    except OSError as e:
        raise UsageError(
            f'{config.source}: [dnc] listen = "{config.listen}": cannot listen there: '
            f"{(e.strerror or str(e)).lower()} (another server answers on {host}:{port}?): "
            "stop it, or give this shop another port"
        ) from None
    finally:
        probe.close()


async def _stopping(server: DncServer) -> None:
    """Say at once that the server stops and what it does with each transfer in flight;
    end them (bounded), then say how each ended."""
    doing = server.in_flight()
    said = "; ".join(f"{name}: {words}" for name, words in doing.items())
    if said:
        said = f": ending what is in flight the clean way (the rest of its block, then %): {said}"
    err_console.print(f"DNC server stopping{said}", markup=False)
    for name, result in (await server.end_transfers("the DNC server stopped")).items():
        err_console.print(f"{name}: {result}", markup=False)


# -- by hand -----------------------------------------------------------------------------------


#: The phase a transfer's bar shows once it stopped before its end (``dnc stop``, Ctrl-C,
#: the server stopping): never the driver's ``done`` of the tape it cut short.
STOPPED = "stopped"
#: The phase it shows once it failed (the link, the control): the error follows on its line.
FAILED = "failed"


class _TimeLeftColumn(TimeRemainingColumn):
    """The time left, while there is any: none once the transfer stopped."""

    def render(self, task: Task) -> Text:
        if task.fields.get("phase") in (STOPPED, FAILED):
            return Text("")
        return super().render(task)


def _bar_columns() -> tuple[Any, ...]:
    return (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} chars"),
        TextColumn("{task.fields[rate]:>6.0f} chars/s"),
        TextColumn("{task.fields[stops]} buffer stops"),
        TextColumn("{task.fields[phase]}"),
        _TimeLeftColumn(),
    )


def _fields(p: dict[str, Any], elapsed: float) -> dict[str, Any]:
    return {
        "total": max(1, p["chars_total"]),
        "completed": p["chars_sent"],
        "rate": p["chars_per_s"],
        "stops": p["buffer_stops"],
        # A stopped transfer's last progress (stopped_progress) says where it ended.
        "phase": STOPPED if "stopped" in p else p["phase"],
    }


def _transfer(
    ctx: click.Context, shop: Path, use_cell: bool, name: str, program: str, drip: bool
) -> None:
    import uuid

    from cellctl.errors import UsageError
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.status import START_READ
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore, check_program_number, read_program_file
    from cellctl.kinds.iso_cnc.driver import prepare
    from cellctl.kinds.menu import MAX_PROGRAM_CHARS
    from cellctl.ui.calls import LazyBar

    config = shop_config(ctx, shop, use_cell)
    options = machine(config, name).options  # an unknown machine first, nothing created
    # A ticket of its own: Ctrl-C stops this transfer, never another's.
    params: dict[str, Any] = {"program": program, "drip": drip, "ticket": uuid.uuid4().hex}
    path = Path(program)
    store = ShopStore(config.root)
    if path.is_file():  # a file here: its text travels (the server may not see this path)
        data = read_program_file(path)
        if len(data) <= MAX_PROGRAM_CHARS:
            params.update(program=path.name, text=data.decode())
        elif store.a_program_file(path):  # too long for a call: the server reads it
            params.update(program=str(path.resolve()))
        else:
            raise UsageError(
                f"{program}: {len(data)} characters, more than a call carries "
                f"({MAX_PROGRAM_CHARS}): put it in {store.folder(name, 'programs')} and "
                "name it there (O1234, or its path)"
            )
    else:  # refused here, before a byte goes out
        data = read_program_file(store.resolve(name, program, options.o_digits))
    # the O-number and the G-code check with the machine's options: before a byte goes out
    check_program_number(program, data)
    prepare(data, options, Path(params["program"]).name, drip)
    what = "drip-feed" if drip else "read-in"
    # In the words `dnc status` and the log use: READ in EDIT would store a drip-feed in
    # memory instead of running it.
    prompt = f"{name}: {what} of {params['program']}: waiting for read: {START_READ[drip]}"
    stopped: list[str] = []  # the `stopped` field of a transfer's last progress
    shown: list[dict[str, Any]] = []  # the last progress the bar shows
    with LazyBar(_bar_columns(), Path(params["program"]).name, _fields) as bar:
        # said once the server has taken the transfer (its first progress), never before a
        # refusal (the machine busy, its link held elsewhere)
        going = _first_then(lambda: err_console.print(prompt, markup=False), bar.update)

        def update(data: dict[str, Any]) -> None:
            if "stopped" in data:
                stopped.append(str(data["stopped"]))
                if not shown:
                    return  # stopped before it began: no bar to end
                bar.update(data)
            else:
                going(data)
            shown[:] = [data]

        async def transfer() -> Any:
            from cellctl.errors import CellctlError

            try:
                return await call_shop(config, name, "dnc.send", params, update)
            except CellctlError as e:
                if stopped:  # stopped before its end (`dnc stop`, the server stopping)
                    return {"stopped": str(e)}
                if shown:  # said once the bar has ended its line, never glued to it
                    return {"failed": e}
                raise

        result = run(transfer)
        ended = isinstance(result, dict) and ("stopped" in result or "interrupted" in result)
        if ended and shown and "stopped" not in shown[0]:
            # Ended early with no last progress of its own (its answer timed out): the bar
            # still says stopped, not the phase it was last seen in.
            bar.update({**shown[0], "stopped": ""})
        if isinstance(result, dict) and "failed" in result:
            bar.update({**shown[0], "phase": FAILED})
    if isinstance(result, dict) and "failed" in result:
        fail(result["failed"])
    _ended_early(result)
    console.print(result["message"], markup=False)


def _first_then(
    first: Callable[[], object], then: Callable[[dict[str, Any]], None]
) -> Callable[[dict[str, Any]], None]:
    """A progress callback that calls ``first()`` once, at the first progress, then ``then``."""
    said = [False]

    def update(data: dict[str, Any]) -> None:
        if not said[0]:
            said[0] = True
            first()
        then(data)

    return update


#: The exit code of a transfer stopped before its end: by its sender's Ctrl-C (as ``run``
#: exits on Ctrl-C), by ``dnc stop``, by the server stopping. Not 0: the program did not all
#: go; not a failure's code (3, 4, 5): the link and the control did what they were asked.
STOPPED_EXIT = 130


def _ended_early(result: Any) -> None:
    """A transfer stopped before its end (Ctrl-C, ``dnc stop``, the server stopping): say
    how it ended and exit :data:`STOPPED_EXIT`."""
    if isinstance(result, dict) and "interrupted" in result:
        err_console.print(f"interrupted: {result['interrupted']}", markup=False)
        sys.exit(STOPPED_EXIT)
    if isinstance(result, dict) and "stopped" in result:
        err_console.print(str(result["stopped"]), markup=False, soft_wrap=True)
        sys.exit(STOPPED_EXIT)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("program")
@shop_options
@click.pass_context
def send(ctx: click.Context, name: str, program: str, shop: Path, use_cell: bool) -> None:
    """Send PROGRAM (a file, or O1234 of the machine's programs/) into the control's memory."""
    _transfer(ctx, shop, use_cell, name, program, drip=False)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("program")
@shop_options
@click.pass_context
def drip(ctx: click.Context, name: str, program: str, shop: Path, use_cell: bool) -> None:
    """Drip-feed PROGRAM: the control runs it as it arrives (RMT / DNC mode)."""
    _transfer(ctx, shop, use_cell, name, program, drip=True)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.option(
    "--timeout",
    # the API's own limit (dnc.receive: above 0, at most an hour), said here as --timeout
    type=click.FloatRange(0, 3600, min_open=True),
    default=600.0,
    show_default=True,
    help="Seconds to wait (at most 3600).",
)
@shop_options
@click.pass_context
def receive(ctx: click.Context, name: str, timeout: float, shop: Path, use_cell: bool) -> None:
    """Keep what the control punches (select the program, press PUNCH on the control)."""
    from cellctl.kinds.iso_cnc.dnc.config import machine

    config = shop_config(ctx, shop, use_cell)
    machine(config, name)
    prompt = _first_then(
        lambda: err_console.print(f"{name}: waiting for the control: press PUNCH on it"),
        lambda data: None,
    )
    result = run(lambda: call_shop(config, name, "dnc.receive", {"timeout": timeout}, prompt))
    for item in result["programs"]:
        if "refused" in item:
            console.print(f"refused: {item['refused']}", markup=False)
        elif "request" in item:
            console.print(f"request: {item['request']}", markup=False)
        else:
            console.print(f"received O{item['program']:04d}: {item['kept']}", markup=False)


@dnc.command("stop")
@click.argument("name", metavar="MACHINE")
@shop_options
@click.pass_context
def stop_transfer(ctx: click.Context, name: str, shop: Path, use_cell: bool) -> None:
    """Stop the read-in or drip-feed in flight on MACHINE (or drop the request waiting for
    its read). A read under way is ended the clean way: the rest of its block, then %."""
    from cellctl.cell.owner import controller_holder
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.handstop import (
        hand_holder,
        in_use_here,
        is_hand_transfer,
        stop_hand_transfer,
    )

    config = shop_config(ctx, shop, use_cell)
    machine(config, name)  # an unknown machine first
    if controller_holder(config.root) is None:  # no server: a hand command may hold it
        found = hand_holder(config, name)
        if found is not None:
            if not is_hand_transfer(found):  # a `dnc receive`, or another `dnc stop`
                refusal = in_use_here(config, name)
                assert refusal is not None
                fail(refusal)
            said = run(lambda: stop_hand_transfer(config, name, found))
            console.print(said, markup=False, soft_wrap=True)
            return
    result = run(lambda: call_shop(config, name, "dnc.stop", {}))
    console.print(str(result.get("message") or f"{name}: nothing was running"), markup=False)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("received", required=False)
@click.option("--against", help="The sent file to compare with (default: the last O-number sent).")
@click.option("--ignore-spaces", is_flag=True, help="Spaces inside blocks do not count.")
@shop_options
@click.pass_context
def diff(
    ctx: click.Context,
    name: str,
    received: str | None,
    against: str | None,
    ignore_spaces: bool,
    shop: Path,
    use_cell: bool,
) -> None:
    """Compare a received program (a file or O1234: its newest copy) with what was sent.

    Exit 0 when they match, 1 when they differ.
    """
    import re

    from cellctl.errors import UsageError
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.diff import compare
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore, as_given, read_program_file

    config = shop_config(ctx, shop, use_cell)
    machine(config, name)  # an unknown machine is named as such; nothing is created
    store = ShopStore(config.root)
    if received is not None and Path(received).is_file():
        got = Path(received)
        number = None
    else:
        found = None if received is None else re.fullmatch(r"[Oo:]?(\d{1,8})", received)
        if received is not None and found is None:
            raise UsageError(f"{received}: no such file, and not a program number like O1234")
        wanted = None if found is None else int(found.group(1))
        copies = store.received(name, wanted)
        if not copies:
            which = "nothing" if wanted is None else f"no {as_given(wanted, received or '')}"
            raise UsageError(
                f"{which} received from {name} yet (in {store.folder(name, 'received')}): "
                f"press PUNCH on the control while `cellctl dnc receive {name}` or "
                "`dnc serve` runs"
            )
        got, number = copies[-1].path, copies[-1].number
    if against is not None:
        sent_path = Path(against)
    else:
        from cellctl.kinds.iso_cnc.tape import o_number, unframe

        number = number if number is not None else o_number(unframe(read_program_file(got)))
        sent = store.sent(name, number) if number is not None else []
        if not sent:
            shown = as_given(number, received or "") if number is not None else "its program"
            raise UsageError(f"nothing sent to {name} as {shown}: give --against FILE")
        sent_path = sent[-1].path
    result = compare(
        read_program_file(sent_path),
        read_program_file(got),
        sent_name=str(sent_path),
        received_name=str(got),
        spaces=not ignore_spaces,
    )
    if result.same:
        console.print(f"{got.name} matches {sent_path.name} ({result.blocks_sent} blocks)")
        return
    console.print(result.text, markup=False, soft_wrap=True)
    sys.exit(1)


@dnc.command()
@shop_options
@json_option
@click.pass_context
def status(ctx: click.Context, shop: Path, use_cell: bool, as_json: bool) -> None:
    """Each machine's state: through the running server, else its log's last line."""
    from cellctl.cell.owner import controller_holder
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore
    from cellctl.service.client import attach

    config = shop_config(ctx, shop, use_cell)
    if controller_holder(config.root) is None:
        store = ShopStore(config.root)
        logged = {name: store.log_lines(name, 1) for name in sorted(config.machines)}
        if as_json:
            print_json(
                {
                    n: {"server": False, "log": last[0] if last else None}
                    for n, last in logged.items()
                }
            )
            return
        for name, last in logged.items():
            console.print(f"{name}: no server runs; {last[0] if last else 'no log'}", markup=False)
        return

    async def main() -> dict[str, Any]:
        async with await attach(config.root) as api:
            answer: dict[str, Any] = await api.call("cell.status")
            return answer

    machines = dict(sorted(run(main)["machines"].items()))
    if as_json:
        print_json(machines)
        return
    for name, m in machines.items():
        console.print(status_text(name, m), markup=False, soft_wrap=True)


def status_text(name: str, m: dict[str, Any]) -> str:
    """A machine of ``cell.status`` in one line, with what the console and dashboard show:
    its state, a transfer's characters of total, rate, buffer stops (in its state), stall
    and time left, and its last refusal or error."""
    condition, state = str(m["condition"]), str(m["state"])
    # "mill1: idle", not "mill1: idle: idle": the condition once when the state says it.
    text = f"{name}: {state}" if state == condition else f"{name}: {condition}: {state}"
    p = m.get("progress") or {}
    if p:
        done, total = int(p.get("done") or 0), int(p.get("total") or 0)
        # no total (a punch, until its end): the characters so far, no share of them
        parts = [f"{done}/{total} chars ({done / total:.0%})" if total else f"{done} chars"]
        parts.append(str(p.get("phase") or ""))
        if p.get("rate_per_s"):
            parts.append(f"{p['rate_per_s']:.0f} chars/s")
        if p.get("stall_s") is not None:
            parts.append(f"stall {p['stall_s']:.1f} s")
        if p.get("time_left_s") is not None:
            parts.append(f"{_duration(float(p['time_left_s']))} left")
        text += " | " + ", ".join(x for x in parts if x)
    error = (m.get("error") or {}).get("text")
    if error:
        text += f" | last error: {error}"
    return text


def _duration(seconds: float) -> str:
    """``3 s``, ``4 min 05 s``, ``1 h 02 min`` (as the console shows time left)."""
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"
