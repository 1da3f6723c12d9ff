"""The CAD model a reconstruction is measured against: the mesh file (checked), where the object sits
(``object_to_base``, mm) and whether to register it by ICP first."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from trimesh.resolvers import FilePathResolver

from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.transforms import invert_transform
from probecal.core.io.files import existing_file, inside, read_bytes
from probecal.core.io.limits import checked_bytes
from probecal.core.io.session import MANIFEST, Session

MESH_BYTES_PER_FILE_BYTE = 16  # what loading a mesh may take per byte of its file, at most


class _MeshFiles(FilePathResolver):
    """The files a mesh file (``owner``) names, as trimesh asks for them (an OBJ's ``mtllib``, a
    glTF's ``buffers[].uri``): only regular files inside its folder ``root``, read without blocking
    (:func:`core.io.files.inside`, :func:`core.io.files.read_bytes`)."""

    def __init__(self, root: Path, owner: Path):
        super().__init__(str(root))
        self.owner = owner

    def get(self, name: str) -> bytes:
        return read_bytes(inside(self.parent, name.strip(), self.owner))

    def namespaced(self, namespace: str) -> _MeshFiles:
        return _MeshFiles(inside(self.parent, namespace, self.owner), self.owner)


def read_mesh(path: str | Path) -> trimesh.Trimesh:
    """A CAD triangle mesh (STL, OBJ, PLY, ... in mm) for surface comparison: finite vertices,
    faces of non-zero area only. InputError naming the file for anything else."""
    path = existing_file(path)
    checked_bytes(path, "loading this mesh", (path.stat().st_size, MESH_BYTES_PER_FILE_BYTE))
    data = read_bytes(path)
    try:
        mesh = trimesh.load_mesh(io.BytesIO(data), file_type=path.suffix.lstrip(".").lower(),
                                 resolver=_MeshFiles(path.parent, path))
    except InputError:
        raise
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(path, f"not a readable mesh ({type(exc).__name__})")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "not a triangle mesh")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputError(path, "the mesh has vertices that are not finite numbers")
    mesh.update_faces(mesh.area_faces > 1e-12)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise InputError(path, "every triangle of the mesh has zero area")
    return mesh


@dataclass(frozen=True)
class CadTarget:
    """The CAD mesh (object frame, mm) and where it is believed to sit (``object_to_base``)."""

    mesh: trimesh.Trimesh
    object_to_base: np.ndarray | None  # None: unknown, found by ICP (``register``)
    register: bool  # refine the placement by ICP before measuring

    def start(self, points_base: np.ndarray) -> np.ndarray:
        """Where ICP starts (``object_to_base``, mm): the known placement, or with none the mesh's
        top centre under the centre of the reconstructed points (base frame, z up)."""
        if self.object_to_base is not None:
            return self.object_to_base
        lo, hi = self.mesh.bounds
        top_centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
        placement = np.eye(4)
        placement[:3, 3] = np.array([*points_base[:, :2].mean(axis=0), points_base[:, 2].max()]) - top_centre
        return placement


def cad_placement_from_session(session: Session, phantom_to_base: np.ndarray | None = None) -> np.ndarray | None:
    """A known object pose: the manifest's ``object_to_base`` or, for a simulated session, the
    one in truth.json (where the twin put the object, like PLUS's PhantomToReference). Given
    ``phantom_to_base``, where a calibration registered the phantom (mm, in the frame the poses
    it puts the volume in are), a simulated object is placed where it sits relative to the
    phantom: the frame the robot's own measurements define, which a navigation or overlay
    registered through the phantom lives in."""
    if session.manifest.object_to_base is not None:
        return np.array(session.manifest.object_to_base, dtype=float)
    truth = session.truth()
    if not truth or truth.get("object_to_base") is None:
        return None
    object_to_base = np.array(truth["object_to_base"], dtype=float)
    if phantom_to_base is None or truth.get("phantom_to_base") is None:
        return object_to_base
    return phantom_to_base @ invert_transform(np.array(truth["phantom_to_base"], dtype=float)) @ object_to_base


def session_cad_target(session: Session, mesh_file: str | Path | None = None, register: bool = False,
                       phantom_to_base: np.ndarray | None = None) -> CadTarget | None:
    """What a volume session's reconstruction is measured against: the mesh in ``mesh_file`` or,
    when None, the one the session names (its manifest's ``cad_mesh``, a file inside the session
    folder), placed where the session records the object (:func:`cad_placement_from_session`).
    Every mesh is checked (:func:`read_mesh`). With no recorded placement the object is found
    by ICP when ``register``; otherwise an asked-for ``mesh_file`` is refused with InputError and
    the session's own mesh is left out (None), as it is when the session names none."""
    if mesh_file is None:
        name = session.manifest.cad_mesh
        if name is None:
            return None
        mesh_file = inside(session.path, name, session.path / MANIFEST)
        asked = False
    else:
        asked = True
    mesh = read_mesh(mesh_file)
    placement = cad_placement_from_session(session, phantom_to_base)
    if placement is None and not register:
        if asked:
            raise InputError(session.path, "the object's pose is not recorded; registering the CAD model to the points "
                                           "(ICP) finds it", (Remedy.REGISTER,))
        return None
    return CadTarget(mesh, placement, register)
