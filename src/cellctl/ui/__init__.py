"""cellctl.ui"""
