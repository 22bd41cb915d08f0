"""Request bodies read with a cap: a client cannot make the server hold more than the cap.

::

    try:
        body = await read_body(request, 64 * 1024)
    except BodyTooLarge as e:
        return refuse(413, e.message)       # in words, and the connection closed
    except ClientGone:
        return Response(status_code=499)    # nobody reads it; nothing in the log

A ``Content-Length`` over the cap is refused before a byte of the body is read; a body
without one (``Transfer-Encoding: chunked``) is read piece by piece and refused as soon as
what came passes the cap. Check the token *before* reading: a caller without one is
answered at once and its body never read (uvicorn drops what comes after the answer).
"""

from __future__ import annotations

from starlette.requests import ClientDisconnect, Request


class BodyTooLarge(Exception):
    """A request body over its route's cap; ``message`` says so in the user's words."""

    def __init__(self, cap: int, length: int | None = None) -> None:
        size = f"{length:,} bytes" if length is not None else f"over {cap:,} bytes"
        self.message = f"refused: the request's body is {size}; at most {cap:,} bytes are taken"
        super().__init__(self.message)


class ClientGone(Exception):
    """The client went away before its whole body came."""


async def read_body(request: Request, cap: int) -> bytes:
    """``request``'s body, at most ``cap`` bytes (see the module docstring)."""
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError:
            length = None  # h11 refuses such a head before it reaches a route
        if length is not None and length > cap:
            raise BodyTooLarge(cap, length)
    body = bytearray()
    try:
        async for piece in request.stream():
            body += piece
            if len(body) > cap:
                raise BodyTooLarge(cap)
    except ClientDisconnect:
        raise ClientGone from None
    return bytes(body)
