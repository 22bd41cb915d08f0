"""Who may use a cell's OPC UA server: users with salted password hashes in a TOML file, and
what each kind of session may do.

::

    add_user(Path("cell/opcua-users.toml"), "alice", "s3cret")   # the file is made 0600
    manager = FileUserManager(Path("cell/opcua-users.toml"), anonymous_read=True)
    server = Server(user_manager=manager)
    server.set_security_policy(POLICIES, permission_ruleset=CellRuleset())

The file (written by ``cellctl opcua adduser NAME [--role ROLE]``)::

    [users.alice]
    password = "scrypt$16384$8$1$<salt, base64>$<hash, base64>"
    role = "operator"        # viewer, operator or engineer; left out: operator

A user's role limits the methods they may call as an API token's does (SubmitOrder and
ClearAlarm need an operator); :func:`session_user` tells a method who calls it.

It is read again at each login, so a user added while the cell runs may log in at once. A
file that others may read is refused, as an SSH key would be.
"""

from __future__ import annotations

import base64
import contextlib
import contextvars
import dataclasses
import hashlib
import hmac
import os
import re
import secrets
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import SimpleRoleRuleset, User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.ua.object_ids import ObjectIds

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.files import reason
from cellctl.service.token import ROLES

#: A user's role when the file names none (such users could call every method before roles).
DEFAULT_ROLE = "operator"

#: scrypt's cost: about 16 MiB and a few tens of ms a check (slow for a guesser, fine for
#: a login).
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
SALT_BYTES = 16
#: Wrong logins per :data:`LOGIN_WINDOW_S` before logins are refused unchecked until the
#: window ends (a password hash costs the server's loop tens of milliseconds: a flood of
#: guesses would stall it, and guess on). Counted per client address, so that a guesser
#: elsewhere locks nobody out: a name from one address (LOGIN_FAILURES), every name from one
#: address (LOGIN_FAILURES_ALL); and past LOGIN_FLOOD from all addresses together, every
#: address with a wrong login in the window (an address with none is still checked).
LOGIN_FAILURES = 5
LOGIN_FAILURES_ALL = 30
LOGIN_FLOOD = 100
LOGIN_WINDOW_S = 60.0
HASH_BYTES = 32
#: User names: what a client can type, nothing that needs quoting in TOML.
NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
#: Requests an anonymous session may not make: it reads, browses and subscribes only.
ANONYMOUS_REFUSED = frozenset(
    ua.NodeId(ua.Int32(i))
    for i in (
        ObjectIds.WriteRequest_Encoding_DefaultBinary,
        ObjectIds.CallRequest_Encoding_DefaultBinary,
        ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary,
    )
)


def hash_password(password: str, *, salt: bytes | None = None) -> str:
    """The stored form of ``password``: ``scrypt$N$r$p$salt$hash`` (base64 parts)."""
    salt = salt if salt is not None else secrets.token_bytes(SALT_BYTES)
    digest = _scrypt(password, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P)
    return "$".join(
        ["scrypt", str(SCRYPT_N), str(SCRYPT_R), str(SCRYPT_P), _b64(salt), _b64(digest)]
    )


def check_password(stored: str, password: str) -> bool:
    """Whether ``password`` matches ``stored`` (a form :func:`hash_password` made)."""
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != "scrypt":
            return False
        expected = base64.b64decode(digest, validate=True)
        found = _scrypt(password, base64.b64decode(salt, validate=True), int(n), int(r), int(p))
    except (ValueError, TypeError, MemoryError):
        return False
    return hmac.compare_digest(found, expected)


