"""The Dyna 2400 CNC mill: DYNALAN, driver, emulator."""
