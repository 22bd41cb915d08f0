"""The ``iso-cnc`` kind: CNC controls with an RS-232 port fed ISO-code G-code (Fanuc / Haas
style) with DC1-DC4 flow control (spec: iso-dnc-rs232.md)."""
