"""Which links are one link: canonical keys, for the owner locks and for "two machines on one
link" checks.

Every spelling of one endpoint has the same keys, so one lock file (or one entry of a check)
stands for it whatever the URL says::

    link_keys("rfc2217://localhost:7001")    # ("tcp://127.0.0.1:7001", "tcp://[::1]:7001")
    link_keys("socket://127.0.0.1:7001")     # ("tcp://127.0.0.1:7001",)
    link_keys("/dev/serial/by-id/usb-FTDI")  # ("/dev/ttyUSB0",)
    link_lock_paths("socket://127.0.0.1:7001")   # [<runtime dir>/link-tcp-127.0.0.1-7001.lock]
    links_overlap("socket://localhost:7001", "rfc2217://127.0.0.1:7001")   # True

- A device path (``serial://`` or none) is resolved (symlinks, ``/dev/pts//2``, ``..``).
- A network URL (``socket://``, ``rfc2217://``, ``modbus://``) is its TCP endpoint: the host
  resolved to its addresses, the port as a number. The scheme is left out on purpose: a raw
  and an RFC 2217 connection to one port reach the same device server port, and either would
  take it from its owner.
- A name with several addresses (``localhost``: 127.0.0.1 and ::1) has one key per address:
  its connection may reach any of them, so its owner holds them all, and any spelling that
  shares one address with it is the same link.
- ``loop://``, ``mem://`` and anything else are their URL as written.

Resolution has a deadline (:data:`RESOLVE_TIMEOUT`). A name that does not resolve is refused
with a LinkError (``unresolved="refuse"``, for a lock: a lock under a key that may not be the
endpoint's would not exclude anyone), or keyed by its name (``unresolved="name"``, for a check
of a configuration read while the name server may be away).

Not caught: two names for one host that share no address (the host's own name and 127.0.0.1,
for a server listening on every interface): which addresses a server listens on cannot be
known from here.
"""

from __future__ import annotations

import ipaddress
import os
import re
import socket
import threading
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from cellctl.errors import LinkError, LinkTimeout, UsageError
from cellctl.link.lock import runtime_dir

#: Seconds a host name is given to resolve before the link is refused.
RESOLVE_TIMEOUT = 3.0

#: Schemes carried over TCP, and their port when the URL gives none (None: one is required).
TCP_SCHEMES: dict[str, int | None] = {"socket": None, "rfc2217": None, "modbus": 502}

_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")

Unresolved = Literal["refuse", "name"]


def link_keys(
    url: str, *, timeout: float = RESOLVE_TIMEOUT, unresolved: Unresolved = "refuse"
) -> tuple[str, ...]:
    """The canonical keys of link ``url`` (sorted, at least one; see module docstring).

    Raises UsageError for a network URL without a host or a valid port, and LinkError
    (LinkTimeout past ``timeout``) for a host that does not resolve when ``unresolved`` is
    ``"refuse"``.
    """
    scheme = _scheme(url)
    if scheme in ("", "serial"):
        path = url.split("://", 1)[1] if scheme else url
        if not path:
            return (url,)
        try:
            return (os.path.realpath(path),)
        except ValueError:  # a NUL byte: no file has such a name
            raise UsageError(f"device path {path!r} not understood: it holds a NUL byte") from None
    if scheme not in TCP_SCHEMES:
        return (url,)
    host, port = _host_port(url, scheme)
    addresses = _numeric(host)
    if addresses is None:
        try:
            addresses = _resolve(host, port, timeout)
        except LinkError:
            if unresolved == "refuse":
                raise
            addresses = [host.lower().rstrip(".")]
    return tuple(sorted({_endpoint(address, port) for address in addresses}))


def needs_lookup(url: str) -> bool:
    """True if :func:`link_keys` of ``url`` asks the name server (a network URL whose host is
    a name, not an address): an event loop calls it from a worker thread, so a slow name
    server stalls the one connection, not every machine the loop serves."""
    scheme = _scheme(url)
    if scheme not in TCP_SCHEMES:
        return False
    try:
        host, _ = _host_port(url, scheme)
    except UsageError:
        return False  # refused where the keys are made, in the caller's own words
    return _numeric(host) is None


