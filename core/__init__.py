"""probecal core: algorithms and models, no UI.

Frames and names follow SPEC §2: every transform is a 4x4 matrix named ``a_to_b`` that maps
coordinates in frame ``a`` to frame ``b``; lengths are in mm and angles in degrees.
"""

from pathlib import Path

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
