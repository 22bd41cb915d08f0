"""How the CLI and the console reach a cell: through the API of the controller that runs it,
or, when none runs, straight to the machines (standalone). Both answer the same calls::

    async with await open_cell(Path("cell"), refs) as cell:   # refs: machines it may open
        print(cell.mode)                                       # "attached" or "standalone"
        status = await cell.call("robot.status", {"machine": "robot"})
        snapshot = await cell.subscribe(on_update)             # on_update(changes)

Every call has a deadline; a refused call raises the same typed error the CLI would. A plan
(``plan.run``) is waited for while it plays, not for one deadline (:func:`plan_call`)::

    async with own_session(cell) as apart:                     # given up: its play ends
        answer = await plan_call(apart, {"shift": "8h"}, 8 * 3600.0, on_progress)
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import pwd
import socket
import struct
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from cellctl.clock import current_clock
from cellctl.errors import (
    AccessDenied,
    CellctlError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    UsageError,
)
from cellctl.mailbox import MAILBOX_FILE
from cellctl.service.rpc import SOCKET_FILE, Caller, error_from_object
from cellctl.service.token import TOKEN_ENV, check_unexpired, client_token, identify
from cellctl.tasks import cancel_and_wait

if TYPE_CHECKING:
    from websockets.asyncio.client import ClientConnection

    # A command that asks a running controller needs none of these: the standalone cell
    # (this process on the machines' links) imports them when it is made.
    from cellctl.service.access import LocalCell
    from cellctl.service.machines import MachineRef
    from cellctl.service.status import CellStatus

Update = Callable[[dict[str, Any]], None]
Progress = Callable[[dict[str, Any]], None]

#: Seconds a call may take: reads, and manual functions (a mill download waits for the cut).
CALL_TIMEOUT = 30.0
MACHINE_CALL_TIMEOUT = 3600.0
#: A plan plays up to 31 days of the cell: seconds to minutes of the computer's time (a
#: plan is waited for while it plays, past this: :func:`plan_call`).
PLAN_CALL_TIMEOUT = 600.0
#: How long a plan of the cell may go unheard: its play tells how far it has gone every
#: minute of plan time (a few times a second); nothing of it for this long, it is stuck.
PLAN_SILENCE_S = 600.0
CONNECT_TIMEOUT = 5.0
#: How often a standalone cell's status is looked at for subscribers.
LOCAL_POLL = 0.5


#: What a client says when the server refused its token.
TOKEN_REFUSED = "the control API refused the token"


class ImpostorSocket(AccessDenied):
    """The process on ``api.sock`` is not the cell's controller: no token was sent to it."""


async def _connect_unix(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.setblocking(False)
    try:
        async with asyncio.timeout(CONNECT_TIMEOUT):
            target = os.path.realpath(path)  # noqa: ASYNC240 - a local lookup, no I/O wait
            await asyncio.get_running_loop().sock_connect(sock, target)
    except BaseException:
        sock.close()
        raise
    return sock


def _user(uid: int) -> str:
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def check_peer(sock: socket.socket, socket_path: Path) -> None:
    """AccessDenied unless the process listening on ``sock`` (``<cell>/api.sock``) is the
    cell's controller: run by this user or by the cell directory's owner, and the process
    the controller's lock names when it names one (Linux's SO_PEERCRED). Whoever can write
    the cell directory could otherwise put a socket of their own in its place and be sent
    the token."""
    directory = Path(socket_path).parent
    creds = getattr(socket, "SO_PEERCRED", None)
    if creds is None:  # no peer credentials here: the socket file's owner stands for them
        pid, uid = 0, os.stat(os.path.realpath(socket_path)).st_uid
    else:
        pid, uid, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, creds, 12))
    owners = {os.getuid(), os.stat(directory).st_uid}
    refused = f"not sent the API token to {socket_path}: "
    remedy = (
        f"someone may have put their own socket in its place: see who can write {directory} "
        f"(`ls -ld {directory}`; `chmod go-w {directory}`) and start `cellctl run` again"
    )
    if uid not in owners:
        raise ImpostorSocket(
            refused + f"the process listening there (pid {pid}) runs as {_user(uid)}, not as "
            f"{' or '.join(_user(u) for u in sorted(owners))}; " + remedy
        )
    from cellctl.cell.owner import controller_holder

    holder = controller_holder(directory)
    here = holder is not None and holder.pid and holder.host in ("", socket.gethostname())
    if pid and here and holder is not None and holder.pid != pid:
        raise ImpostorSocket(
            refused + f"the process listening there (pid {pid}) is not the cell's "
            f"controller ({holder}); " + remedy
        )


