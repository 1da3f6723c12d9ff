"""Make docs/img/reconstruction_vs_cad.png: the simulated test object's CAD model beside the point
cloud that `probecal reconstruct` builds from a robot sweep, coloured by distance to the CAD.

Run: .venv/bin/python benchmarks/make_volume_figure.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.simulate import simulate_volume
from probecal.core.calibration.result import load_calibration
from probecal.core.geometry.transforms import invert_transform, transform_points
from probecal.core.volume.cad import session_cad_target
from probecal.core.volume.pointcloud import error_colors
from probecal.core.volume.reconstruct import reconstruct_session

OUT = Path(__file__).resolve().parent.parent / "docs" / "img" / "reconstruction_vs_cad.png"
SIZE, SCALE = 520, 7.0  # pixels, pixels per mm
VIEW = Rotation.from_euler("zx", [-35, -55], degrees=True).as_matrix()


def splat(points: np.ndarray, colors: np.ndarray, centre: np.ndarray, size_px: int = 2) -> np.ndarray:
    """Orthographic view of coloured points, nearer points drawn over farther ones."""
    view = (points - centre) @ VIEW.T
    order = np.argsort(view[:, 2])
    u = (SIZE / 2 + SCALE * view[order, 0]).astype(int)
    v = (SIZE / 2 - SCALE * view[order, 1]).astype(int)
    image = np.full((SIZE, SIZE, 3), 255, np.uint8)
    for du in range(size_px):
        for dv in range(size_px):
            ok = (u + du >= 0) & (u + du < SIZE) & (v + dv >= 0) & (v + dv < SIZE)
            image[v[ok] + dv, u[ok] + du] = colors[order][ok][:, ::-1]
    return image


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_volume(Path(tmp) / "v", seed=0)
        cad = session_cad_target(session)
        mesh, placement = cad.mesh, cad.object_to_base
        result = reconstruct_session(session, load_calibration(session.path / "truth.json"), Path(tmp) / "r", cad=cad)
        report, cloud = result.report, result.points_base
    points = transform_points(invert_transform(placement), cloud)
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    samples, faces = trimesh.sample.sample_surface_even(mesh, 300000, seed=0)
    facing = (mesh.face_normals[faces] @ VIEW.T)[:, 2] > 0  # keep faces turned towards the viewer
    samples, faces = samples[facing], faces[facing]
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shade = (0.35 + 0.65 * np.clip(mesh.face_normals[faces] @ light, 0, 1))[:, None]
    cad_colors = (shade * np.array([150, 170, 200])).astype(np.uint8)
    centre = mesh.bounds.mean(axis=0)
    left = splat(samples, cad_colors, centre, size_px=3)
    right = splat(points, error_colors(distance, 0.2), centre)
    for image, text in ((left, "CAD model (test_object.stl)"),
                        (right, f"reconstructed: {len(points)} points, mean {report['surface_mean_mm']:.3f} mm")):
        cv2.putText(image, text, (12, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
    cv2.putText(right, "colour: distance to CAD, blue 0 -> red 0.2 mm", (12, SIZE - 16),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, (40, 40, 40), 1, cv2.LINE_AA)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT), np.hstack([left, np.full((SIZE, 8, 3), 200, np.uint8), right]))
    print(f"{OUT}: mean {report['surface_mean_mm']:.3f} mm, p95 {report['surface_p95_mm']:.3f} mm")


if __name__ == "__main__":
    main()
