"""``python -m cellctl``: the same as the ``cellctl`` command."""

from cellctl.ui.cli import main

main(prog_name="cellctl")
