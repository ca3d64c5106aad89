"""Domain randomisation for training sets, declared in a scene's ``[randomize]`` table.

Each sequence of a dataset is the base scene with these values redrawn from
``numpy.random.default_rng([scene.seed, sequence_index])``; ranges are ``[low, high]`` (uniform).
A key left out keeps the base scene's value. Units: mm, degrees, MPa; scales are factors.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, Field, model_validator

from transtac_sim.config.fields import STRICT

Range = Annotated[tuple[float, float], Field(description="[low, high], uniform")]


class Randomize(BaseModel):
    model_config = STRICT
    indenter_meshes: list[str] = Field(default_factory=list, description="choose each indenter's mesh from these (mm)")
    start_xy_mm: tuple[Range, Range] | None = None
    start_gap_mm: Range | None = Field(default=None, description="height of the lowest point above the surface")
    rotation_z_deg: Range | None = None
    press_depth_mm: Range | None = None
    slide_direction_deg: Range | None = None
    slide_distance_mm: Range | None = None
    friction: Range | None = None
    marker_layout_seed: bool = Field(default=False, description="draw a new layout seed per sequence")
    youngs_modulus_mpa: Range | None = None
    light_scale: Range | None = None
    exposure_scale: Range | None = None

    @model_validator(mode="after")
    def _valid_ranges(self) -> Randomize:
        positive = {"youngs_modulus_mpa", "light_scale", "exposure_scale", "press_depth_mm", "slide_distance_mm"}
        ranges = [(name, getattr(self, name)) for name in type(self).model_fields if name != "start_xy_mm"]
        ranges += [("start_xy_mm", r) for r in (self.start_xy_mm or ())]
        for name, r in ranges:
            if not (isinstance(r, tuple) and len(r) == 2):
                continue
            if r[0] > r[1]:
                raise ValueError(f"{name}: low {r[0]} > high {r[1]}")
            if name in positive and r[0] <= 0 or name == "friction" and r[0] < 0:
                raise ValueError(f"{name}: low {r[0]} is out of range (must be {'>=' if name == 'friction' else '>'} 0)")
        return self
