"""cellctl: drivers, emulators and a cell controller for serial-protocol machining cells."""

__version__ = "0.1.0"
