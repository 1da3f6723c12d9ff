"""The digital twin: the true set-up, B-mode image synthesis and the volume test object.

Takes a seed and a level; gives frames at flange poses and the ground truth behind them.
"""
