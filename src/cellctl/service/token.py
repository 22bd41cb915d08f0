"""The cell's API token, ``<cell>/api-token``: made once (0600), read by every client::

    token = ensure_token(Path("cell"))   # the server: read it, or make it on the first run
    token = read_token(Path("cell"))     # a client: read it (AccessDenied when there is none)

The file is opened with ``O_NOFOLLOW`` and made with ``O_EXCL``: a symbolic link put in its
place is refused, never followed (its target would become the token, or be overwritten). A
token shorter than :data:`MIN_TOKEN` characters is refused too. Both refusals say what to do:
remove the file, and the next ``cellctl run`` writes a new token.
"""

from __future__ import annotations

import errno
import os
import secrets
import stat
from pathlib import Path

from cellctl.errors import AccessDenied, UsageError

TOKEN_FILE = "api-token"
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
    except OSError as e:
        raise AccessDenied(f"cannot read the API token {path}: {e}") from None
