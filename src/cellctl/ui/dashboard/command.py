"""``cellctl dashboard``: open the running cell's dashboard in a browser.

The page is at ``[api] listen`` of cell.toml. The browser is given a code good once
(``http://127.0.0.1:7125/#code=...``, :mod:`cellctl.ui.dashboard.handover`), which the page
swaps for the token: a browser keeps its URL in its command line, where every user of the host
reads it. ``--print`` prints the URL with the token itself in its fragment
(``#token=...``), which a browser never sends to a server or writes to a log.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
import webbrowser
from pathlib import Path

import click

from cellctl.errors import AccessDenied, UsageError
from cellctl.service.machines import load_cell_file
from cellctl.service.token import TOKEN_ENV, TOKEN_FILE, client_token
from cellctl.ui.common import cell_dir, console

#: Seconds to wait for the controller to answer.
ANSWER_TIMEOUT = 3.0


def dashboard_url(directory: Path) -> str:
    """The dashboard's URL with the token in its fragment; refused clearly when the cell has
    no TCP listener, no token, or no controller answering there."""
    base, token = _dashboard(directory)
    return f"{base}/#token={token}"


def handover_url(directory: Path) -> str:
    """The dashboard's URL with a code good once in its fragment (the page swaps it for the
    token); refused as :func:`dashboard_url` is."""
    base, token = _dashboard(directory)
    request = urllib.request.Request(
        f"{base}/dashboard/handover/new", data=b"", headers={"Authorization": f"Bearer {token}"}
    )
    try:
        with urllib.request.urlopen(request, timeout=ANSWER_TIMEOUT) as answer:
            code = json.loads(answer.read())["code"]
    except (OSError, ValueError, KeyError, TypeError):
        raise UsageError(
            f"the controller on {base} gave no code to open the dashboard with: "
            "use `cellctl dashboard --print`"
        ) from None
    return f"{base}/#code={code}"


def _dashboard(directory: Path) -> tuple[str, str]:
    """The dashboard's base URL and the token to open it with (see :func:`dashboard_url`)."""
    from cellctl.service.server import parse_listen  # the API server: imported when used

    if not (directory / "cell.toml").is_file():
        raise UsageError(f"no cell at {directory}: it has no cell.toml (--cell DIR names one)")
    api = load_cell_file(directory).get("api")
    listen = api.get("listen") if isinstance(api, dict) else None
    if not isinstance(listen, str) or not listen:
        raise UsageError(
            f"{directory / 'cell.toml'} names no [api] listen address: add "
            '[api] listen = "127.0.0.1:7125" and restart `cellctl run` to serve the dashboard'
        )
    remote = isinstance(api, dict) and api.get("allow_remote") is True
    host, port = parse_listen(listen, allow_remote=remote)
    if host in ("0.0.0.0", "::"):
        host = "127.0.0.1"
    base = f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"
    try:
        # $CELLCTL_TOKEN first, as every client (a named token: the page acts with its role).
        token = client_token(directory)  # a link or a short token: UsageError, what to do
    except AccessDenied:
        token = ""
    if not token:
        raise UsageError(
            f"no API token in {directory / TOKEN_FILE} and no ${TOKEN_ENV}: start the "
            "controller (`cellctl run`) first, or set a token of `cellctl token add`"
        )
    request = urllib.request.Request(
        f"{base}/server/info", headers={"Authorization": f"Bearer {token}"}
    )
    try:
        with urllib.request.urlopen(request, timeout=ANSWER_TIMEOUT) as answer:
            info = json.loads(answer.read())
    except urllib.error.HTTPError as e:
        if e.code == 401:
            raise AccessDenied(
                f"the API on {base} refused the token in {directory / TOKEN_FILE}: "
                "is it another cell's controller?"
            ) from None
        raise UsageError(f"the API on {base} answered HTTP {e.code}") from None
    except (OSError, ValueError):
        raise UsageError(
            f"no controller answers on {base}: start `cellctl --cell {directory} run` first"
        ) from None
    if not isinstance(info, dict) or info.get("mode") != "attached":
        raise UsageError(f"no controller runs behind {base}: start `cellctl run` first")
    return base, token


@click.command("dashboard")
@click.option(
    "--print", "print_only", is_flag=True, help="Print the URL (the token in it); open no browser."
)
@click.pass_context
def dashboard_command(ctx: click.Context, print_only: bool) -> None:
    """Open the running cell's dashboard in a browser (with a code good once for a minute,
    not the token: a browser's command line is read by every user of the host).

    The controller (`cellctl run`) serves it on [api] listen of cell.toml. --print prints
    the URL with the token in its fragment, to paste in a browser.
    """
    if print_only:
        console.print(dashboard_url(cell_dir(ctx)), markup=False, soft_wrap=True)
        return
    url = handover_url(cell_dir(ctx))
    if not webbrowser.open(url):
        raise UsageError("no browser could be started here: use `cellctl dashboard --print`")
    console.print(f"dashboard opened in your browser ({url.split('#')[0]})", markup=False)


def serve_dashboard_in(directory: Path) -> str:
    """Give a cell (the demo's emulated one) an ``[api] listen`` on a free loopback port and
    a token; the dashboard's URL (with the token in its fragment) once its controller runs."""
    import socket

    from cellctl.service.token import ensure_token

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = int(probe.getsockname()[1])
    toml = directory / "cell.toml"
    text = toml.read_text(encoding="utf-8")
    if "[api]" in text:
        raise UsageError(f"{toml} already has an [api] table")
    toml.write_text(text.rstrip("\n") + f'\n\n[api]\nlisten = "127.0.0.1:{port}"\n', "utf-8")
    return f"http://127.0.0.1:{port}/#token={ensure_token(directory)}"
