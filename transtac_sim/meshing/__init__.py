"""Meshing stage: the gel's tet mesh (cached) and the markers embedded in it."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

from transtac_sim.meshing import cache
from transtac_sim.meshing.contact_region import contact_region
from transtac_sim.meshing.embedding import Embedding, embed_points
from transtac_sim.meshing.gel_mesh import GelMesh, Rect, tetrahedralize_gel
from transtac_sim.meshing.quality import MeshQuality, mesh_quality
from transtac_sim.scene_setup import SceneSetup

__all__ = ["Embedding", "GelMesh", "MeshedGel", "embed_points", "mesh_gel", "mesh_quality"]


@dataclass(frozen=True)
class MeshedGel:
    mesh: GelMesh
    markers: Embedding
    quality: MeshQuality
    contact_region: Rect | None
    cache_key: str
    cache_hit: bool
    seconds: float


def mesh_gel(setup: SceneSetup, *, use_cache: bool = True) -> MeshedGel:
    """Tet mesh of the scene's gel, refined under its contact region, with the markers embedded."""
    t0 = time.perf_counter()
    size = setup.sensor.gel_size_mm
    cfg = setup.scene.mesh
    region = contact_region(setup)
    key = cache.mesh_key(size_mm=list(size), region=region_inputs(setup) if region else None,
                         edge_mm=cfg.edge_mm, contact_edge_mm=cfg.contact_edge_mm)
    mesh = cache.load_cached(key) if use_cache else None
    hit = mesh is not None
    if mesh is None:
        mesh = tetrahedralize_gel(size, region, cfg.edge_mm, cfg.contact_edge_mm)
        if use_cache:
            cache.store(key, mesh)
    markers = embed_points(mesh.vertices_mm, mesh.tets, setup.sensor.markers_rest_gel_mm)
    quality = mesh_quality(mesh.vertices_mm, mesh.tets)
    return MeshedGel(mesh, markers, quality, region, key, hit, time.perf_counter() - t0)


def region_inputs(setup: SceneSetup) -> dict:
    """What decides the contact region, as configured: the refine margin and, per indenter, its mesh file's
    bytes (or the loaded mesh's arrays) and its placement and trajectory values. The mesh cache key hashes
    these instead of the region itself, whose last bits depend on the machine (the indenter's vertices are
    posed by a BLAS matrix product, which rounds differently on another CPU), so that a cache made on one
    machine is found on another. Appearance (colour, texture) and friction do not enter."""
    placement = {"units", "anchor", "start_xy_mm", "start_gap_mm", "rotation_deg", "trajectory"}
    out = []
    for ind in setup.indenters:
        source = Path(ind.mesh.source)
        if source.is_file():
            geometry = hashlib.sha256(source.read_bytes()).hexdigest()
        else:
            m = ind.mesh.mesh
            geometry = hashlib.sha256(m.vertices.tobytes() + m.faces.tobytes()).hexdigest()
        out.append({"geometry": geometry, **ind.config.model_dump(mode="json", include=placement)})
    return {"refine_margin_mm": setup.scene.mesh.refine_margin_mm, "indenters": out}
