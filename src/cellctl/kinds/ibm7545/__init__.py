"""The IBM 7545 and 7547 robots (one package: the 7547 is a variant): records, AML/E,
driver, emulator."""
