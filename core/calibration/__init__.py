"""Calibration: segmentation, labelling, registration, hand-eye, the solve, its metrics.

Takes a calibration session; gives ``image_to_tool`` with its pixel spacing and how far to trust it.
"""
