"""Where a server of cellctl's listens: ``HOST:PORT`` from a configuration table, checked::

    parse_listen("127.0.0.1:7125", allow_remote=False)          # ("127.0.0.1", 7125)
    parse_listen("0.0.0.0:7130", False, table="dnc")            # UsageError, in [dnc] words

Loopback unless the table says ``allow_remote = true``: private by default. ``localhost`` is
bound as ``127.0.0.1``, never looked up.
"""

from __future__ import annotations

import ipaddress

from cellctl.errors import UsageError


def parse_listen(
    text: str, allow_remote: bool, *, table: str = "api", example: str = "127.0.0.1:7125"
) -> tuple[str, int]:
    """``"127.0.0.1:7125"`` → (host, port); a non-loopback host only with ``allow_remote``.
    ``localhost`` gives ``127.0.0.1``: the name was let through as loopback, so what is bound
    must be loopback, whatever a hosts file says the name is. A refusal names the
    configuration ``table`` the setting is in (``[api]``, ``[dnc]``)."""
    host, sep, port_text = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port_text.isdecimal() or not 0 < int(port_text) < 65536:
        raise UsageError(f'[{table}] listen = "{text}": write "HOST:PORT", e.g. "{example}"')
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not allow_remote:
        raise UsageError(
            f'[{table}] listen = "{text}" is not a loopback address: the API answers there '
            f"only with allow_remote = true in [{table}]"
        )
    return ("127.0.0.1" if host == "localhost" else host), int(port_text)


__all__ = ["parse_listen"]
