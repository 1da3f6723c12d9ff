"""Remakes static/meshes/test_object.stl, the volume test object the twin scans: steps, a slope
and a curved top on a 60 x 40 mm block, a watertight prism (mm, object frame: origin at a bottom
corner, x along the profile, y along the extrusion, z up).

    .venv/bin/python benchmarks/make_test_object.py
"""

from __future__ import annotations

import numpy as np
import trimesh

from probecal.core.twin.testobject import TEST_OBJECT_FILE

LENGTH_X_MM = 60.0
DEPTH_Y_MM = 40.0


def top_profile() -> np.ndarray:
    """(K, 2) points (x, z) of the top surface, mm, left to right; steps repeat an x."""
    steps = [(0.0, 10.0), (8.0, 10.0), (8.0, 14.0), (16.0, 14.0), (16.0, 18.0), (22.0, 18.0)]
    slope = [(22.0, 12.0), (38.0, 22.0)]
    arc_x = np.linspace(38.0, 60.0, 23)
    radius, centre_x, centre_z = 16.0, 49.0, 6.5
    arc = [(x, centre_z + np.sqrt(radius**2 - (x - centre_x) ** 2)) for x in arc_x]
    return np.array(steps + slope + arc)


def _side_triangles(profile: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """Triangulate the side polygon under the profile (x-z plane) without T-junctions.

    Each strip between consecutive distinct x is a convex polygon whose vertical edges may hold
    several profile points (a step); fanning from the strip's centre keeps every edge shared.
    Returns 2D vertices (x, z) and triangles wound counter-clockwise seen from -y.
    """
    xs = np.unique(profile[:, 0])
    points = [tuple(p) for p in profile] + [(x, 0.0) for x in xs]
    index = {p: i for i, p in enumerate(dict.fromkeys(points))}
    vertices = list(index)

    def column(x: float, height: float) -> list[tuple[float, float]]:
        """Vertices on the vertical line at x from the bottom up to ``height``, ascending."""
        return sorted({p for p in vertices if p[0] == x and p[1] <= height}, key=lambda p: p[1])

    triangles = []
    for a, b in zip(xs[:-1], xs[1:]):
        left = column(a, profile[profile[:, 0] == a][-1, 1])
        right = column(b, profile[profile[:, 0] == b][0, 1])
        ring = [left[0]] + right + left[:0:-1]  # counter-clockwise in (x, z)
        centre = (0.5 * (a + b), 0.5 * min(left[-1][1], right[-1][1]))
        index[centre] = len(vertices)
        vertices.append(centre)
        for p, q in zip(ring, ring[1:] + ring[:1]):
            triangles.append([index[centre], index[p], index[q]])
    return np.array(vertices), triangles


def build_test_object() -> trimesh.Trimesh:
    """A watertight prism: the top profile extruded along y, closed by flat sides and bottom."""
    profile = top_profile()
    side, side_triangles = _side_triangles(profile)
    n = len(side)
    vertices = np.concatenate(
        [np.column_stack([side[:, 0], np.zeros(n), side[:, 1]]),
         np.column_stack([side[:, 0], np.full(n, DEPTH_Y_MM), side[:, 1]])]
    )
    # (x, z) counter-clockwise seen from -y gives the y = 0 side an outward (-y) normal.
    faces = [[c, p, q] for c, p, q in side_triangles]
    faces += [[c + n, q + n, p + n] for c, p, q in side_triangles]
    lookup = {tuple(v): i for i, v in enumerate(side.tolist())}
    outline = [lookup[tuple(p)] for p in profile.tolist()]
    outline = [outline[0]] + [i for i, j in zip(outline[1:], outline[:-1]) if i != j]
    ring = outline + [lookup[(x, 0.0)] for x in np.unique(profile[:, 0])[::-1]]
    for i, j in zip(ring, ring[1:] + ring[:1]):
        faces += [[i, j, j + n], [i, j + n, i + n]]
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=True)
    return mesh


def main() -> None:
    mesh = build_test_object()
    TEST_OBJECT_FILE.write_bytes(mesh.export(file_type="stl"))
    print(f"{TEST_OBJECT_FILE}: {len(mesh.faces)} faces, watertight {mesh.is_watertight}, "
          f"{mesh.bounds[1] - mesh.bounds[0]} mm")


if __name__ == "__main__":
    main()
