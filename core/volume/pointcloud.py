"""Surface point clouds from tracked frames, and their comparison with a CAD mesh (design §5).

A surface pixel (u, v) maps to the base frame by
``tool_to_base · image_to_tool_rigid · diag(sx, sy, 1) · (u, v, 0, 1)`` (thesis eq. 3.25). Points
are in mm in the base frame; meshes in their own (object) frame, placed by ``object_to_base``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import invert_transform, transform_points
from probecal.core.io.files import read_bytes, write_atomic

VOXEL_MM = 0.2  # duplicate removal: one point per voxel of this size
OUTLIER_NEIGHBOURS = 20
OUTLIER_STD = 2.0
FLOOR_TOLERANCE_MM = 0.6
CROP_MARGIN_MM = 1.0


def base_points_from_pixels(u: np.ndarray, v: np.ndarray, tool_to_base: np.ndarray,
                            image_to_tool: np.ndarray) -> np.ndarray:
    """(n, 3) base-frame points of pixels of one frame; ``image_to_tool`` includes the spacing."""
    pixels = np.column_stack([u, v, np.zeros(len(u))])
    return transform_points(tool_to_base @ image_to_tool, pixels)


def clean(points: np.ndarray, voxel_mm: float = VOXEL_MM) -> np.ndarray:
    """Merge overlapping sweeps: voxel down-sampling, then statistical outlier removal (open3d)."""
    if len(points) == 0:
        return points
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud = cloud.voxel_down_sample(voxel_mm)
    if len(cloud.points) > OUTLIER_NEIGHBOURS:
        cloud, _ = cloud.remove_statistical_outlier(OUTLIER_NEIGHBOURS, OUTLIER_STD)
    return np.asarray(cloud.points)


def remove_floor(points: np.ndarray, up: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Drop the tank floor: the lowest large plane facing ``up`` (RANSAC, open3d), if there is one
    below everything else. The object stands on it, so it is not part of the object's surface."""
    up = np.asarray(up, dtype=float)
    if len(points) < 100:
        return points
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.utility.random.seed(0)
    plane, inliers = cloud.segment_plane(FLOOR_TOLERANCE_MM, 3, 500)
    normal = np.asarray(plane[:3]) / np.linalg.norm(plane[:3])
    if abs(normal @ up) < 0.98 or len(inliers) < 0.05 * len(points):
        return points
    height = points @ up
    on_plane = np.zeros(len(points), bool)
    on_plane[inliers] = True
    floor = np.median(height[on_plane])
    if (~on_plane).any() and floor > np.percentile(height[~on_plane], 1):
        return points  # a plane with points below it is a face of the object, not the floor
    return points[height > floor + FLOOR_TOLERANCE_MM]


