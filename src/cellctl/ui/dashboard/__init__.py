"""The web dashboard: a live page of the cell on the control API's HTTP listener.

``cellctl run`` serves it at ``/`` (``extra_routes=dashboard_routes``); ``cellctl dashboard``
opens it in a browser with the token in the URL's fragment. Its assets ship in ``static/``.
"""

from cellctl.ui.dashboard.command import dashboard_command
from cellctl.ui.dashboard.routes import dashboard_routes

__all__ = ["dashboard_command", "dashboard_routes"]
