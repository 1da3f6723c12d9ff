"""Geometry: frames, transforms, the N-wire phantom model, the probe's image and the nominal set-up.

Takes numbers; gives 4x4 transforms (mm, ``a_to_b``), wire crossings of an image plane and the
planner's idea of where things are. Reads and writes no files.
"""