def call_timeout(method: str) -> float:
    """The deadline for ``method``."""
    family = method.split(".", 1)[0]
    if family == "plan":
        return PLAN_CALL_TIMEOUT
    return MACHINE_CALL_TIMEOUT if family in ("robot", "mill") else CALL_TIMEOUT


class RemoteCell:
    """A JSON-RPC client on a running controller's API (Unix socket or TCP)."""

    mode = "attached"

    def __init__(
        self, ws: ClientConnection, again: Callable[[], Awaitable[RemoteCell]] | None = None
    ) -> None:
        self._ws = ws
        self._again = again  # another connection as this one was made (another())
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._progress: dict[int, Progress] = {}
        self._updates: list[Update] = []
        self._reader = asyncio.create_task(self._read())
        self.closed = asyncio.Event()

    @classmethod
    async def connect(
        cls, *, token: str, socket_path: Path | None = None, url: str | None = None
    ) -> RemoteCell:
        """Connect to ``socket_path`` (a cell's ``api.sock``) or ``url`` (``ws://host:port``)."""
        # websockets is imported by a command that finds a controller to talk to, not by
        # every command that looks whether one runs.
        from websockets.asyncio.client import connect, unix_connect
        from websockets.exceptions import InvalidStatus, WebSocketException

        headers = {"Authorization": f"Bearer {token}"}
        try:
            if socket_path is not None:
                # Connected, and its peer checked, before the token goes out on it.
                sock = await _connect_unix(socket_path)
                try:
                    check_peer(sock, socket_path)
                except BaseException:
                    sock.close()
                    raise
                ws = await unix_connect(
                    None,
                    "ws://localhost/websocket",
                    sock=sock,
                    additional_headers=headers,
                    open_timeout=CONNECT_TIMEOUT,
                    max_size=None,
                    proxy=None,
                )
            else:
                assert url is not None
                ws = await connect(
                    url.rstrip("/") + "/websocket",
                    additional_headers=headers,
                    open_timeout=CONNECT_TIMEOUT,
                    max_size=None,
                    proxy=None,
                )
        except InvalidStatus as e:
            if e.response.status_code in (401, 403):
                raise AccessDenied(TOKEN_REFUSED) from None
            raise LinkError(f"the control API refused the connection: {e}") from None
        except TimeoutError:
            raise LinkTimeout("the control API did not answer within 5 s") from None
        except (OSError, WebSocketException) as e:
            raise LinkError(f"cannot reach the control API: {e}") from None

        async def again() -> RemoteCell:
            return await cls.connect(token=token, socket_path=socket_path, url=url)

        return cls(ws, again)

    async def another(self) -> RemoteCell:
        """A second connection to the same API, as the same caller (its token): a read
        called on it ends when it is closed (the API ends a plan's play whose session
        closed), whatever this one goes on with. LinkError if it cannot be made."""
        if self._again is None:
            raise LinkError("this connection to the control API cannot be opened again")
        return await self._again()

    async def _read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for text in self._ws:
                found = json.loads(text)
                # A batch's answers come as one array (JSON-RPC 2.0).
                for message in found if isinstance(found, list) else [found]:
                    if isinstance(message, dict):
                        self._take(message)
        except (ConnectionClosed, ValueError):
            pass
        finally:
            self.closed.set()
            for future in self._pending.values():
                if not future.done():
                    future.set_exception(LinkClosed("the control API closed the connection"))
            self._pending.clear()

    def _take(self, message: dict[str, Any]) -> None:
        """One answer or notification from the server."""
        if "id" in message and message.get("id") in self._pending:
            future = self._pending.pop(message["id"])
            self._progress.pop(message["id"], None)
            if future.done():
                return
            if "error" in message:
                future.set_exception(error_from_object(message["error"]))
            else:
                future.set_result(message.get("result"))
        elif message.get("method") == "notify_progress":
            params = message.get("params", {})
            callback = self._progress.get(params.get("id"))
            if callback is not None:
                callback(params)
        elif message.get("method") == "notify_status_update":
            for update in list(self._updates):
                update(message.get("params", {}))

    async def call(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        progress: Progress | None = None,
        *,
        timeout: float | None = None,
    ) -> Any:
        """Call ``method``; its result, or the typed error it raised."""
        from websockets.exceptions import ConnectionClosed

        if self.closed.is_set():
            raise LinkClosed("the control API closed the connection")
        rid = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[rid] = future
        if progress is not None:
            self._progress[rid] = progress
        request = {"jsonrpc": "2.0", "id": rid, "method": method, "params": params or {}}
        try:
            await self._ws.send(json.dumps(request))
        except ConnectionClosed:
            self._pending.pop(rid, None)
            raise LinkClosed("the control API closed the connection") from None
        limit = timeout if timeout is not None else call_timeout(method)
        try:
            async with asyncio.timeout(limit):
                return await future
        except TimeoutError:
            raise LinkTimeout(
                f"{method}: no answer from the control API within {limit:g} s"
            ) from None
        finally:
            self._pending.pop(rid, None)
            self._progress.pop(rid, None)

    async def subscribe(self, update: Update) -> dict[str, Any]:
        """The status now; ``update(changes)`` is called with every change pushed after it."""
        self._updates.append(update)
        result: dict[str, Any] = await self.call("cell.subscribe")
        return result

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await self._ws.close()
        self._reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._reader

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