def _scrypt(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    if not (2 <= n <= 2**20 and 1 <= r <= 32 and 1 <= p <= 16):
        raise ValueError("scrypt cost out of range")  # a hand-edited file cannot stall a login
    return hashlib.scrypt(
        password.encode("utf-8"), salt=salt, n=n, r=r, p=p, maxmem=256 * 1024**2, dklen=HASH_BYTES
    )


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def load_users(path: Path) -> dict[str, str]:
    """``name -> stored password`` from the users file; UsageError naming what is wrong."""
    return {name: stored for name, (stored, _) in load_entries(path).items()}


def load_entries(path: Path) -> dict[str, tuple[str, str]]:
    """``name -> (stored password, role)`` from the users file; UsageError naming what is
    wrong."""
    try:
        mode = path.stat().st_mode
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file (add a user: cellctl opcua adduser NAME)") from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read the OPC UA users: {e.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: not a users file (TOML): {e}") from None
    if mode & 0o077:
        raise UsageError(f"{path}: others may read it: chmod 600 {path}")
    table = data.get("users", {})
    if not isinstance(table, dict) or set(data) - {"users"}:
        raise UsageError(f'{path}: expected only [users.NAME] tables with password = "..."')
    users: dict[str, tuple[str, str]] = {}
    for name, entry in table.items():
        stored = entry.get("password") if isinstance(entry, dict) else None
        if not NAME.fullmatch(name) or not isinstance(stored, str):
            raise UsageError(f'{path}: [users.{name}] needs a plain name and password = "..."')
        role = entry.get("role", DEFAULT_ROLE)
        if role not in ROLES:
            raise UsageError(f"{path}: [users.{name}] role: one of {', '.join(ROLES)}")
        users[name] = (stored, role)
    return users


def add_user(path: Path, name: str, password: str, role: str | None = None) -> tuple[bool, str]:
    """Add ``name`` (or set its password, and its role if ``role`` is given) in the users
    file, made 0600: (True if it is new, the role it has). A new user without ``role`` gets
    :data:`DEFAULT_ROLE`; a known one keeps its own (a new password promotes nobody)."""
    if not NAME.fullmatch(name):
        raise UsageError(f"user name {name!r}: use 1 to 64 letters, digits, '_', '.' or '-'")
    if not password:
        raise UsageError("an empty password is not a password")
    if role is not None and role not in ROLES:
        raise UsageError(f"role {role[:40]!r}: choose one of {', '.join(ROLES)}")
    users = load_entries(path) if path.exists() else {}
    new = name not in users
    kept = role or (DEFAULT_ROLE if new else users[name][1])
    users[name] = (hash_password(password), kept)
    text = "# OPC UA users of this cell: cellctl opcua adduser NAME (salted scrypt hashes)\n"
    text += "".join(
        f'\n[users.{n}]\npassword = "{stored}"\nrole = "{r}"\n' for n, (stored, r) in users.items()
    )
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)  # a reader sees the old file or the new one, never half of it
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise UsageError(f"{path}: cannot write the OPC UA users: {reason(e)}") from None
    return new, kept


@dataclasses.dataclass
class CellUser(User):
    """asyncua's user with the cell's role (:data:`~cellctl.service.token.ROLES`)."""

    cell_role: str = "viewer"


#: The user of the request being served (set by :class:`CellRuleset` as it checks it).
_SESSION_USER: contextvars.ContextVar[User | None] = contextvars.ContextVar(
    "opcua_user", default=None
)


def session_user() -> tuple[str, str]:
    """Who calls the method being served, and their role: ``("opcua:NAME", role)``."""
    user = _SESSION_USER.get()
    if isinstance(user, CellUser) and user.name:
        return f"opcua:{user.name}", user.cell_role
    return "opcua:anonymous", "viewer"


