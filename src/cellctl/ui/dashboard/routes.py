"""The dashboard's routes on the API server: the page, its assets, and the calls it makes.

::

    server = ApiServer(access, directory, listen="127.0.0.1:7125", extra_routes=dashboard_routes)

- ``GET /``: the page, a static shell with no cell data in it. It takes the token from the
  URL's fragment (``#token=...``), keeps it in sessionStorage, and sends it as
  ``Authorization: Bearer`` with every request.
- ``GET /static/NAME``: the page's scripts, stylesheet and icon (only the files shipped here);
  ``GET /favicon.ico`` is the icon too (a browser asks for it by that name).
- ``POST /dashboard/call`` ``{"method": ..., "params": {...}}``: one of the API's methods the
  dashboard uses (:data:`DASHBOARD_METHODS`), answered as ``{"result": ...}`` or
  ``{"error": {code, message, data}}`` (HTTP 400; 403 with ``data.role``, the role the
  token lacks). It needs the token in the header (never a
  cookie), a JSON body, and no page of another origin (403): another site cannot drive the cell.

- ``POST /dashboard/handover/new`` (the token in the header) and ``POST /dashboard/handover``
  ``{"code": ...}``: a code that stands for the token once, for ``cellctl dashboard`` to open
  the page with (:mod:`cellctl.ui.dashboard.handover`): the token stays out of the browser's
  command line.

Live updates come from the API's WebSocket (``/websocket`` with a one-shot token).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from importlib import resources
from typing import TYPE_CHECKING, Any

from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import BaseRoute, Route

from cellctl.errors import AccessDenied, exit_code
from cellctl.service.bodies import BodyTooLarge, ClientGone, read_body
from cellctl.service.logins import foreign_origin
from cellctl.service.rpc import APP_ERROR_BASE, INVALID_REQUEST, METHOD_NOT_FOUND, PARSE_ERROR
from cellctl.ui.dashboard.handover import HANDOVER_S, Handovers

if TYPE_CHECKING:
    from cellctl.service.server import ApiServer

#: Calls that end when their caller goes away (the page closed, a client stopped): a plan
#: plays for as long as its horizon needs, and holds the one play a cell runs at a time. An
#: acting call runs to its end whoever left (as over the websocket).
ENDS_WITH_CALLER = frozenset({"plan.run"})
#: How often a call that ends with its caller looks whether the caller is still there, s.
CALLER_LOOK_S = 0.5

#: What the page may call through ``POST /dashboard/call``.
DASHBOARD_METHODS = frozenset(
    {
        "cell.status",
        "cell.layout",
        "steps.list",
        "report.shift",
        "programs.preview",
        "traffic.tail",
        "orders.list",
        "orders.submit",
        "orders.cancel",
        "alarms.list",
        "alarms.clear",
        "alarms.ack",
        "alarms.shelve",
        "alarms.unshelve",
        "alarms.history",
        "parts.list",
        "parts.release",
        "parts.scrap",
        # One set of controls (the CLI's and the console's): the cell and its machines.
        "cell.pause",
        "cell.resume",
        "cell.estop",
        "machines.list",
        "machines.out_of_service",
        "machines.return_to_service",
        "audit.list",
        # The What-if panel: a plan of the running cell, played on a copy.
        "plan.run",
    }
)
#: The largest request body taken by ``/dashboard/call`` (a call's method and parameters).
MAX_BODY = 64 * 1024
#: The largest body ``/dashboard/handover`` takes, before any token: ``{"code": ...}``.
MAX_HANDOVER_BODY = 1024
#: AccessDenied as the API codes it (-32000 minus its exit code, -32007).
ACCESS_DENIED = APP_ERROR_BASE - exit_code(AccessDenied(""))
_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
}


def _assets() -> dict[str, tuple[bytes, str]]:
    """The shipped files by name, read once: nothing else is ever served."""
    folder = resources.files("cellctl.ui.dashboard") / "static"
    found: dict[str, tuple[bytes, str]] = {}
    for entry in folder.iterdir():
        suffix = "." + entry.name.rpartition(".")[2]
        if entry.is_file() and suffix in _TYPES:
            found[entry.name] = (entry.read_bytes(), _TYPES[suffix])
    return found


def dashboard_routes(server: ApiServer) -> list[BaseRoute]:
    """The page, its assets and its call endpoint, for ``ApiServer(extra_routes=...)``."""
    assets = _assets()

    async def page(request: Request) -> Response:
        body, kind = assets["index.html"]
        return Response(body, media_type=kind)

    async def icon(request: Request) -> Response:
        body, kind = assets["favicon.svg"]
        return Response(body, media_type=kind)

    async def asset(request: Request) -> Response:
        found = assets.get(request.path_params["name"])
        if found is None or found[1].startswith("text/html"):
            return JSONResponse({"error": {"message": "no such file"}}, status_code=404)
        return Response(found[0], media_type=found[1])

    async def call(request: Request) -> Response:
        if server.foreign_origin(request.headers) or request.headers.get(
            "sec-fetch-site", "same-origin"
        ) not in ("same-origin", "none"):
            origin = request.headers.get("origin") or request.headers.get("sec-fetch-site", "")
            await server.login_refused(request, foreign_origin(str(origin)))
            return _refused(403, "refused: a page of another origin may not drive the cell")
        entry = server.caller(request.headers)
        if entry is None:
            await server.login_refused(request)
            return _refused(401, "missing or wrong API token")
        if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return _refused(
                415, "send the call as JSON (Content-Type: application/json)", INVALID_REQUEST
            )
        body = await _body(request, MAX_BODY)  # the token checked first: none, nothing read
        if isinstance(body, Response):
            return body
        try:
            data: Any = json.loads(body)
        except (ValueError, RecursionError):
            return _refused(400, "not JSON", PARSE_ERROR)
        method = data.get("method") if isinstance(data, dict) else None
        if not isinstance(method, str) or method not in DASHBOARD_METHODS:
            return _refused(400, f"the dashboard does not call {method!r}", METHOD_NOT_FOUND)
        params = data.get("params") or {}
        answer = server.answer(method, params, entry, wrap=True)  # 403: the role lacked
        if method not in ENDS_WITH_CALLER:
            return await answer
        return await _while_connected(request, answer)

    handovers = Handovers()

    def same_origin(request: Request) -> bool:
        return not server.foreign_origin(request.headers) and request.headers.get(
            "sec-fetch-site", "same-origin"
        ) in ("same-origin", "none")

    async def handover_new(request: Request) -> Response:
        if not same_origin(request):
            await server.login_refused(request, foreign_origin(str(request.headers.get("origin"))))
            return _refused(403, "refused: a page of another origin may not open the dashboard")
        caller = server.caller(request.headers)
        if caller is None:
            await server.login_refused(request)
            return _refused(401, "missing or wrong API token")
        token = request.headers["authorization"].partition(" ")[2].strip()
        return _json({"code": handovers.new(token, caller.name), "valid_s": HANDOVER_S}, 200)

    async def handover(request: Request) -> Response:
        if not same_origin(request):
            return _refused(403, "refused: a page of another origin may not open the dashboard")
        # No token here (the code stands for one): the body is a code's few bytes, no more.
        body = await _body(request, MAX_HANDOVER_BODY)
        if isinstance(body, Response):
            return body
        try:
            data: Any = json.loads(body)
        except (ValueError, RecursionError):
            data = None
        code = data.get("code") if isinstance(data, dict) else None
        token = handovers.take(code) if isinstance(code, str) else None
        # Checked again: a token revoked since the code was made opens nothing.
        if token is None or server.caller({"authorization": f"Bearer {token}"}) is None:
            return _refused(
                401,
                "the dashboard's code is spent, has lapsed or is wrong: open it again "
                "(`cellctl dashboard`)",
            )
        return _json({"token": token}, 200)

    return [
        Route("/", page),
        Route("/static/{name}", asset),
        Route("/favicon.ico", icon),
        Route("/dashboard/call", call, methods=["POST"]),
        Route("/dashboard/handover/new", handover_new, methods=["POST"]),
        Route("/dashboard/handover", handover, methods=["POST"]),
    ]


def _json(content: Any, status: int) -> Response:
    text = json.dumps(content, default=str, allow_nan=False)
    return Response(text, status_code=status, media_type="application/json")


async def _body(request: Request, cap: int) -> bytes | Response:
    """The request's body, or the answer instead: 413 in words (the connection closed: the
    rest of the body is not read) past ``cap``, nothing for a client gone mid-body."""
    try:
        return await read_body(request, cap)
    except BodyTooLarge as e:
        refusal = _refused(413, e.message, INVALID_REQUEST)
        refusal.headers["Connection"] = "close"
        return refusal
    except ClientGone:
        return Response(status_code=499)  # nobody reads it; not an error of the server's


def _refused(status: int, message: str, code: int = ACCESS_DENIED) -> Response:
    """An HTTP refusal with a JSON-RPC error: access denied (the default), or what was wrong
    with the request itself (JSON-RPC's own codes)."""
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse(
        {"error": {"code": code, "message": message}}, status_code=status, headers=headers
    )


async def _while_connected(request: Request, answer: Any) -> Response:
    """``answer`` (a coroutine), cancelled if the caller goes away before it is ready (its
    play stops: the HTTP twin of a websocket's close); the caller hears nothing then."""
    task = asyncio.ensure_future(answer)
    try:
        while True:
            done, _ = await asyncio.wait({task}, timeout=CALLER_LOOK_S)
            if done:
                return task.result()  # type: ignore[no-any-return]
            if await request.is_disconnected():
                return Response(status_code=499)  # nobody reads it
    finally:
        if not task.done():
            task.cancel()
            with contextlib.suppress(BaseException):
                await task
