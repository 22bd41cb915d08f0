"""Machine kinds: what every kind declares, the registry that finds them, the families the
cell talks to, and the conditions every surface shows.

``Condition`` is the one word a surface needs for a machine (offline, idle, busy, ...); each
kind maps its own states onto it. A surface reads the condition, never the state's words.
A kind (:class:`~cellctl.kinds.kind.MachineKind`) lives in a package of its own and is found
through :mod:`cellctl.kinds.registry`; nobody imports a kind by name.
"""

from cellctl.kinds.condition import Condition, LastError

__all__ = ["Condition", "LastError"]