def _ply_layout(n: int, colored: bool) -> tuple[np.dtype, bytes]:
    """The vertex record and the header of the PLY :func:`write_ply` writes for ``n`` points."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}",
              "property float x", "property float y", "property float z"]
    if colored:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    return np.dtype(fields), ("\n".join([*header, "end_header"]) + "\n").encode()


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of points (mm) with optional uint8 RGB colours; written atomically."""
    points = np.asarray(points, dtype="<f4")
    record, header = _ply_layout(len(points), colors is not None)
    data = np.empty(len(points), dtype=record)
    data["x"], data["y"], data["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        data["red"], data["green"], data["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    write_atomic(path, header + data.tobytes())


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The points (N, 3) mm and colours (N, 3) uint8 or None of a PLY :func:`write_ply` wrote;
    InputError naming ``path`` for any other file, or one whose size is not its header's."""
    data = read_bytes(path)
    end = data.find(b"end_header\n", 0, 1024)
    lines = data[:max(end, 0)].split(b"\n")
    count = lines[2].removeprefix(b"element vertex ") if end > 0 and len(lines) > 2 else b""
    if not count.isdigit():
        raise InputError(path, "not a point cloud probecal wrote (binary PLY of vertices)")
    n = int(count)
    for colored in (False, True):
        record, header = _ply_layout(n, colored)
        if data.startswith(header):
            if len(data) != len(header) + n * record.itemsize:
                raise InputError(path, f"holds {len(data) - len(header)} bytes of points, not the {n} its header says")
            vertices = np.frombuffer(data, record, count=n, offset=len(header))
            points = np.column_stack([vertices["x"], vertices["y"], vertices["z"]]).astype(float)
            colors = np.column_stack([vertices["red"], vertices["green"], vertices["blue"]]) if colored else None
            return points, colors
    raise InputError(path, "not a point cloud probecal wrote (binary PLY of vertices)")


def error_colors(distances_mm: np.ndarray, full_scale_mm: float = 1.0) -> np.ndarray:
    """Blue (0 mm) through green to red (>= full scale): a per-point error colouring."""
    t = np.clip(np.asarray(distances_mm) / full_scale_mm, 0.0, 1.0)
    red = np.clip(2 * t - 1, 0, 1)
    blue = np.clip(1 - 2 * t, 0, 1)
    green = 1 - red - blue
    return (np.column_stack([red, green, blue]) * 255).astype(np.uint8)


@dataclass(frozen=True)
class SurfaceError:
    """design §5 surface error (mm): both directed point-to-mesh distances."""

    points_to_cad_mean: float
    points_to_cad_p95: float
    cad_to_points_mean: float
    cad_to_points_p95: float
    point_distances: np.ndarray  # per reconstructed point, to the CAD surface



def refine_cad_placement(points: np.ndarray, mesh: trimesh.Trimesh, object_to_base: np.ndarray,
                    max_distance_mm: float = 3.0) -> np.ndarray:
    """Refine ``object_to_base`` by point-to-plane ICP (open3d) of the points onto the CAD
    surface, sampled where it faces up (the side the probe sees) and placed at the start pose."""
    samples, faces = trimesh.sample.sample_surface_even(mesh, 40000, seed=0)
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(transform_points(object_to_base, samples)))
    target.normals = o3d.utility.Vector3dVector(mesh.face_normals[faces] @ object_to_base[:3, :3].T)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    result = o3d.pipelines.registration.registration_icp(
        source, target, max_distance_mm, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60),
    )
    return invert_transform(np.asarray(result.transformation)) @ object_to_base


CLOSEST_PAIRS = 100_000
"""Point-face pairs looked up on the mesh at once (about 150 bytes each): trimesh's closest-point
search takes memory per point and per face near it, and every face is near a point far off the
mesh (a calibration 100 mm off took 260 MB at 10 000 points a call)."""


def surface_error(points_base: np.ndarray, mesh: trimesh.Trimesh, object_to_base: np.ndarray) -> SurfaceError:
    """Point-to-mesh distances both ways. For CAD -> points, the CAD surface is cropped to what
    was scanned: sample points of faces that face the probes (up in the base frame) and lie within
    the scanned footprint, each to its nearest reconstructed point."""
    if len(points_base) == 0:
        raise ValueError("no surface points to compare")
    points_obj = transform_points(invert_transform(object_to_base), points_base)
    per_call = max(1, CLOSEST_PAIRS // len(mesh.faces))
    chunks = np.array_split(points_obj, -(-len(points_obj) // per_call))
    to_cad = np.concatenate([trimesh.proximity.closest_point(mesh, chunk)[1] for chunk in chunks])
    samples, faces = trimesh.sample.sample_surface_even(mesh, 40000, seed=0)
    up_obj = invert_transform(object_to_base)[:3, :3] @ np.array([0.0, 0.0, 1.0])
    lo, hi = points_obj.min(axis=0) + CROP_MARGIN_MM, points_obj.max(axis=0) - CROP_MARGIN_MM
    seen = ((mesh.face_normals[faces] @ up_obj > 0.3)
            & np.all((samples[:, :2] >= lo[:2]) & (samples[:, :2] <= hi[:2]), axis=1))
    to_points, _ = cKDTree(points_obj).query(samples[seen])
    return SurfaceError(
        float(to_cad.mean()), float(np.percentile(to_cad, 95)),
        float(to_points.mean()) if len(to_points) else float("nan"),
        float(np.percentile(to_points, 95)) if len(to_points) else float("nan"),
        to_cad,
    )
