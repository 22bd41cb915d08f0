"""The cell's API tokens. ``<cell>/api-token``: made once (0600), read by every client::

    token = ensure_token(Path("cell"))   # the server: read it, or make it on the first run
    token = read_token(Path("cell"))     # a client: read it (AccessDenied when there is none)
    token = client_token(Path("cell"))   # $CELLCTL_TOKEN (a named token) or api-token

The file is opened with ``O_NOFOLLOW`` and made with ``O_EXCL``: a symbolic link put in its
place is refused, never followed (its target would become the token, or be overwritten). A
token shorter than :data:`MIN_TOKEN` characters is refused too. Both refusals say what to do:
remove the file, and the next ``cellctl run`` writes a new token.

Named tokens with a role (viewer, operator, engineer) live in ``<cell>/tokens/NAME`` (0600,
the same rules), each holding a SHA-256 of its secret, never the secret::

    secret = add_token(Path("cell"), "ann", "operator")    # shown once
    entry = identify(Path("cell"), secret)                 # TokenEntry(name="ann", ...)
    revoke_token(Path("cell"), "ann")                      # refused from now on

A named token may expire: ``add_token(..., expires=parse_expiry("8h"))`` (or a date and time,
``"2026-12-31T18:00"``). Past that time :func:`identify` and :func:`still_valid` refuse it as
a revoked one (the API answers it as a wrong token); :func:`expired_entry` still names it, so
a client can say why (:func:`client_token` does, for ``$CELLCTL_TOKEN``). An entry without an
expiry (every entry made before expiries, and ``default``) never expires.

At its start the server enters ``api-token`` as the engineer token ``default``
(:func:`ensure_default`), so an older cell and its clients go on as before.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import math
import os
import re
import secrets
import stat
import tomllib
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from cellctl.clock import current_clock
from cellctl.errors import AccessDenied, UsageError

TOKEN_FILE = "api-token"
#: A named token the CLI and the console act with, instead of ``api-token`` (the engineer's).
TOKEN_ENV = "CELLCTL_TOKEN"
#: The shortest token taken (a new one has 43 characters: 32 random bytes, base64url).
MIN_TOKEN = 32
#: The longest file read as a token.
MAX_TOKEN_FILE = 4096


def _remedy(path: Path) -> str:
    return f"remove {path} and start `cellctl run` again: a new token is written"


def _read(path: Path) -> str:
    """The token in ``path``: FileNotFoundError when there is none, UsageError when the file is
    a link, not a plain file, or holds no usable token."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UsageError(
                f"{path} is a symbolic link: the API token is never read through one; "
                + _remedy(path)
            ) from None
        raise
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise UsageError(f"{path} is not a plain file; " + _remedy(path))
        if stat.S_IMODE(info.st_mode) != 0o600 and info.st_uid == os.getuid():
            os.fchmod(f.fileno(), 0o600)  # the file itself, never a link's target
        raw = f.read(MAX_TOKEN_FILE + 1)
    try:
        token = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        token = ""
    if len(raw) > MAX_TOKEN_FILE or len(token) < MIN_TOKEN or not token.isprintable():
        raise UsageError(
            f"{path} holds no usable API token (at least {MIN_TOKEN} characters); " + _remedy(path)
        )
    return token


def ensure_token(directory: Path) -> str:
    """The cell's API token, made (0600) on first use; UsageError for a link or a bad file."""
    path = Path(directory) / TOKEN_FILE
    try:
        return _read(path)
    except FileNotFoundError:
        pass
    Path(directory).mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, 0o600)
    except FileExistsError:
        # Made meanwhile, or a dangling link: read what is there (a link is refused).
        return _read(path)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(token + "\n")
    return token


def read_token(directory: Path) -> str:
    """The cell's API token for a client: AccessDenied when it cannot be read, UsageError
    when the file is a link or holds no usable token."""
    path = Path(directory) / TOKEN_FILE
    try:
        return _read(path)
    except FileNotFoundError:
        raise AccessDenied(
            f"no API token in {path}: `cellctl run` writes one as it starts; or set "
            f"${TOKEN_ENV} to a token of `cellctl token add`"
        ) from None
    except OSError as e:
        raise AccessDenied(f"cannot read the API token {path}: {e.strerror or e}") from None


