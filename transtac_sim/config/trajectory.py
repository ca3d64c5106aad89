"""Indenter trajectories as declared in scene files.

A trajectory is a list of segments run one after the other; each segment lasts ``frames`` quasi-static
frames and moves the indenter rigidly, in the gel frame (mm, degrees in files):

- ``press``:   move along -z until the indenter's lowest point is ``depth_mm`` below the undeformed
               contact surface (z = thickness), or until the normal force on the gel reaches ``force_n``.
- ``hold``:    stay where it is.
- ``slide``:   translate ``distance_mm`` in the xy plane along ``direction_deg`` (0 = +x, 90 = +y).
- ``rotate``:  turn ``angle_deg`` about ``axis`` through the indenter's reference point (its mesh
               origin) -- a twist when the axis is z.
- ``roll``:    roll without slipping ``distance_mm`` along ``direction_deg``: translate and turn about
               the horizontal axis perpendicular to the travel, by distance / rolling radius, where the
               rolling radius is the height of the reference point above the lowest point at the start.
- ``release``: move back along +z to where the indenter was at the start of its first press.

Motion within a segment is linear in time; the pose at the end of a segment is the start of the next.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, Field, model_validator

from transtac_sim.config.fields import STRICT, Direction


class _Segment(BaseModel):
    model_config = STRICT
    frames: int = Field(ge=1, le=10_000, description="quasi-static frames in this segment")


class Press(_Segment):
    kind: Literal["press"]
    depth_mm: float | None = Field(default=None, gt=0.0, le=50.0)
    force_n: float | None = Field(default=None, gt=0.0, le=1000.0)

    @model_validator(mode="after")
    def _one_target(self) -> Press:
        if (self.depth_mm is None) == (self.force_n is None):
            raise ValueError("a press needs exactly one of depth_mm or force_n")
        return self


class Hold(_Segment):
    kind: Literal["hold"]


class Slide(_Segment):
    kind: Literal["slide"]
    direction_deg: float = Field(ge=-360.0, le=360.0)
    distance_mm: float = Field(gt=0.0, le=100.0)


class Rotate(_Segment):
    kind: Literal["rotate"]
    axis: Direction = (0.0, 0.0, 1.0)
    angle_deg: float = Field(ge=-360.0, le=360.0)


class Roll(_Segment):
    kind: Literal["roll"]
    direction_deg: float = Field(ge=-360.0, le=360.0)
    distance_mm: float = Field(gt=0.0, le=100.0)


class Release(_Segment):
    kind: Literal["release"]


Segment = Annotated[Union[Press, Hold, Slide, Rotate, Roll, Release], Field(discriminator="kind")]
