"""Helpers for testing cellctl and for programs built on it.

- :func:`expected_exchange` / :class:`ScriptedLink` (:mod:`cellctl.testing.scripted`):
  replay the exact bytes of the manual to a driver.
- :class:`cellctl.testing.rig.CellRig`: the emulated cell and its controller in one process,
  with an operator at the command line -- the way to run a whole cell in one process (tests,
  benches, notebooks). Import it from :mod:`cellctl.testing.rig`: it sits above every layer
  (it drives the CLI as an operator would), so importing :mod:`cellctl.testing` alone does not
  load it.
"""

from cellctl.testing.scripted import ScriptedLink, expected_exchange

__all__ = ["ScriptedLink", "expected_exchange"]
