"""Refused logins on the control API, in the audit trail and the run log (as OPC UA's
"login refused for user 'NAME'")::

    logins = LoginRefusals(dispatcher.trail, say=lambda text: controller.log(f"API: {text}"))
    await logins.refused(headers, peer="127.0.0.1:40112", asked="GET /api/status")
    await logins.refused(headers, peer=..., asked="POST /dashboard/call orders.submit",
                         why=foreign_origin("http://evil.example"))

Who is the token's name when it names one of the cell's tokens (``token:ann``: a page of
another origin carrying it), or a revoked one (``token:ann (revoked)``), else ``unknown
token`` (``no token`` when none was sent): never the token itself. The entry's method is
:data:`LOGIN`, its parameters where the request came from and what it asked.

A flood is one growing entry: a refusal repeating the same caller's last one (the same
words) within :data:`cellctl.service.audit.COLLAPSE_S` s is counted on it, as role
refusals are, and only a new entry (a burst's first refusal) is said in the run log.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from cellctl.service.audit import AuditEntry
from cellctl.service.token import expired_entry, identify, revoked_name
from cellctl.service.trail import CallTrail

log = logging.getLogger(__name__)

#: The method a refused login is audited under.
LOGIN = "api.login"
#: Why a request without one of the cell's tokens is refused.
WRONG_TOKEN = "refused: missing, wrong or revoked API token"
#: A caller sent no token at all.
NO_TOKEN = "no token"
#: A token that is none of the cell's, and never was.
UNKNOWN_TOKEN = "unknown token"


def _shown(text: str, limit: int = 200) -> str:
    # What a peer sent (a path, an Origin) goes to the log and the terminal: printable only.
    return "".join(c if c.isprintable() else "?" for c in text[:limit])


def foreign_origin(origin: str) -> str:
    """Why a request from a browser page of another origin is refused, token or not."""
    return (
        f"refused: a page of another origin ({_shown(origin, 100)}) sent it (a cross-site request)"
    )


def bearer(headers: Mapping[str, Any]) -> str | None:
    """The token in ``Authorization: Bearer``; None when there is none."""
    scheme, _, token = str(headers.get("authorization", "")).partition(" ")
    token = token.strip()
    return token if scheme.lower() == "bearer" and token else None


def who_refused(directory: Path, token: str | None) -> str:
    """Who a refused request is, for the audit trail: never the token itself."""
    if token is None:
        return NO_TOKEN
    entry = identify(directory, token)
    if entry is not None:
        return f"token:{entry.name}"
    expired = expired_entry(directory, token)
    if expired is not None:
        return f"token:{expired.name} (expired)"
    name = revoked_name(directory, token)
    return f"token:{name} (revoked)" if name is not None else UNKNOWN_TOKEN


def peer_of(client: tuple[str, int] | list[Any] | None, socket_path: Path | None) -> str:
    """Where a request came from: ``HOST:PORT``, or the Unix socket it came in on."""
    if client and client[0]:
        return f"{client[0]}:{client[1]}"
    return f"the Unix socket {socket_path}" if socket_path is not None else "a Unix socket"


class LoginRefusals:
    """Refused logins of one API server: audited in ``trail`` (collapsed), said by ``say``
    once per burst."""

    def __init__(self, trail: CallTrail, say: Callable[[str], None] | None = None) -> None:
        self.trail = trail
        self.say = say or (lambda text: log.warning("API: %s", text))

    async def refused(
        self,
        headers: Mapping[str, Any],
        *,
        peer: str,
        asked: str,
        why: str = WRONG_TOKEN,
    ) -> AuditEntry | None:
        """Record one refused login (see the module docstring); the entry as written."""
        who = who_refused(self.trail.directory, bearer(headers))
        asked = _shown(asked)
        params = {"from": peer, "asked": asked}
        try:
            entry = await self.trail.record(who, LOGIN, params, why, collapse=True)
        except Exception as e:  # the disk, a lock: the refusal stands, and is logged
            log.warning("a refused login was not audited: %s", e)
            entry = None
        if entry is None or entry.repeats == 1:
            self.say(f"login refused for {who} from {peer} ({asked}): {why}")
        return entry
