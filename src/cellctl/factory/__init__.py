"""The system level above the cells (docs/factory.md, docs/opcua.md).

- :mod:`~cellctl.factory.config`, :mod:`~cellctl.factory.store` (its records in
  :mod:`~cellctl.factory.records`), :mod:`~cellctl.factory.dispatch`,
  :mod:`~cellctl.factory.controller`: ``cellctl factory``, the system controller that spreads
  orders over the cells through an MQTT broker; :mod:`~cellctl.factory.cancel`: cancelling
  one of its orders, at the factory and at its cell;
- :mod:`~cellctl.factory.broker`: a private Mosquitto for tests and demos;
- :mod:`~cellctl.factory.emulated`: a broker and N emulated cells (``cellctl emulate factory``);
- :mod:`~cellctl.factory.bound`: the least makespan of a batch split over cells;
- :mod:`~cellctl.factory.opcua`: each cell's OPC UA server.
"""
