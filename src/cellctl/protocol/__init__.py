"""cellctl.protocol"""