def link_lock_paths(url: str, *, timeout: float = RESOLVE_TIMEOUT) -> list[Path]:
    """The owner lock files of link ``url`` in this user's runtime directory, one per key:
    ``link-<key>.lock`` (a device path's name as it always was, ``link-dev_pts_3.lock``).

    Take them all, in this order, to own the link. Raises as :func:`link_keys` refusing.
    """
    directory = runtime_dir()
    return [directory / f"link-{_file_stem(key)}.lock" for key in link_keys(url, timeout=timeout)]


def links_overlap(a: str, b: str, *, timeout: float = RESOLVE_TIMEOUT) -> bool:
    """True if links ``a`` and ``b`` share a key: one endpoint, however each is written (a
    name that does not resolve is compared by name, see ``unresolved="name"``)."""
    keys_a = link_keys(a, timeout=timeout, unresolved="name")
    return not set(keys_a).isdisjoint(link_keys(b, timeout=timeout, unresolved="name"))


def _scheme(url: str) -> str:
    """``url``'s scheme in lower case; "" for a device path written bare."""
    return url.split("://", 1)[0].lower() if "://" in url else ""


def _host_port(url: str, scheme: str) -> tuple[str, int]:
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:  # a port that is no number 0..65535, an unclosed "["
        raise UsageError(f"link URL {url!r} not understood: {e}") from None
    if port is None:
        port = TCP_SCHEMES[scheme]
    if not parts.hostname or port is None:
        raise UsageError(f"{url}: write {scheme}://HOST:PORT")
    return parts.hostname, port


def _canonical(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str:
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    if address.is_unspecified:  # a connection to 0.0.0.0 or :: reaches this host
        loopback = "127.0.0.1" if address.version == 4 else "::1"
        address = ipaddress.ip_address(loopback)
    return address.compressed


def _numeric(host: str) -> list[str] | None:
    """``host`` as a canonical address when it is written as one (no name server asked)."""
    address, percent, scope = host.partition("%")
    try:
        parsed = ipaddress.ip_address(address)
    except ValueError:
        return None
    return [_canonical(parsed) + (percent + scope if parsed.version == 6 else "")]


def _resolve(host: str, port: int, timeout: float) -> list[str]:
    """The addresses ``host`` resolves to, within ``timeout`` seconds.

    getaddrinfo cannot be interrupted: it runs in a daemon thread, left behind (never
    waited for, and it cannot keep the process alive) when its deadline passes.
    """
    found: list[list[str] | BaseException] = []

    def lookup() -> None:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
            found.append([str(info[4][0]) for info in infos])
        except (OSError, UnicodeError) as e:
            found.append(e)

    worker = threading.Thread(target=lookup, name=f"resolve {host}", daemon=True)
    worker.start()
    worker.join(timeout)
    if not found:
        raise LinkTimeout(
            f"cannot resolve the host {host!r} within {timeout:g} s: the link is not opened "
            "(write its address, or check the name server)"
        )
    outcome = found[0]
    if isinstance(outcome, BaseException):
        why = getattr(outcome, "strerror", None) or str(outcome) or type(outcome).__name__
        raise LinkError(f"cannot resolve the host {host!r}: {why}: the link is not opened")
    addresses: list[str] = []
    for raw in outcome:
        numeric = _numeric(raw)
        addresses.extend(numeric if numeric is not None else [raw])
    if not addresses:
        raise LinkError(f"cannot resolve the host {host!r}: no address: the link is not opened")
    return addresses


def _endpoint(address: str, port: int) -> str:
    return f"tcp://[{address}]:{port}" if ":" in address else f"tcp://{address}:{port}"


def _file_stem(key: str) -> str:
    """A file-safe, one-to-one name for ``key`` (a TCP key's colons become dashes: IPv6
    addresses stay apart, ``[::1]`` → ``--1``)."""
    if key.startswith("tcp://"):
        key = "tcp-" + key.removeprefix("tcp://").replace("[", "").replace("]", "")
        key = key.replace(":", "-")
    stem = _SAFE.sub("_", key).strip("_.")
    if not stem:
        raise UsageError(f"cannot make a lock name from {key!r}")
    return stem


__all__ = [
    "RESOLVE_TIMEOUT",
    "TCP_SCHEMES",
    "link_keys",
    "link_lock_paths",
    "links_overlap",
    "needs_lookup",
]
