"""The system level above the cells (docs/factory.md, docs/opcua.md).

- :mod:`~cellctl.factory.config`, :mod:`~cellctl.factory.store`,
  :mod:`~cellctl.factory.dispatch`, :mod:`~cellctl.factory.controller`: ``cellctl factory``,
  the system controller that spreads orders over the cells through an MQTT broker;
- :mod:`~cellctl.factory.broker`: a private Mosquitto for tests and demos;
- :mod:`~cellctl.factory.emulated`: a broker and N emulated cells (``cellctl emulate factory``);
- :mod:`~cellctl.factory.bound`: the least makespan of a batch split over cells;
- :mod:`~cellctl.factory.opcua`: each cell's OPC UA server.
"""
