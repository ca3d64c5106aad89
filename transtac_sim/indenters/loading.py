"""Loading rigid indenter meshes (STL/OBJ/PLY) in declared units, with checks and documented repairs.

Returned meshes are in millimetres, in the indenter's own frame (the file's origin is its reference
point). Repairs applied silently and reported in ``IndenterMesh.repairs``: merging duplicate vertices,
dropping degenerate (zero-area) and duplicate faces, and making normals consistent and outward.
Refused with ``IndenterMeshError``: unreadable or empty files, open (non-watertight) meshes after those
repairs, several disconnected bodies, and sizes absurd for the declared unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

#: Millimetres per declared unit.
MM_PER_UNIT = {"mm": 1.0, "m": 1000.0, "inch": 25.4}
#: A tactile indenter's largest extent must lie in this range once converted to mm.
PLAUSIBLE_EXTENT_MM = (0.05, 500.0)


class IndenterMeshError(ValueError):
    """An indenter mesh that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class IndenterMesh:
    mesh: trimesh.Trimesh  # watertight, outward normals, mm
    source: str
    repairs: tuple[str, ...]


def _fail(path: Path | str, msg: str) -> IndenterMeshError:
    return IndenterMeshError(f"{path}: {msg}")


def check_and_repair(mesh: trimesh.Trimesh, source: str | Path, units: str = "mm") -> IndenterMesh:
    """Scale ``mesh`` to mm, repair what can be repaired, refuse what cannot."""
    if units not in MM_PER_UNIT:
        raise _fail(source, f"unknown unit {units!r} (allowed: {', '.join(MM_PER_UNIT)})")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise _fail(source, "no faces could be read: the file is empty, cut short, or not a mesh file")
    if not np.isfinite(mesh.vertices).all():
        raise _fail(source, "the mesh has NaN or infinite vertex coordinates")
    mesh = mesh.copy()
    mesh.apply_scale(MM_PER_UNIT[units])
    extent = float(mesh.extents.max())
    lo, hi = PLAUSIBLE_EXTENT_MM
    if not lo <= extent <= hi:
        guesses = [u for u, s in MM_PER_UNIT.items() if lo <= extent / MM_PER_UNIT[units] * s <= hi and u != units]
        hint = f"; did you mean units = {guesses[0]!r}?" if guesses else ""
        raise _fail(source, f"largest extent is {extent:g} mm with units = {units!r}, outside the plausible "
                            f"{lo}..{hi} mm for an indenter{hint}")
    repairs = []
    n_v = len(mesh.vertices)
    mesh.merge_vertices()
    if len(mesh.vertices) < n_v:
        repairs.append(f"merged {n_v - len(mesh.vertices)} duplicate vertices")
    keep = mesh.nondegenerate_faces(height=1e-9 * extent) & mesh.unique_faces()
    if not keep.all():
        mesh.update_faces(keep)
        mesh.remove_unreferenced_vertices()
        repairs.append(f"dropped {int((~keep).sum())} degenerate or duplicate faces")
    if len(mesh.faces) < 4:
        raise _fail(source, f"only {len(mesh.faces)} usable faces left after dropping degenerate ones")
    bodies = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1)
    if len(bodies) > 1:
        raise _fail(source, f"the mesh has {len(bodies)} separate bodies; an indenter must be one body "
                            "(split it into several indenters in the scene file)")
    if not mesh.is_watertight:
        raise _fail(source, f"the mesh is not watertight ({len(mesh.faces)} faces, "
                            f"{len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))} open edges); "
                            "close its holes in a mesh editor")
    was_consistent = mesh.is_winding_consistent and mesh.volume > 0
    trimesh.repair.fix_normals(mesh)
    if not was_consistent:
        repairs.append("made face winding consistent and outward")
    if mesh.volume <= 0:
        raise _fail(source, "the mesh encloses no volume")
    return IndenterMesh(mesh=mesh, source=str(source), repairs=tuple(repairs))


def load_indenter_mesh(path: str | Path, units: str) -> IndenterMesh:
    """Read ``path`` (STL/OBJ/PLY) in ``units`` and return the checked mesh in mm."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise _fail(path, f"cannot be read as a mesh ({type(e).__name__}: {e})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise _fail(path, "contains no triangle mesh")
    return check_and_repair(loaded, path, units)
