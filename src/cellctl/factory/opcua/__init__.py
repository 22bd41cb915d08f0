"""The cell's OPC UA server (asyncua), shaped after OPC 40501-1 (Machine Tools) as far as it
fits; docs/opcua.md describes the address space, security and how to connect.

::

    server = OpcuaServer(AttachedCell(controller), config.opcua, log=controller.log)
    await server.start()
    await server.close()

:func:`add_user` writes a user into the users file (``cellctl opcua adduser NAME``).
"""

from cellctl.factory.opcua.server import NAMESPACE, OpcuaServer
from cellctl.factory.opcua.users import add_user

__all__ = ["NAMESPACE", "OpcuaServer", "add_user"]
