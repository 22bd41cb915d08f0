"""The Kerf 100 bar saw as a cellctl machine kind (entry point ``kerf100`` in
``cellctl.machine_kinds``): its line protocol, cut lists, driver, emulator and menu."""