class StandaloneCell:
    """The same calls, served in this process on links it opens itself (holding their locks)."""

    mode = "standalone"

    def __init__(self, access: LocalCell) -> None:
        from cellctl.service.methods import Dispatcher

        self.access = access
        self.dispatcher = Dispatcher(access)
        self.caller = env_caller(access.directory)
        self._updates: list[Update] = []
        self._poller: asyncio.Task[None] | None = None

    async def call(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        progress: Progress | None = None,
        *,
        timeout: float | None = None,
    ) -> Any:
        limit = timeout if timeout is not None else call_timeout(method)
        try:
            async with asyncio.timeout(limit):
                return await self.dispatcher.call(
                    method, params or {}, progress, caller=self.caller
                )
        except TimeoutError:
            raise LinkTimeout(f"{method}: not done within {limit:g} s") from None

    async def subscribe(self, update: Update) -> dict[str, Any]:
        self._updates.append(update)
        status = self.access.status()
        if self._poller is None:
            self._poller = asyncio.create_task(self._poll(status))
        return status.model_dump(mode="json")

    async def _poll(self, last: CellStatus) -> None:
        from cellctl.service.status import difference

        while True:
            await current_clock().sleep(LOCAL_POLL)
            try:
                await self.access.refresh()
                status = self.access.status()
            except CellctlError:
                continue
            changes = difference(last, status)
            last = status
            if not changes.empty():
                pushed = changes.as_json()
                for update in list(self._updates):
                    update(pushed)

    async def close(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._poller
        await self.access.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


CellClient = RemoteCell | StandaloneCell


@contextlib.asynccontextmanager
async def own_session(cell: Any) -> AsyncIterator[Any]:
    """``cell`` for a call that must end when its caller gives it up: a :class:`RemoteCell`'s
    on a connection of its own, closed after (the API ends a plan whose session closed, not
    only when ``cell`` closes); any other cell as it is (a standalone cell's call runs in
    this process and ends with its task). Used as ``async with own_session(cell) as c:``."""
    if not isinstance(cell, RemoteCell) or cell._again is None:
        yield cell
        return
    apart = await cell.another()
    try:
        yield apart
    finally:
        await apart.close()


async def plan_call(
    cell: Any,
    params: dict[str, Any],
    span_s: float,
    progress: Progress | None = None,
    *,
    silence_s: float = PLAN_SILENCE_S,
) -> Any:
    """``plan.run`` on ``cell`` (a :func:`open_cell` client), its progress to ``progress``:
    waited for while its play goes on, not for the API's one deadline of any call (a plan
    of days on a busy cell plays longer than that). Given up (:class:`LinkTimeout`) when
    nothing of it is heard for ``silence_s``, or once it has taken ``span_s``, the plan's
    own span (a plan slower than the cell is no plan); the call is cancelled then (its play
    ends when its session closes: :func:`own_session`). The CLI, the factory's plan and the
    console's WHAT IF all wait so."""
    clock = current_clock()
    heard = clock.monotonic()

    def told(data: dict[str, Any]) -> None:
        nonlocal heard
        heard = clock.monotonic()
        if progress is not None:
            progress(data)

    limit = max(span_s, silence_s)
    call = asyncio.create_task(cell.call("plan.run", params, told, timeout=limit))
    try:
        while True:
            left = heard + silence_s - clock.monotonic()
            if left <= 0:
                raise LinkTimeout(
                    f"plan.run: nothing heard of the plan for {silence_s:g} s: it is stuck "
                    "(the cell's log may say why)"
                )
            with contextlib.suppress(TimeoutError):
                async with clock.timeout(left):
                    return await asyncio.shield(call)
    finally:
        await cancel_and_wait([call])  # given up or Ctrl-C: the cell's play ends with it


#: A ``$CELLCTL_TOKEN`` the cell does not know, whether or not its controller runs.
NOT_A_TOKEN = "${env} is no token of {directory} (wrong or revoked)"


def env_caller(directory: Path) -> Caller | None:
    """Who calls in this process: the named token in ``$CELLCTL_TOKEN``, with its role (so an
    operator's token acts as an operator without a controller too); None (the local user,
    an engineer) when it is not set. AccessDenied for a token that is not the cell's."""
    given = os.environ.get(TOKEN_ENV, "").strip()
    if not given:
        return None
    check_unexpired(directory, given)  # said as expired, as with a controller running
    entry = identify(directory, given)
    if entry is None:
        raise AccessDenied(NOT_A_TOKEN.format(env=TOKEN_ENV, directory=directory))
    return Caller(f"token:{entry.name}", entry.role)


async def attach(directory: Path) -> RemoteCell:
    """Connect to the API of the controller running ``directory`` (with ``$CELLCTL_TOKEN``
    when set, else ``api-token``)."""
    try:
        return await RemoteCell.connect(
            token=client_token(directory), socket_path=directory / SOCKET_FILE
        )
    except AccessDenied as e:
        # Said as without a controller: the same wrong token, the same words.
        if not isinstance(e, ImpostorSocket) and os.environ.get(TOKEN_ENV, "").strip():
            raise AccessDenied(NOT_A_TOKEN.format(env=TOKEN_ENV, directory=directory)) from None
        raise


def require_cell(directory: Path) -> None:
    """Refuse a directory with neither a cell.toml nor a mailbox (a mailbox alone is a cell
    as the system level sees it): a mistyped --cell must not answer "no alarms" from a
    mailbox made there now."""
    here = Path(directory)
    if not (here / "cell.toml").is_file() and not (here / MAILBOX_FILE).is_file():
        raise UsageError(
            f"no cell at {os.path.abspath(directory)}: it has no cell.toml and no mailbox "
            "(name the cell's directory with --cell DIR or $CELLCTL_CELL; `cellctl --cell "
            "DIR emulate cell` makes one)"
        )


async def open_cell(
    directory: Path,
    refs: dict[str, MachineRef],
    *,
    trace: str | Path | None = None,
    readiness: str | None = None,
) -> CellClient:
    """The running controller's API if one runs on ``directory``; otherwise the machines in
    ``refs`` straight from this process."""
    from cellctl.cell.owner import controller_holder

    holder = controller_holder(directory)
    if holder is None:
        from cellctl.service.access import LocalCell

        require_cell(directory)
        return StandaloneCell(LocalCell(directory, refs, trace=trace, readiness=readiness))
    try:
        return await attach(directory)
    except LinkError as e:
        raise LinkError(
            f"a controller runs on {directory} ({holder}) but its API does not answer: {e}"
        ) from None
