"""The system level above the cells: orders dispatched to cells over MQTT.

``cellctl.factory.broker.MosquittoBroker`` starts a private Mosquitto for tests and demos.
"""
