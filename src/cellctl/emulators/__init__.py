"""cellctl.emulators"""
