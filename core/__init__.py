"""probecal core: algorithms and models, no UI.

Frames and names follow design §2: every transform is a 4x4 matrix named ``a_to_b`` that maps
coordinates in frame ``a`` to frame ``b``; lengths are in mm and angles in degrees.
"""

import os
from importlib import resources
from pathlib import Path

# Our linear algebra is many small problems; multi-threaded BLAS only contends for the two cores.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

STATIC_DIR = Path(str(resources.files("probecal.static")))
"""The shipped assets (package data: an installed wheel's as well as a checkout's ``static/``)."""