def client_token(directory: Path) -> str:
    """The token a client of the cell sends: ``$CELLCTL_TOKEN`` when set (a named token, so
    the CLI and the console act with its role), else ``<cell>/api-token``. TokenExpired (a
    UsageError, with when and what to do) for a named token past its expiry: never sent."""
    given = os.environ.get(TOKEN_ENV, "").strip()
    if any(not "!" <= c <= "~" for c in given):
        # Refused here, not sent: a header with it is not HTTP (and would be echoed back).
        raise AccessDenied(
            f"${TOKEN_ENV} is not a token: it holds a space, a line break or a character "
            "a token never has; set it to a token as `cellctl token add` printed it"
        )
    if given:
        check_unexpired(directory, given)
    return given or read_token(directory)


# -- named tokens with roles ------------------------------------------------------------------

#: The roles, least first: each may do what the ones before it may.
ROLES = ("viewer", "operator", "engineer")
#: Where the named tokens live: ``<cell>/tokens/NAME`` (0600, the directory 0700).
TOKENS_DIR = "tokens"
#: The token ``<cell>/api-token`` becomes: an engineer's, so existing clients keep working.
DEFAULT_NAME = "default"
#: Token names: what a shell takes unquoted, never a hidden file.
TOKEN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
#: The longest named-token file read.
MAX_ENTRY_FILE = 1024


@dataclass(frozen=True)
class TokenEntry:
    """One named token as stored: its name, role, when it was made, a SHA-256 of the secret
    (the secret itself is shown once, at :func:`add_token`), and when it expires (unix
    seconds; None: never)."""

    name: str
    role: str
    created: float
    digest: str
    expires: float | None = None

    def expired(self, now: float | None = None) -> bool:
        """Whether its expiry has come (at ``now``, else the clock's now)."""
        if self.expires is None:
            return False
        return (current_clock().now() if now is None else now) >= self.expires


class TokenExpired(UsageError):
    """A client holds a named token past its expiry: said (with when, and how to get a new
    one) before it is sent. ``entry`` is the expired token's entry."""

    def __init__(self, entry: TokenEntry) -> None:
        self.entry = entry
        super().__init__(
            f"${TOKEN_ENV}: the token {entry.name!r} expired on "
            f"{format_time(entry.expires or 0.0)} and the cell's API refuses it; an engineer "
            f"makes you a new one (`cellctl token add NAME --role {entry.role} --expires 8h`, "
            f"or a date: --expires 2026-12-31T18:00) to set in ${TOKEN_ENV}; "
            f"`cellctl token revoke {entry.name}` removes this one"
        )


def format_time(t: float) -> str:
    """``t`` (unix seconds) as the local date and time the CLI shows: 2026-12-31 18:00:00."""
    return datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


#: ``--expires`` as a span from now: 90s, 30m, 8h, 30d.
_SPAN = re.compile(r"(\d{1,9})([smhd])")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_expiry(text: str, now: float | None = None) -> float:
    """``--expires``: a span from now (``8h``, ``30d``) or a local date and time
    (``2026-12-31T18:00``; a bare date is its midnight; an offset such as ``+01:00`` is
    taken), as unix seconds. UsageError for anything else, a time already past, or one
    past the year 9999."""
    now = current_clock().now() if now is None else now
    shown = text.strip()[:40]
    span = _SPAN.fullmatch(text.strip())
    try:
        if span:
            when = now + int(span.group(1)) * _UNITS[span.group(2)]
        else:
            when = datetime.fromisoformat(text.strip()).timestamp()
    except (ValueError, OverflowError, OSError):
        raise UsageError(
            f"--expires {shown!r}: give a span from now (8h, 30d) or a date and time "
            "(2026-12-31T18:00)"
        ) from None
    try:
        said = format_time(when)
    except (OverflowError, OSError, ValueError):
        raise UsageError(f"--expires {shown!r} is too far ahead: name a date up to 9999") from None
    if when <= now:
        raise UsageError(f"--expires {shown!r} ({said}) is past: give a time to come")
    return when


def role_allows(role: str, needed: str) -> bool:
    """Whether ``role`` may do what ``needed`` may (engineer > operator > viewer)."""
    return role in ROLES and ROLES.index(role) >= ROLES.index(needed)


def check_name(name: str) -> str:
    if not TOKEN_NAME.fullmatch(name):
        raise UsageError(
            f"token name {name[:80]!r}: use 1 to 64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit"
        )
    return name


def check_role(role: str) -> str:
    if role not in ROLES:
        raise UsageError(f"role {role[:40]!r}: choose one of {', '.join(ROLES)}")
    return role


