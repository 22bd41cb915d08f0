"""How a hand command of ``cellctl dnc`` reaches a machine::

    result = await call_shop(config, "mill1", "dnc.send", params, progress)

Through the running ``dnc serve``'s control API when one runs on the shop, else on the
machine's link opened here, under its owner locks. A transfer (``params`` with a
``ticket``) stops on Ctrl-C or SIGTERM, and only that transfer.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any

from cellctl.ui.common import err_console, stop_signals

if TYPE_CHECKING:
    from cellctl.kinds.iso_cnc.dnc.config import ShopConfig

__all__ = ["STOPPED_ANSWER_S", "STOP_CALL_S", "call_shop"]


async def call_shop(
    config: ShopConfig,
    name: str,
    method: str,
    params: dict[str, Any],
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> Any:
    """``method`` on machine ``name``: through the running server's API, or on the link
    opened here (under its owner locks) when no server runs on the shop.

    With a ``ticket`` in ``params`` (a transfer), Ctrl-C or SIGTERM stops that transfer, and
    only it (``dnc.stop`` with the ticket): the answer is then ``{"interrupted": words}``.
    On the link opened here, ``cellctl dnc stop`` from another terminal stops it too
    (:mod:`cellctl.kinds.iso_cnc.dnc.handstop`): ``{"stopped": words}``."""
    from cellctl.cell.owner import controller_holder
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.server import TRANSFER_S
    from cellctl.service.client import attach

    machine(config, name)
    params = {"machine": name, **params}
    stop = {"machine": name, "ticket": params.get("ticket")}
    if controller_holder(config.root) is not None:
        async with await attach(config.root) as api:
            return await _stoppable(
                api.call(method, params, progress, timeout=TRANSFER_S),
                lambda: api.call("dnc.stop", stop, timeout=STOP_CALL_S),
                stop["ticket"],
            )
    if stop["ticket"] is None:
        return await _call_here(config, name, method, params, progress, None)
    from cellctl.kinds.iso_cnc.dnc.handstop import hand_stop_signal

    hand = asyncio.Event()
    # Taken before the machine's lock, whose record names this process as a transfer that
    # `dnc stop` may signal: from then on the signal stops it, never kills it.
    with hand_stop_signal(hand):
        return await _call_here(config, name, method, params, progress, hand)


async def _call_here(
    config: ShopConfig,
    name: str,
    method: str,
    params: dict[str, Any],
    progress: Callable[[dict[str, Any]], None] | None,
    hand: asyncio.Event | None,
) -> Any:
    """``call_shop`` on the machine's link opened here (no server runs on the shop)."""
    from cellctl.errors import MachineInUse
    from cellctl.kinds.iso_cnc.dnc.access import DncAccess
    from cellctl.kinds.iso_cnc.dnc.handstop import in_use_here
    from cellctl.kinds.iso_cnc.dnc.server import DncServer
    from cellctl.service.methods import Dispatcher

    one = dataclasses.replace(config, machines={name: config.machines[name]})
    server = DncServer(one)
    try:
        await server.start(retry=False)  # its own task listens, as under `dnc serve`
    except MachineInUse as e:  # another hand command has it: say what works instead
        raise in_use_here(config, name) or e from None
    try:
        line = server.line(name)
        if line.driver is None:  # its link could not be opened: say why at once
            from cellctl.errors import LinkError

            raise LinkError(line.status.error)
        dispatcher = Dispatcher(DncAccess(server))
        ticket = params.get("ticket")
        return await _stoppable(
            dispatcher.call(method, params, progress),
            lambda: dispatcher.call("dnc.stop", {"machine": name, "ticket": ticket}),
            ticket,
            hand=hand,
            stop_by_hand=lambda: dispatcher.call("dnc.stop", {"machine": name}),
            begun=lambda: bool(line.claimed) or line.transfer is not None,
        )
    finally:
        await server.close()


#: Seconds a client waits for ``dnc.stop``'s answer (the server's own deadline is 10 s).
STOP_CALL_S = 40.0
#: Seconds a stopped transfer's own answer is waited for once the stop has answered.
STOPPED_ANSWER_S = 10.0


async def _stoppable(
    work: Coroutine[Any, Any, Any],
    stop: Callable[[], Coroutine[Any, Any, Any]],
    ticket: str | None,
    *,
    hand: asyncio.Event | None = None,
    stop_by_hand: Callable[[], Coroutine[Any, Any, Any]] | None = None,
    begun: Callable[[], bool] | None = None,
) -> Any:
    """``work``; with a ticket, Ctrl-C / SIGTERM meanwhile calls ``stop`` and returns
    ``{"interrupted": how the transfer ended}``; ``hand`` set (``dnc stop`` from elsewhere)
    calls ``stop_by_hand`` and returns ``{"stopped": how it ended}``. ``begun``: whether the
    transfer has been taken by the machine yet (one that has not is cancelled here: nothing
    of it went out)."""
    from cellctl.clock import current_clock
    from cellctl.errors import CellctlError

    if ticket is None:
        return await work
    stopped = asyncio.Event()
    with stop_signals(stopped):
        task = asyncio.ensure_future(work)
        signals = [asyncio.ensure_future(stopped.wait())]
        if hand is not None:
            signals.append(asyncio.ensure_future(hand.wait()))
        try:
            await asyncio.wait({task, *signals}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiting in signals:
                waiting.cancel()
        if task.done():
            return task.result()
        by_hand = hand is not None and hand.is_set() and not stopped.is_set()
        said_as = "stopped" if by_hand else "interrupted"
        if by_hand:
            err_console.print("stopped by `cellctl dnc stop`: ending this transfer ...")
        else:
            err_console.print("interrupted: stopping this transfer ...", markup=False)
        if begun is not None and not begun():
            task.cancel()  # not taken by the machine yet: nothing of it went out
            with contextlib.suppress(asyncio.CancelledError, CellctlError):
                await task
            why = "stopped by hand" if by_hand else "stopped by its sender"
            return {
                said_as: f"{why}: the transfer was cancelled before it began (nothing was sent)"
            }
        try:
            ending = stop_by_hand if by_hand and stop_by_hand is not None else stop
            answer = await ending()
            said = str(answer["message"])
        except CellctlError as e:
            said = str(e)
        else:
            if by_hand and answer.get("stopped") is False:
                # `dnc stop` when all of it was out already changes nothing: the transfer
                # ends as it would have (its own deadline), 0 and logged as such.
                err_console.print(said, markup=False, highlight=False)
                return await task
        try:  # the transfer's own answer says where it ended
            async with current_clock().timeout(STOPPED_ANSWER_S):
                return await task
        except CellctlError as e:
            said = str(e)
        except TimeoutError:
            task.cancel()  # a drip-feed's end is out; the control runs what it holds
        return {said_as: said}
