"""cellctl.link"""
