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

At its start the server enters ``api-token`` as the engineer token ``default``
(:func:`ensure_default`), so an older cell and its clients go on as before.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import os
import re
import secrets
import stat
import tomllib
from dataclasses import dataclass
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
    the CLI and the console act with its role), else ``<cell>/api-token``."""
    given = os.environ.get(TOKEN_ENV, "").strip()
    if any(not "!" <= c <= "~" for c in given):
        # Refused here, not sent: a header with it is not HTTP (and would be echoed back).
        raise AccessDenied(
            f"${TOKEN_ENV} is not a token: it holds a space, a line break or a character "
            "a token never has; set it to a token as `cellctl token add` printed it"
        )
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
    """One named token as stored: its name, role, when it was made, and a SHA-256 of the
    secret (the secret itself is shown once, at :func:`add_token`)."""

    name: str
    role: str
    created: float
    digest: str


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
    if (
        name != path.name
        or role not in ROLES
        or not isinstance(created, int | float)
        or not isinstance(digest, str)
        or not re.fullmatch(r"[0-9a-f]{64}", digest)
    ):
        raise UsageError(f"{path} is not a token entry; revoke it (cellctl token revoke)")
    return TokenEntry(str(name), str(role), float(created), digest)


def _write_entry(directory: Path, name: str, role: str, token: str) -> TokenEntry:
    folder = _tokens_dir(directory)
    try:
        # Never parents: a missing cell directory is a mistyped one, not one to make here.
        folder.mkdir(mode=0o700, exist_ok=True)
    except FileNotFoundError:
        raise UsageError(f"no cell at {os.path.abspath(directory)}: no such directory") from None
    except OSError as e:
        raise UsageError(f"{folder}: cannot make the tokens' directory: {e.strerror}") from None
    entry = TokenEntry(name, role, round(current_clock().now(), 3), _digest(token))
    path = folder / name
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, 0o600)
    except FileExistsError:
        raise UsageError(f"a token named {name!r} exists: revoke it first") from None
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(
            f'name = "{name}"\nrole = "{role}"\ncreated = {entry.created}\n'
            f'sha256 = "{entry.digest}"\n'
        )
    return entry


def add_token(directory: Path, name: str, role: str) -> str:
    """Make a token ``name`` with ``role``; the secret is returned once and kept only as a
    hash. UsageError for a bad name or role, or a name already taken."""
    check_name(name)
    check_role(role)
    token = secrets.token_urlsafe(32)
    _write_entry(directory, name, role, token)
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
        f.write(
            f'name = "{entry.name}"\nrole = "{entry.role}"\ncreated = {entry.created}\n'
            f'sha256 = "{entry.digest}"\n'
        )


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
    if entry is None or not hmac.compare_digest(entry.digest, _digest(token)):
        path.unlink(missing_ok=True)
        _write_entry(directory, DEFAULT_NAME, "engineer", token)
    return token


def identify(directory: Path, token: str) -> TokenEntry | None:
    """The entry whose secret ``token`` is, read now (a revoked token is refused at once)."""
    if not token or len(token) > MAX_TOKEN_FILE:
        return None
    digest = _digest(token)
    found = None
    for entry in list_tokens(directory):
        if hmac.compare_digest(entry.digest, digest):
            found = entry
    return found


def still_valid(directory: Path, entry: TokenEntry) -> bool:
    """Whether ``entry`` is still there, unchanged (not revoked, not made again)."""
    try:
        now = _read_entry(_tokens_dir(directory) / entry.name)
    except (OSError, UsageError):
        return False
    return now == entry
