"""Per-sequence draws of a scene's ``[randomize]`` table (see ``transtac_sim.config.randomize``).

``sequence_variant(scene, i)`` returns the scene of sequence ``i`` and the render-side scales; every draw
comes from ``numpy.random.default_rng([scene.seed, i])``, so a sequence does not depend on how many
others there are or on the order they run in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from transtac_sim.config.scene import Scene
from transtac_sim.config.trajectory import Press, Slide


@dataclass(frozen=True)
class Variant:
    scene: Scene
    youngs_modulus_mpa: float | None = None  # None: the material file's value
    marker_seed: int | None = None  # None: the layout's own seed
    light_scale: float = 1.0
    exposure_scale: float = 1.0


def sequence_variant(scene: Scene, index: int) -> Variant:
    r = scene.randomize
    if r is None:
        return Variant(scene)
    rng = np.random.default_rng([scene.seed, index])

    def draw(rng_range):
        return None if rng_range is None else float(rng.uniform(*rng_range))

    indenters = []
    for ind in scene.indenters:
        upd: dict = {}
        if r.indenter_meshes:
            upd["mesh"] = r.indenter_meshes[int(rng.integers(len(r.indenter_meshes)))]
            upd["units"] = "mm"
        if r.start_xy_mm is not None:
            upd["start_xy_mm"] = (draw(r.start_xy_mm[0]), draw(r.start_xy_mm[1]))
        if r.rotation_z_deg is not None:
            upd["rotation_deg"] = (ind.rotation_deg[0], ind.rotation_deg[1], draw(r.rotation_z_deg))
        if r.friction is not None:
            upd["friction"] = draw(r.friction)
        segs = []
        for s in ind.trajectory:
            if isinstance(s, Press) and r.press_depth_mm is not None and s.depth_mm is not None:
                s = s.model_copy(update={"depth_mm": draw(r.press_depth_mm)})
            elif isinstance(s, Slide):
                su = {}
                if r.slide_direction_deg is not None:
                    su["direction_deg"] = draw(r.slide_direction_deg)
                if r.slide_distance_mm is not None:
                    su["distance_mm"] = draw(r.slide_distance_mm)
                s = s.model_copy(update=su)
            segs.append(s)
        upd["trajectory"] = segs
        if r.start_gap_mm is not None:
            upd["start_gap_mm"] = draw(r.start_gap_mm)
        indenters.append(ind.model_copy(update=upd))
    return Variant(
        scene=scene.model_copy(update={"indenters": indenters}),
        youngs_modulus_mpa=draw(r.youngs_modulus_mpa),
        marker_seed=int(rng.integers(2**31)) if r.marker_layout_seed else None,
        light_scale=draw(r.light_scale) or 1.0,
        exposure_scale=draw(r.exposure_scale) or 1.0,
    )