def _digest(token: str) -> str:
    # The secrets are 32 random bytes: a plain SHA-256 cannot be guessed back.
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def _tokens_dir(directory: Path) -> Path:
    folder = Path(directory) / TOKENS_DIR
    if folder.is_symlink():
        raise UsageError(f"{folder} is a symbolic link: tokens are never kept through one")
    return folder


def _read_entry(path: Path) -> TokenEntry:
    """The entry in ``path``: FileNotFoundError when there is none, UsageError when broken."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UsageError(
                f"{path} is a symbolic link: a token is never read through one"
            ) from None
        raise
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise UsageError(f"{path} is not a plain file")
        if stat.S_IMODE(info.st_mode) != 0o600 and info.st_uid == os.getuid():
            os.fchmod(f.fileno(), 0o600)
        raw = f.read(MAX_ENTRY_FILE + 1)
    try:
        data = tomllib.loads(raw.decode("utf-8")) if len(raw) <= MAX_ENTRY_FILE else {}
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        data = {}
    name, role, created, digest = (data.get(k) for k in ("name", "role", "created", "sha256"))
    # No expiry (an entry of a cellctl from before expiries too): it never expires. One that
    # is no time is a broken entry: it lets nobody in, rather than never expiring.
    expires = data.get("expires")
    if (
        name != path.name
        or role not in ROLES
        or not isinstance(created, int | float)
        or not isinstance(digest, str)
        or not re.fullmatch(r"[0-9a-f]{64}", digest)
        or not (expires is None or _is_time(expires))
    ):
        raise UsageError(f"{path} is not a token entry; revoke it (cellctl token revoke)")
    return TokenEntry(
        str(name), str(role), float(created), digest, None if expires is None else float(expires)
    )


def _is_time(value: object) -> bool:
    """Whether ``value`` (from TOML) is unix seconds the CLI can show: not a bool, nan, inf."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return False
    try:
        format_time(value)
    except (OverflowError, OSError, ValueError):
        return False
    return True


def _entry_text(entry: TokenEntry) -> str:
    text = (
        f'name = "{entry.name}"\nrole = "{entry.role}"\ncreated = {entry.created}\n'
        f'sha256 = "{entry.digest}"\n'
    )
    # Written only when there is one: an entry without it is the one older cellctl wrote.
    return text if entry.expires is None else text + f"expires = {float(entry.expires)}\n"


def _write_entry(
    directory: Path, name: str, role: str, token: str, expires: float | None = None
) -> TokenEntry:
    folder = _tokens_dir(directory)
    try:
        # Never parents: a missing cell directory is a mistyped one, not one to make here.
        folder.mkdir(mode=0o700, exist_ok=True)
    except FileNotFoundError:
        raise UsageError(f"no cell at {os.path.abspath(directory)}: no such directory") from None
    except OSError as e:
        raise UsageError(f"{folder}: cannot make the tokens' directory: {e.strerror}") from None
    entry = TokenEntry(name, role, round(current_clock().now(), 3), _digest(token), expires)
    path = folder / name
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, 0o600)
    except FileExistsError:
        raise UsageError(f"a token named {name!r} exists: revoke it first") from None
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(_entry_text(entry))
    return entry


def add_token(directory: Path, name: str, role: str, expires: float | None = None) -> str:
    """Make a token ``name`` with ``role``, refused from ``expires`` on (unix seconds, e.g.
    :func:`parse_expiry`; None: never); the secret is returned once and kept only as a
    hash. UsageError for a bad name or role, a name already taken, an expiry not to come,
    or one for ``default`` (api-token's, which never expires)."""
    check_name(name)
    check_role(role)
    if expires is not None:
        if name == DEFAULT_NAME:
            # The local CLI acts with api-token as `default`: it must go on working.
            raise UsageError(
                f"the token {DEFAULT_NAME!r} is the cell's api-token, which never expires: "
                "give an expiring token another name"
            )
        if not _is_time(expires) or expires <= current_clock().now():
            raise UsageError(f"token {name!r}: its expiry must be a time to come")
    token = secrets.token_urlsafe(32)
    _write_entry(directory, name, role, token, expires)
    return token


def list_tokens(directory: Path) -> list[TokenEntry]:
    """The named tokens, by name (a broken entry is skipped: it lets nobody in)."""
    folder = _tokens_dir(directory)
    if not folder.is_dir():
        return []
    found = []
    for path in sorted(folder.iterdir()):
        if TOKEN_NAME.fullmatch(path.name):
            try:
                found.append(_read_entry(path))
            except (OSError, UsageError):
                continue
    return found


