"""Acquisition: plans, image sources, pose pairing and sweeps into sessions.

Takes a robot and an image source; gives recorded sessions (frames paired with flange poses).
"""
