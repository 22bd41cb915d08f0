"""cellctl.drivers"""