def revoke_token(directory: Path, name: str) -> None:
    """Remove token ``name`` (refused at once by a running server). Revoking ``default``
    removes ``<cell>/api-token`` too: the next ``cellctl run`` makes a new one."""
    check_name(name)
    folder = _tokens_dir(directory)
    path = folder / name
    try:
        entry = _read_entry(path)
    except (OSError, UsageError):
        entry = None  # a broken entry lets nobody in: nothing to name a refusal by
    try:
        path.unlink()
    except FileNotFoundError:
        raise UsageError(f"no token named {name!r} (cellctl token list shows them)") from None
    if entry is not None:
        _keep_revoked(folder, entry)
    if name == DEFAULT_NAME:
        (Path(directory) / TOKEN_FILE).unlink(missing_ok=True)


#: Where revoked tokens' entries are kept (hash only), so that a refused login with one is
#: audited by its name: hidden, so no token is ever named so.
REVOKED_DIR = ".revoked"


def _keep_revoked(folder: Path, entry: TokenEntry) -> None:
    revoked = folder / REVOKED_DIR
    if revoked.is_symlink():
        return  # never written through one; the refusal then says "unknown token"
    revoked.mkdir(mode=0o700, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(revoked / entry.name, flags, 0o600)
    except OSError:
        return  # a link there: only the naming of later refusals is lost
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(_entry_text(entry))


def revoked_name(directory: Path, token: str) -> str | None:
    """The name of the revoked token whose secret ``token`` was (None: it never was one)."""
    if not token or len(token) > MAX_TOKEN_FILE:
        return None
    digest = _digest(token)
    revoked = _tokens_dir(directory) / REVOKED_DIR
    if revoked.is_symlink() or not revoked.is_dir():
        return None
    for path in sorted(revoked.iterdir()):
        if TOKEN_NAME.fullmatch(path.name):
            try:
                entry = _read_entry(path)
            except (OSError, UsageError):
                continue
            if hmac.compare_digest(entry.digest, digest):
                return entry.name
    return None


def ensure_default(directory: Path) -> str:
    """The server's start: ``<cell>/api-token`` (made if missing) entered as the engineer
    token ``default`` if it is not yet (an older cell keeps its token and its clients)."""
    token = ensure_token(directory)
    path = _tokens_dir(directory) / DEFAULT_NAME
    try:
        entry = _read_entry(path)
    except FileNotFoundError:
        entry = None
    except UsageError:
        path.unlink()  # a broken default entry: made again from api-token
        entry = None
    # An expiry put in by hand is dropped too: the local CLI acts with api-token.
    if (
        entry is None
        or entry.expires is not None
        or not hmac.compare_digest(entry.digest, _digest(token))
    ):
        path.unlink(missing_ok=True)
        _write_entry(directory, DEFAULT_NAME, "engineer", token)
    return token


def _entry_of(directory: Path, token: str) -> TokenEntry | None:
    """The entry whose secret ``token`` is, expired or not."""
    if not token or len(token) > MAX_TOKEN_FILE:
        return None
    digest = _digest(token)
    found = None
    for entry in list_tokens(directory):
        if hmac.compare_digest(entry.digest, digest):
            found = entry
    return found


def identify(directory: Path, token: str) -> TokenEntry | None:
    """The entry whose secret ``token`` is, read now: None for a token that is none of the
    cell's, revoked (refused at once) or past its expiry."""
    entry = _entry_of(directory, token)
    return None if entry is None or entry.expired() else entry


def expired_entry(directory: Path, token: str) -> TokenEntry | None:
    """The entry of ``token`` when it is one of the cell's past its expiry (None otherwise):
    for a client to say why it is refused (:class:`TokenExpired`)."""
    entry = _entry_of(directory, token)
    return entry if entry is not None and entry.expired() else None


def check_unexpired(directory: Path, token: str) -> None:
    """Raise :class:`TokenExpired` if ``token`` is one of the cell's named tokens past its
    expiry. A cell whose tokens this user cannot read is left to the server to judge."""
    try:
        entry = expired_entry(directory, token)
    except (OSError, UsageError):
        return
    if entry is not None:
        raise TokenExpired(entry)


def still_valid(directory: Path, entry: TokenEntry) -> bool:
    """Whether ``entry`` is still there, unchanged (not revoked, not made again), and not
    past its expiry: a session it opened ends at that time."""
    try:
        now = _read_entry(_tokens_dir(directory) / entry.name)
    except (OSError, UsageError):
        return False
    return now == entry and not now.expired()
