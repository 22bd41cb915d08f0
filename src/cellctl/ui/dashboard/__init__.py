"""The web dashboard: a live page of the cell on the control API's HTTP listener.

``cellctl run`` serves it at ``/`` (``extra_routes=dashboard_routes``); ``cellctl dashboard``
opens it in a browser with the token in the URL's fragment. Its assets ship in ``static/``.
"""

from typing import Any

from cellctl.ui.dashboard.command import dashboard_command

__all__ = ["dashboard_command", "dashboard_routes"]


def __getattr__(name: str) -> Any:
    # The routes (the API server's side) are imported when asked for: `cellctl dashboard`
    # only opens a browser.
    if name == "dashboard_routes":
        from cellctl.ui.dashboard.routes import dashboard_routes

        return dashboard_routes
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
