"""Volume: surface extraction, point clouds, compounding and reconstruction.

Takes a volume session and a calibration; gives a point cloud (PLY), a volume (NRRD) and the
surface error against the CAD model.
"""
