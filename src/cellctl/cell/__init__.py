"""cellctl.cell"""
