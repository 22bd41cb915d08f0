"""Machine kinds: what every kind declares, and the conditions every surface shows.

``Condition`` is the one word a surface needs for a machine (offline, idle, busy, ...); each
kind maps its own states onto it. A surface reads the condition, never the state's words.
"""

from cellctl.kinds.condition import Condition, LastError

__all__ = ["Condition", "LastError"]
