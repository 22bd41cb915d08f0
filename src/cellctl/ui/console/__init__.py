"""The operator console (Textual): the source's menu program on a live screen.

``cellctl console`` (:func:`console_command`) runs :class:`~cellctl.ui.console.app.ConsoleApp`
on the cell: attached to a running controller's API, or standalone on the machines' links.
"""

from cellctl.ui.console.command import console_command

__all__ = ["console_command"]
