"""Temporal calibration: how late the images are relative to the pose stream.

Takes frames with their timestamps and the probe's pose stream over a short motion (a PLUS video
and tracker buffer, or a robot session that kept its pose stream); gives ``image_latency_s``, the
meaning of ``--latency``: a frame stamped ``t`` shows the probe where it was at ``t - image_latency_s``.
"""
