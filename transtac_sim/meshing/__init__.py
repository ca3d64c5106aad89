"""Meshing stage: the gel's tet mesh (cached) and the markers embedded in it."""

from __future__ import annotations

import time
from dataclasses import dataclass

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
    key = cache.mesh_key(size_mm=list(size), region=list(region) if region else None,
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