class FileUserManager:
    """asyncua's user manager: users from the file (read at each login); anonymous sessions
    only with ``anonymous_read`` (the server also offers the anonymous token only then).
    ``refused`` is told the name and client address of each login refused after its
    password was checked; an address (or a name from it) with too many wrong logins lately
    is refused unchecked (:data:`LOGIN_FAILURES`). The address is the one
    :func:`track_peers` notes for the server's sessions ("" when none is noted)."""

    def __init__(
        self,
        path: Path | None,
        *,
        anonymous_read: bool,
        refused: Callable[[str, str], None] | None = None,
    ) -> None:
        self.path = path
        self.anonymous_read = anonymous_read
        self.refused = refused
        self._dummy = hash_password(secrets.token_urlsafe(12))
        # (when, address, name) of wrong logins, in order.
        self._failed: list[tuple[float, str, str]] = []

    def _held_back(self, peer: str, username: str) -> bool:
        """True if ``username`` from ``peer``, or ``peer`` itself, failed too often in the
        window, or a flood is on and ``peer`` took part: refused without a hash."""
        now = current_clock().monotonic()
        self._failed = [f for f in self._failed if now - f[0] < LOGIN_WINDOW_S]
        from_peer = [name for _, address, name in self._failed if address == peer]
        if not from_peer:
            return False
        return (
            from_peer.count(username) >= LOGIN_FAILURES
            or len(from_peer) >= LOGIN_FAILURES_ALL
            or len(self._failed) >= LOGIN_FLOOD
        )

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        """The session's user, or None (the login is refused: BadUserAccessDenied)."""
        if username is None:  # ``certificate`` is the client application's, not a user's
            return CellUser(role=UserRole.Anonymous) if self.anonymous_read else None
        peer = _PEER.get()
        if self._held_back(peer, username):
            return None  # unchecked and unlogged: the wrong logins before it were logged
        try:
            users = load_entries(self.path) if self.path is not None else {}
        except UsageError:
            users = {}  # told at start; a broken file lets nobody in rather than anyone
        # An unknown name costs the same hash as a known one: timing does not tell names.
        stored, role = users.get(username, (self._dummy, "viewer"))
        if check_password(stored, password or "") and username in users:
            return CellUser(role=UserRole.User, name=username, cell_role=role)
        self._failed.append((current_clock().monotonic(), peer, username))
        if self.refused is not None:
            self.refused(username, peer)
        return None


#: The client address of the session being activated (set by :func:`track_peers`).
_PEER: contextvars.ContextVar[str] = contextvars.ContextVar("opcua_peer", default="")


@contextlib.contextmanager
def login_from(address: str) -> Iterator[None]:
    """Logins in the block come from ``address``, as :func:`track_peers` says for a session."""
    token = _PEER.set(address)
    try:
        yield
    finally:
        _PEER.reset(token)


class _PeerSession(InternalSession):
    """asyncua's session, whose activation (where the user manager is asked) knows the
    client's address: asyncua names a session by its connection's peer."""

    def activate_session(
        self, params: ua.ActivateSessionParameters, peer_certificate: bytes | None
    ) -> ua.ActivateSessionResult:
        name: Any = self.name
        address = str(name[0]) if isinstance(name, tuple) and name else str(name or "")
        with login_from(address):
            return super().activate_session(params, peer_certificate)


def track_peers(server: Any) -> None:
    """Make ``server`` (asyncua's Server) tell its user manager each login's client address,
    so that wrong logins are held back per address (:class:`FileUserManager`)."""
    iserver = server.iserver

    def create_session(
        name: str, user: User | None = None, external: bool = False
    ) -> InternalSession:
        user = user if user is not None else User(role=UserRole.Anonymous)
        return _PeerSession(
            iserver,
            iserver.aspace,
            iserver.subscription_service,
            name,
            user=user,
            external=external,
        )

    iserver.create_session = create_session


class CellRuleset(SimpleRoleRuleset):
    """Users may do what asyncua's users may (read, browse, subscribe, call); anonymous
    sessions the same minus writing, calling methods and updating history."""

    def __init__(self) -> None:
        super().__init__()  # type: ignore[no-untyped-call]
        rules = self._permission_dict
        rules[UserRole.Anonymous] = set(rules[UserRole.User]) - ANONYMOUS_REFUSED

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        """asyncua's check, which also notes the user for the method it may go on to call
        (the call runs in the same task, right after)."""
        _SESSION_USER.set(user)
        return bool(super().check_validity(user, action_type_id, body))  # type: ignore[no-untyped-call]
