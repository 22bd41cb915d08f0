"""The control API server that ``cellctl run`` starts: JSON-RPC 2.0 over WebSocket, and plain
HTTP GET for read-only state, on Starlette/uvicorn.

::

    server = ApiServer(AttachedCell(controller), directory)
    await server.start()        # <cell>/api.sock (0600); [api] listen = "127.0.0.1:7125" too
    ...
    await server.close()

- ``ws://…/websocket``: requests ``{"jsonrpc": "2.0", "id": 1, "method": "cell.status"}``;
  ``cell.subscribe`` answers the status, then pushes ``notify_status_update`` with what changed
  since the status that client holds (:func:`~cellctl.service.status.difference`);
  a long call pushes ``notify_progress`` (``{"id": <call id>, ...}``).
- ``GET /api/status`` (the status, :mod:`cellctl.service.status`; its JSON Schema at
  ``/api/schema``) (and ``/api/orders``, ``/api/alarms``, ``/api/parts``, ``/api/machines``,
  ``/api/traffic/{machine}``, ``/server/info``).

Every request needs ``Authorization: Bearer <token>``: ``<cell>/api-token`` (0600, made at the
first run; the engineer token ``default``) or a named token with a role
(:mod:`cellctl.service.token`): a missing, wrong or revoked one gets 401 (HTTP) or a refused
handshake (WebSocket). Each method needs a role (``Method.role``): a lower one is refused
with 403 (HTTP) or a JSON-RPC error naming the role it lacks (``data.role``), and recorded in
the audit trail (:mod:`cellctl.service.audit`) with every acting call. A
browser, which cannot set that header on a WebSocket, fetches ``/access/oneshot_token`` (with
the header) and opens ``/websocket?token=ONESHOT`` within 10 s. A handshake from a page of
another origin, or naming a host the server does not answer to, is refused. A call that acts,
or talks to a machine, runs to its end even if its client goes away, so no machine is left
half-commanded; a read that touches no machine (a report, a plan) ends with its client. A
batch (at most :data:`MAX_BATCH` requests, answered as one array) runs its calls one after
the other and stops when its client leaves. A session has at most
``ApiLimits.calls_per_session`` calls in flight and a token ``calls_per_token`` over all its
sessions: a call past them is refused at once (:data:`SERVER_BUSY`), and a session's frames
are taken one per turn of the loop, so no client can hold the controller's loop. A token
holds at most ``sessions_per_token`` WebSockets (429 past it). Closing
(:meth:`ApiServer.close`) waits for the calls that must run to their end, as ``cellctl run``
waits for its steps in flight. Every HTTP answer carries a Content-Security-Policy that allows
only the server's own assets. The connections' limits are in :mod:`cellctl.service.limits`.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import os
import secrets
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

import uvicorn
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import BaseRoute, Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from cellctl.clock import current_clock
from cellctl.errors import AccessDenied, UsageError
from cellctl.link.listen import parse_listen
from cellctl.service.access import CellAccess
from cellctl.service.inflight import (
    CLOSE_GRACE,
    Flight,
    InFlight,
    Session,
    rpc_error,
    stopping_error,
)
from cellctl.service.limits import (
    ApiLimits,
    GuardedServer,
    HostCheck,
    Listener,
    SecurityHeaders,
    api_limits,
)
from cellctl.service.logins import WRONG_TOKEN, LoginRefusals, foreign_origin, peer_of
from cellctl.service.methods import (
    INTERNAL_ERROR,
    INVALID_REQUEST,
    MAX_BATCH,
    PARSE_ERROR,
    Caller,
    Dispatcher,
    RoleRefused,
    error_object,
)
from cellctl.service.publish import Publisher
from cellctl.service.rpc import SOCKET_FILE
from cellctl.service.token import (
    TOKEN_FILE,
    TokenEntry,
    ensure_default,
    ensure_token,
    identify,
    still_valid,
)

__all__ = [
    "SOCKET_FILE",
    "TOKEN_FILE",
    "ApiLimits",
    "ApiServer",
    "api_limits",
    "ensure_token",
    "parse_listen",
]

log = logging.getLogger(__name__)

#: The largest WebSocket frame accepted (a program text fits; more closes the connection).
MAX_FRAME = 8 * 1024 * 1024
#: Seconds a one-shot WebSocket token stays good.
ONESHOT_TTL = 10.0
#: Where Unix socket paths must fit (sun_path is 108 bytes on Linux).
MAX_SOCKET_PATH = 100


def socket_target(directory: Path) -> Path:
    """Where the cell's socket really is: ``<cell>/api.sock``, or (a path too long for a Unix
    socket) a short one in the runtime directory that ``<cell>/api.sock`` links to."""
    path = (directory / SOCKET_FILE).absolute()
    if len(os.fsencode(path)) <= MAX_SOCKET_PATH:
        return path
    from cellctl.link.lock import runtime_dir

    digest = hashlib.sha256(os.fsencode(path)).hexdigest()[:16]
    return Path(runtime_dir()) / f"api-{digest}.sock"


class ApiServer(InFlight, Publisher):
    """Serves one cell's API on its Unix socket and, if configured, on TCP."""

    def __init__(
        self,
        access: CellAccess,
        directory: Path,
        *,
        listen: str | None = None,
        allow_remote: bool = False,
        extra_routes: Callable[[ApiServer], list[BaseRoute]] | None = None,
        limits: ApiLimits | None = None,
    ) -> None:
        self.access = access
        self.directory = Path(directory)
        self.dispatcher = Dispatcher(access)
        self.token = ensure_default(self.directory)
        self.tcp = parse_listen(listen, allow_remote) if listen else None
        self.limits = limits or ApiLimits()
        self.socket_path = self.directory / SOCKET_FILE
        self.sessions: set[Session] = set()
        self.calls: set[asyncio.Task[None]] = set()
        self._token_calls: dict[str, int] = {}  # calls in flight by token name
        self._token_sessions: dict[str, int] = {}  # WebSockets open by token name
        self._refusals = Listener("WebSocket", self.limits)  # its rate-limited log
        self._flights: dict[asyncio.Task[Any], Flight] = {}  # the task that runs each call
        self._closing = False
        self._changed = asyncio.Event()
        self._server: GuardedServer | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.push_count = 0
        self._oneshot: dict[str, tuple[float, TokenEntry]] = {}
        # Refused logins: audited (a flood is one growing entry), one run-log line a burst.
        self.logins = LoginRefusals(self.dispatcher.trail, say=self._say)
        self.app = Starlette(
            middleware=[
                Middleware(SecurityHeaders),
                Middleware(
                    HostCheck, listen=self.tcp[0] if self.tcp else None, hosts=self.limits.hosts
                ),
            ],
            routes=[
                Route("/access/oneshot_token", self._oneshot_token),
                WebSocketRoute("/websocket", self._websocket),
                Route("/api/status", self._get("cell.status")),
                Route("/api/schema", self._get("cell.schema")),
                Route("/api/orders", self._get("orders.list")),
                Route("/api/alarms", self._get("alarms.list")),
                Route("/api/parts", self._get("parts.list")),
                Route("/api/machines", self._get("machines.list")),
                Route("/api/traffic/{machine}", self._traffic),
                Route("/server/info", self._get("server.info")),
                *(extra_routes(self) if extra_routes else []),
            ],
        )

    # -- life -------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the socket(s) and serve in the background."""
        sockets = [self._unix_socket()]
        if self.tcp is not None:
            host, port = self.tcp
            family = socket.AF_INET6 if ":" in host else socket.AF_INET
            tcp = socket.socket(family, socket.SOCK_STREAM)
            tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                tcp.bind((host, port))
            except OSError as e:
                tcp.close()
                raise UsageError(f"[api] listen: cannot listen on {host}:{port}: {e}") from None
            tcp.listen(128)
            tcp.setblocking(False)
            sockets.append(tcp)
        config = uvicorn.Config(
            self.app,
            log_level="warning",
            access_log=False,
            lifespan="off",
            ws="websockets-sansio",
            ws_max_size=MAX_FRAME,
            ws_ping_interval=20.0,
            ws_ping_timeout=20.0,
            timeout_graceful_shutdown=2,
            timeout_keep_alive=max(1, round(self.limits.idle_timeout)),
            h11_max_incomplete_event_size=16 * 1024,
        )
        self._server = GuardedServer(config, self.limits)
        self._tasks.append(asyncio.create_task(self._server.serve(sockets=sockets)))
        self._tasks.append(asyncio.create_task(self._publisher()))
        with contextlib.suppress(UsageError):
            self.access.controller().listeners.append(self.changed)
        clock = current_clock()
        deadline = clock.monotonic() + 10
        while not self._server.started:
            if self._tasks[0].done():
                await self._tasks[0]
                raise UsageError("the API server stopped at start")
            if clock.monotonic() > deadline:
                raise UsageError("the API server did not start within 10 s")
            await clock.sleep(0.01)

    def _unix_socket(self) -> socket.socket:
        target = socket_target(self.directory)
        for path in {target, self.socket_path}:
            if path.is_symlink() or path.exists():
                path.unlink()
        # Bound under a passing name and renamed once it listens: a client that sees
        # api.sock can connect (no "connection refused" between bind and listen).
        passing = target.with_name(target.name + "~")
        with contextlib.suppress(FileNotFoundError):
            passing.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # the socket is born 0600: no moment where others may connect
        try:
            sock.bind(str(passing))
        finally:
            os.umask(old)
        os.chmod(passing, 0o600)
        sock.listen(128)
        sock.setblocking(False)
        os.replace(passing, target)
        if target != self.socket_path.absolute():
            self.socket_path.symlink_to(target)
        return sock

    @property
    def url(self) -> str:
        """The TCP address (``http://host:port``) or the socket path."""
        if self.tcp is not None:
            return f"http://{self.tcp[0]}:{self.tcp[1]}"
        return str(self.socket_path)

    @property
    def where(self) -> str:
        """Every place it serves, as the run log names them: the socket, and the TCP address
        with ``[api] listen`` (the cell's own commands use the socket either way)."""
        if self.tcp is not None:
            return f"{self.socket_path} and {self.url}"
        return str(self.socket_path)

    async def close(self) -> None:
        """Stop serving. From now on a new call is refused (:data:`SERVER_BUSY`, "stopping");
        a read that touches no machine is cut short; every other call in flight (one that acts,
        or talks to a machine: a download) runs to its end first, as ``cellctl run`` finishes
        its steps in flight: waited for without a bound, and said in the log. Ctrl-C or
        SIGTERM meanwhile (or this close cancelled) cuts them short: each is said in the log
        and audited ``cancelled``. Then the clients get their answers and a close frame."""
        with contextlib.suppress(UsageError):
            listeners = self.access.controller().listeners
            if self.changed in listeners:
                listeners.remove(self.changed)
        self._closing = True
        for task, flight in list(self._flights.items()):
            if flight.cut:
                task.cancel()
        await self._finish_calls()
        if self.calls:
            await asyncio.wait(self.calls, timeout=CLOSE_GRACE)
        for session in list(self.sessions):
            session.finish(1001)
        ended = [asyncio.ensure_future(s.ended.wait()) for s in self.sessions]
        if ended:
            await asyncio.wait(ended, timeout=CLOSE_GRACE)
            for waiter in ended:
                waiter.cancel()
        if self._server is not None:
            self._server.should_exit = True
        for task in self._tasks[1:]:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                async with asyncio.timeout(5):
                    await task
        target = socket_target(self.directory)
        for path in {target, self.socket_path}:
            with contextlib.suppress(OSError):
                path.unlink()
        self.dispatcher.close()

    def _say(self, text: str) -> None:
        """A line for the controller's events (``cellctl run`` shows them); for the log
        without one (a DNC shop's server, a standalone one)."""
        try:
            controller = self.access.controller()
        except UsageError:
            log.warning("API: %s", text)
        else:
            controller.log(f"API: {text}")

    # -- auth ---------------------------------------------------------------------------------

    def caller(self, headers: Any) -> TokenEntry | None:
        """The token a request carries (``Authorization: Bearer``), None if it is no token
        of the cell's (missing, wrong, or revoked)."""
        given = headers.get("authorization", "")
        scheme, _, token = given.partition(" ")
        if scheme.lower() != "bearer":
            return None
        return identify(self.directory, token.strip())

    def authorized(self, headers: Any) -> bool:
        """Whether a request carries one of the cell's tokens."""
        return self.caller(headers) is not None

    async def _oneshot_token(self, request: Request) -> Response:
        """A token for one WebSocket handshake within ``ONESHOT_TTL`` s: a browser cannot set
        the Authorization header on a WebSocket, so it fetches one of these (with the header)
        and hands it over as ``?token=``. It opens a session with the fetching token's role."""
        entry = self.caller(request.headers)
        if entry is None:
            await self.login_refused(request)
            return _unauthorized()
        now = current_clock().monotonic()
        self._oneshot = {t: v for t, v in self._oneshot.items() if v[0] > now}
        token = secrets.token_urlsafe(24)
        self._oneshot[token] = (now + ONESHOT_TTL, entry)
        return JSONResponse({"token": token, "expires_in": ONESHOT_TTL})

    def _oneshot_entry(self, token: str | None) -> TokenEntry | None:
        found = self._oneshot.pop(token, None) if token else None
        return found[1] if found is not None and found[0] > current_clock().monotonic() else None

    def foreign_origin(self, headers: Any) -> bool:
        """A browser page from another site (clients that are not browsers send no Origin)."""
        origin = headers.get("origin")
        if origin is None:
            return False
        host = str(headers.get("host", ""))
        return str(origin).split("://", 1)[-1] != host

    # -- HTTP ---------------------------------------------------------------------------------

    async def login_refused(self, request: Request | WebSocket, why: str = WRONG_TOKEN) -> None:
        """Audit and log a request refused for its token or its origin (:mod:`logins`)."""
        peer = peer_of(request.scope.get("client"), self.socket_path)
        asked = f"{request.scope.get('method', 'WebSocket')} {request.url.path}"
        await self.logins.refused(request.headers, peer=peer, asked=asked, why=why)

    def _get(self, method: str) -> Any:
        async def endpoint(request: Request) -> Response:
            entry = self.caller(request.headers)
            if entry is None:
                await self.login_refused(request)
                return _unauthorized()
            params = {}
            if method == "alarms.list" and "all" in request.query_params:
                # As the parameter says it (1/0, true/false, yes/no): any other word is a 400.
                params["all"] = request.query_params["all"]
            return await self.answer(method, params, entry)

        return endpoint

    async def _traffic(self, request: Request) -> Response:
        entry = self.caller(request.headers)
        if entry is None:
            await self.login_refused(request)
            return _unauthorized()
        limit = request.query_params.get("limit", "100")
        params = {"machine": request.path_params["machine"], "limit": limit}
        return await self.answer("traffic.tail", params, entry)

    async def answer(
        self, method: str, params: dict[str, Any], entry: TokenEntry, *, wrap: bool = False
    ) -> Response:
        """An HTTP answer to one call by ``entry``'s token: the result (``{"result": ...}``
        with ``wrap``), 403 with the role it lacks, 400 or 500 with the error; 503 while
        the server stops."""
        if self._closing:
            return _json({"error": stopping_error()}, 503)
        caller = as_caller(entry)
        try:
            called = self.dispatcher.call(method, params, caller=caller)
            if self.dispatcher.abandoned(method):
                result = await called  # uvicorn's own shutdown ends it
            else:
                with self._flight(method, caller, params, cut=False):
                    result = await called
        except Exception as e:
            error = error_object(e)
            status = 403 if isinstance(e, RoleRefused) else 400
            status = 500 if error["code"] <= INTERNAL_ERROR else status
            return _json({"error": error}, status)
        return _json({"result": result} if wrap else result, 200)

    # -- WebSocket ----------------------------------------------------------------------------

    async def _websocket(self, ws: WebSocket) -> None:
        entry = self.caller(ws.headers) or self._oneshot_entry(ws.query_params.get("token"))
        if entry is None or self.foreign_origin(ws.headers):
            origin = str(ws.headers.get("origin", ""))
            why = WRONG_TOKEN if entry is None else foreign_origin(origin)
            await ws.close(code=1008)  # before accept: the handshake is refused (HTTP 403)
            await self.login_refused(ws, why)
            return
        refusal = self._open_session(entry.name)
        if refusal is not None:  # 429 in words: the connection slots stay free for the others
            await ws.send_denial_response(_json({"error": refusal}, 429))
            return
        try:
            await self._session(ws, entry)
        finally:
            self._close_session(entry.name)

    async def _session(self, ws: WebSocket, entry: TokenEntry) -> None:
        await ws.accept()
        session = Session(ws, entry)
        self.sessions.add(session)
        writer = asyncio.create_task(session.writer())
        try:
            while session.open:
                message = await ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                text = message.get("text")
                if text is None:
                    session.send(rpc_error(None, INVALID_REQUEST, "binary frames are not JSON-RPC"))
                    continue
                self._handle(session, text)
                # One frame a turn of the loop: a client sending frames as fast as it can
                # holds it no longer than any other task (the monitor polls in between).
                await current_clock().sleep(0)
        except WebSocketDisconnect:
            pass
        except asyncio.CancelledError:
            # The server is going away under the session (`cellctl run` aborted by a second
            # Ctrl-C): the session ends here, quietly, not as an ASGI application's error.
            pass
        finally:
            session.open = False
            self.sessions.discard(session)
            for call in session.abandoned:
                call.cancel()  # a read (a plan) nobody waits for any more burns no CPU
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await writer
            if ws.client_state is not WebSocketState.DISCONNECTED:
                with contextlib.suppress(Exception):
                    await ws.close()
            session.ended.set()

    def _handle(self, session: Session, text: str) -> None:
        try:
            request = json.loads(text)
        except (ValueError, RecursionError):
            session.send(rpc_error(None, PARSE_ERROR, "parse error: not JSON"))
            return
        if not isinstance(request, list):
            if not self._refused(session, [request], batch=False):
                self._spawn(session, self._single(session, request))
        elif not request:
            session.send(rpc_error(None, INVALID_REQUEST, "invalid request: an empty batch"))
        elif len(request) > MAX_BATCH:
            session.send(
                rpc_error(
                    None,
                    INVALID_REQUEST,
                    f"invalid request: a batch of {len(request)} requests; "
                    f"at most {MAX_BATCH} in one batch",
                )
            )
        elif not self._refused(session, request, batch=True):
            self._spawn(session, self._batch(session, request))

    async def _single(self, session: Session, request: Any) -> None:
        answer = await self._call(session, request)
        if answer is not None:
            session.send(answer)

    async def _batch(self, session: Session, requests: list[Any]) -> None:
        """A batch's calls one after the other, answered as one array (JSON-RPC 2.0)."""
        answers = []
        for request in requests:
            if not session.open:
                return  # the client left: the call in flight ended, the others do not start
            answer = await self._call(session, request)
            if answer is not None:
                answers.append(answer)
            await current_clock().sleep(0)  # the monitor and the other clients go on between calls
        if answers:
            session.send(answers)

    async def _call(self, session: Session, request: Any) -> dict[str, Any] | None:
        """The answer to one request (None for a notification: a request without an id)."""
        rid = request.get("id") if isinstance(request, dict) else None
        if (
            not isinstance(request, dict)
            or request.get("jsonrpc") != "2.0"
            or not isinstance(request.get("method"), str)
            or not isinstance(rid, str | int | float | None)
        ):
            rid = rid if isinstance(rid, str | int | float) else None
            return rpc_error(rid, INVALID_REQUEST, "invalid request: not JSON-RPC 2.0")
        method = request["method"]
        params = request.get("params")

        def progress(data: dict[str, Any]) -> None:
            if rid is not None:
                session.send(
                    {"jsonrpc": "2.0", "method": "notify_progress", "params": {"id": rid, **data}}
                )

        try:
            if not still_valid(self.directory, session.entry):
                gone = "expired" if session.entry.expired() else "was revoked"
                raise AccessDenied(f"the token {session.entry.name!r} {gone}")
            if method == "cell.subscribe":
                status = self.access.status()
                session.subscribed = True
                session.last = status
                result: Any = status.model_dump(mode="json")
            elif method == "cell.unsubscribe":
                session.subscribed = False
                session.last = None
                result = {"message": "unsubscribed"}
            elif self._closing:  # a batch's next call, once closing began
                return (
                    None
                    if rid is None
                    else {"jsonrpc": "2.0", "id": rid, "error": stopping_error()}
                )
            else:
                caller = as_caller(session.entry)
                cut = self.dispatcher.abandoned(method)
                called = self.dispatcher.call(method, params, progress, caller=caller)
                with self._flight(method, caller, params, cut=cut):
                    if not cut:
                        result = await called
                    else:
                        call = asyncio.ensure_future(called)
                        session.abandoned.add(call)
                        try:
                            result = await call
                        finally:
                            session.abandoned.discard(call)
        except Exception as e:
            error = error_object(e)
            if error["code"] == INTERNAL_ERROR:
                log.exception("API method %s failed", method[:100])
            return None if rid is None else {"jsonrpc": "2.0", "id": rid, "error": error}
        return None if rid is None else {"jsonrpc": "2.0", "id": rid, "result": result}


def as_caller(entry: TokenEntry) -> Caller:
    """The caller a token is, for the dispatcher and the audit trail."""
    return Caller(f"token:{entry.name}", entry.role)


def _json(content: Any, status: int) -> Response:
    text = json.dumps(content, default=str, allow_nan=False)
    return Response(text, status_code=status, media_type="application/json")


def _unauthorized() -> Response:
    return JSONResponse(
        {"error": {"code": -32007, "message": "missing or wrong API token"}},
        status_code=401,
        headers={"WWW-Authenticate": "Bearer"},
    )
