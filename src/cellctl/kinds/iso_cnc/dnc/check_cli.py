"""``cellctl dnc check MACHINE PROGRAM``: what ``dnc send`` and ``dnc drip`` would make of a
program on that machine, before anyone stands at the control::

    $ cellctl dnc check mill1 O1234 --dir shop
    O1234 (O1234 surface.nc) for mill1 at 9600,7E2: 188 blocks that take time, 4,691
      characters of program (what the control stores; its tape, with leader, % and trailer,
      is 4,734)
      runs 6.4 s (the motion model); the tape is 5.4 s on the line
      drip-feed: the axes wait 1.4 s for data at 132 blocks (longest 0.02 s, for
      `G1 X4.000 Y14.500 Z-0.010`); it ends 7.8 s after the control's first DC1
      no wait from 19200 baud

The forecast is the driver's own model of the control's buffer (``buffer.py``) played at the
machine's line rate: where blocks run faster than the line brings them, the tool dwells and
may mark the part. Exit 1 when the program would be refused (every problem, with its line:
the G-code check's, and a file whose name and text disagree on its O-number), as every
``cellctl ... check`` does; 2 when there is nothing to check (an unknown machine, no such
program, a file that is not text, an ambiguous O-number).
"""

from __future__ import annotations

import dataclasses
import sys
from array import array
from pathlib import Path

import click

from cellctl.kinds.iso_cnc.dnc.shopopts import shop_config, shop_options
from cellctl.ui.common import console

#: Line rates tried above the machine's when its drip-feed would wait (the usual ones).
BAUD_RATES = (4800, 9600, 19200, 38400, 57600, 115200)


def _hms(seconds: float) -> str:
    """Seconds as a user reads them: ``6.4 s``, ``0.015 s`` (two figures under a second:
    a short wait is never ``0.0 s``), ``0:20:05`` from a minute."""
    if seconds <= 0:
        return "0 s"
    if seconds < 0.001:
        return "under 0.001 s"
    if seconds < 0.995:  # 0.995 and more read 1.0 s, as tenths
        return f"{seconds:.2g} s"
    if seconds < 60:
        return f"{seconds:.1f} s"
    whole = round(seconds)
    return f"{whole // 3600}:{whole % 3600 // 60:02d}:{whole % 60:02d}"


@click.command("check", short_help="Refused or not; how long its drip-feed waits for data")
@click.argument("name", metavar="MACHINE")
@click.argument("program")
@shop_options
@click.pass_context
def check(ctx: click.Context, name: str, program: str, shop: Path, use_cell: bool) -> None:
    """Check PROGRAM (a file, or O1234 of the machine's programs/) as `dnc send` would, and
    forecast its drip-feed at the machine's line rate: run time, line time, and how long the
    axes would wait for data. Exit 1 if it would be refused."""
    from cellctl.errors import UsageError
    from cellctl.kinds.iso_cnc import gcode
    from cellctl.kinds.iso_cnc.buffer import forecast_drip, tape_blocks
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.store import (
        ShopStore,
        check_program_number,
        program_chars,
        read_program_file,
    )
    from cellctl.kinds.iso_cnc.options import prepare, program_text

    config = shop_config(ctx, shop, use_cell)
    chosen = machine(config, name)
    path = ShopStore(config.root).resolve(name, program, chosen.options.o_digits)
    data = read_program_file(path)
    o = chosen.options
    # As a drip-feed takes it (cellctl's widest caps); a read-in's narrower cap is said below.
    found = gcode.errors(program_text(data, str(path)), o.check_options(drip=True))
    problems = [p.format(str(path)) for p in found]
    try:  # a problem of the program like the others: said with them, exit 1
        check_program_number(path.name, data)
    except UsageError as e:
        problems.insert(0, str(e))
        found.insert(0, gcode.Finding(1, 0, str(e)))
    for problem in problems:
        console.print(problem, style="red", markup=False, soft_wrap=True)
    if problems:
        said = f"{path}: {gcode.counted(found)}: cellctl refuses to send it to {name}"
        console.print(said, soft_wrap=True)
        sys.exit(1)
    framed = prepare(data, o, path.name, drip=True)
    # Compact (16 bytes a block), for the forecasts at several rates: never a list of tuples.
    ends, times = array("q"), array("d")
    for end, seconds in tape_blocks(framed, o.motion(), o.motion_scale):
        ends.append(end)
        times.append(seconds)
    settings = chosen.settings
    forecast = forecast_drip(
        framed, zip(ends, times, strict=True), settings.char_time, o.sender(settings.char_time)
    )
    count = forecast.timed
    lines = [
        f"{program} ({path.name}) for {name} at {settings}: {count:,} "
        f"block{'' if count == 1 else 's'} that take{'s' if count == 1 else ''} time, "
        f"{program_chars(data):,} characters of program (what the control stores; its tape, "
        f"with leader, % and trailer, is {forecast.chars:,})",
        f"  runs {_hms(forecast.run_s)} (the motion model); the tape is "
        f"{_hms(forecast.line_s)} on the line",
    ]
    ending = f"it ends {_hms(forecast.end_s)} after the control's first DC1"
    if not forecast.stalls:
        lines.append(f"  drip-feed: the axes never wait for data; {ending}")
    else:
        lines.append(
            f"  drip-feed: the axes wait {_hms(forecast.stall_s)} for data at "
            f"{forecast.stalls:,} block{'' if forecast.stalls == 1 else 's'} (longest "
            f"{_hms(forecast.longest_s)}, for "
            f"`{forecast.longest_block}`); {ending}"
        )
        faster = [b for b in BAUD_RATES if b > settings.baudrate]
        for baud in faster:
            rate = dataclasses.replace(settings, baudrate=baud)
            blocks = zip(ends, times, strict=True)
            tried = forecast_drip(framed, blocks, rate.char_time, o.sender(rate.char_time))
            if not tried.stalls:
                lines.append(f"  no wait from {baud} baud")
                break
        else:
            top = max(BAUD_RATES)
            lines.append(
                f"  it waits at every rate up to {top} baud: its blocks run faster than a line "
                "brings them (longer segments, or a slower feed)"
            )
    if o.motion_scale != 1:  # an emulated control's times, not a real machine's
        lines.append(
            f"  times for options.motion_scale = {o.motion_scale:g}: an emulated control "
            f"{o.motion_scale:g} times faster than the machine (a real machine's is 1)"
        )
    caps = o.check_options(drip=False)
    if len(data) > caps.max_bytes or data.count(b"\n") > caps.max_blocks:
        lines.append(
            f"  drip-feed only: more than a read-in takes ({caps.max_bytes:,} characters, "
            f"{caps.max_blocks:,} blocks: cellctl's cap, not the control's)"
        )
    for text_line in lines:
        console.print(text_line, markup=False, soft_wrap=True)
