"""The 3D-printable volume test object: steps, a slope and a curved top on a 60 x 40 mm block
(``benchmarks/make_test_object.py`` makes its STL).

The object's frame has its origin at a bottom corner, x along the profile, y along the
extrusion and z up (mm). Its top surface faces the probe and echoes brightly.
"""

from __future__ import annotations

import trimesh

from probecal.core import STATIC_DIR

TEST_OBJECT_FILE = STATIC_DIR / "meshes" / "test_object.stl"


def load_test_object() -> trimesh.Trimesh:
    """The shipped STL of the test object (mm, object frame)."""
    return trimesh.load_mesh(TEST_OBJECT_FILE)
