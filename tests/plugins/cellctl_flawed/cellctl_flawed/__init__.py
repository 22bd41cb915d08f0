"""Badly written machine kinds for the plug-in contract's tests (README.md)."""
