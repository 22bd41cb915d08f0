"""cellctl.mailbox"""
