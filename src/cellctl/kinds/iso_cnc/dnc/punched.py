"""What a control punched to the DNC server: each program kept in the shop's received folder,
or, a request (``O9999 (LOAD O1234)``), answered with its program on the control's next read.
:class:`~cellctl.kinds.iso_cnc.dnc.line.DncLine` hands each whole punch here."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.kinds.iso_cnc.dnc.request import Request, parse_request
from cellctl.kinds.iso_cnc.dnc.status import Activity
from cellctl.kinds.iso_cnc.dnc.store import check_program_number, o_name, read_program_file
from cellctl.kinds.iso_cnc.options import off_loop, prepare
from cellctl.kinds.iso_cnc.tape import split_programs, unframe

if TYPE_CHECKING:
    from cellctl.kinds.iso_cnc.dnc.line import DncLine


async def take_punch(line: DncLine, data: bytes) -> list[dict[str, Any]]:
    """Split a punched tape into programs: answer a request (the control's next read sends
    its program), keep the others in the shop's received folder; what became of each."""
    now = current_clock().now()
    done: list[dict[str, Any]] = []
    refused = False  # an error of this punch stays, whatever it brought after it
    for program in split_programs(unframe(data)):
        raw = program.text.encode("latin-1", "replace")
        try:
            request = parse_request(program.number, program.text, line.config.request)
        except UsageError as e:
            kept = line.store.keep_received(line.name, program.number, raw, now)
            line._note(f"request refused: {e}; kept as {kept.path.name}")
            line._set(last=f"request refused: {e}", error=str(e))
            refused = True
            done.append({"program": program.number, "refused": str(e), "kept": str(kept.path)})
            continue
        if request is not None:
            answer = await _request(line, request, program.number, raw, now)
            refused = refused or "refused" in answer
            done.append(answer)
            continue
        kept = line.store.keep_received(line.name, program.number, raw, now)
        message = f"received {o_name(program.number)} ({len(raw)} chars) as {kept.path.name}"
        line._note(message)
        # Kept: an earlier error is behind, as after a program sent (dnc status's last error).
        line._set(last=message, error=line.status.error if refused else "")
        done.append({"program": program.number, "kept": str(kept.path), "chars": len(raw)})
    waiters, line.punch_waiters = line.punch_waiters, []
    for waiter in waiters:
        if not waiter.done():
            waiter.set_result(done)
    return done


async def _request(
    line: DncLine, request: Request, number: int, raw: bytes, now: float
) -> dict[str, Any]:
    try:
        options = line.config.options
        path = line.store.program(line.name, request.program, options.o_digits)
        data = read_program_file(path)
        check_program_number(path.name, data)
        # The G-code check too: a program the read would refuse (empty, a block too long)
        # is the request's refusal now, not a failed read-in once the control reads.
        await off_loop(data, prepare, data, options, path.stem, request.drip)
    except UsageError as e:  # the punched request is kept as received, as docs/dnc.md says
        kept = line.store.keep_received(line.name, number, raw, now)
        line._note(f"request {request} refused: {e}; kept as {kept.path.name}")
        line._set(last=f"request {request} refused", error=f"request {request} refused: {e}")
        return {"request": str(request), "refused": str(e), "kept": str(kept.path)}
    line.pending, line.pending_since = request, current_clock().now()
    message = f"request: {request} ({path.name}) on the control's next read"
    line._note(message)
    line._set(activity=Activity.WAITING, pending=str(request), last=message, error="")
    return {"request": str(request), "file": str(path)}
