"""The hardware model of a sensor (files in ``hardware_models/*.toml``).

Frames: the *gel frame* has its origin at the centre of the gel's bonded face, x right, y down, z away from
the cameras (parallel to the left camera's OpenCV axes); the gel fills [-w/2, w/2] x [-h/2, h/2] x [0, t]
and z = t is the contact surface. The left camera sits at ``-gel_origin_in_left_camera_mm`` in that frame.
Units: mm, degrees in files.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, Field, model_validator

from transtac_sim.config.fields import STRICT, Direction


class _Strict(BaseModel):
    model_config = STRICT


class Gel(_Strict):
    material: str = "solaris"
    size_mm: tuple[Annotated[float, Field(gt=1.0, le=500.0)], Annotated[float, Field(gt=1.0, le=500.0)]]
    thickness_mm: float = Field(gt=0.2, le=100.0)


class Backing(_Strict):
    material: str = "acrylic"
    thickness_mm: float = Field(gt=0.1, le=50.0)


class Housing(_Strict):
    material: str = "pla_matte_black"
    wall_mm: float = Field(default=2.0, gt=0.0, le=20.0)


class Camera(_Strict):
    """One camera's intrinsics. ``distortion`` follows OpenCV: (k1, k2, p1, p2, k3) for ``pinhole``,
    (k1, k2, k3, k4) for ``fisheye``. The focal length follows from ``hfov_deg`` of the ideal model."""

    model: Literal["pinhole", "fisheye"] = "pinhole"
    image_size: tuple[Annotated[int, Field(ge=16, le=8192)], Annotated[int, Field(ge=16, le=8192)]]
    hfov_deg: float = Field(gt=1.0, lt=179.0)
    principal_point_offset_px: tuple[float, float] = (0.0, 0.0)
    distortion: list[float] = Field(default_factory=lambda: [0.0] * 5)

    @model_validator(mode="after")
    def _distortion_length(self) -> Camera:
        want = 5 if self.model == "pinhole" else 4
        if len(self.distortion) != want:
            raise ValueError(f"distortion of a {self.model} camera has {want} coefficients, got {len(self.distortion)}")
        return self


class StereoRig(_Strict):
    """Two cameras behind the backing, looking along +z. ``baseline_mm`` along +x (right camera to the
    right of the left one); ``distance_to_backing_mm`` from the camera centres to the backing's outer face."""

    baseline_mm: float = Field(gt=0.0, le=200.0)
    distance_to_backing_mm: float = Field(gt=0.5, le=500.0)
    left: Camera
    right: Camera


class Light(_Strict):
    """A rectangular LED strip (area light), in the gel frame. ``kind`` = ``uv`` (365 nm) or ``white``."""

    name: str
    kind: Literal["uv", "white"]
    center_mm: tuple[float, float, float]
    size_mm: tuple[Annotated[float, Field(gt=0.0)], Annotated[float, Field(gt=0.0)]]
    normal: Direction
    radiant_power_mw: float = Field(gt=0.0, le=10_000.0)
    visible_leak: float = Field(default=0.0, ge=0.0, le=1.0, description="visible fraction a UV LED also emits")


class _Layout(_Strict):
    radius_mm: float = Field(gt=0.005, le=5.0, description="marker radius")
    depth_mm: float = Field(gt=0.0, le=100.0, description="depth of marker centres below the contact surface")
    depth_jitter_mm: float = Field(default=0.0, ge=0.0, le=10.0, description="uniform +- jitter of depth")
    margin_mm: float = Field(default=1.0, ge=0.0, le=100.0, description="keep-out band along the gel's edges")
    seed: int = Field(default=0, ge=0)


class PoissonDiskLayout(_Layout):
    """Irregular layout of the real sensor: random, no two centres closer than ``min_spacing_mm``."""

    layout: Literal["poisson_disk"]
    count: int | None = Field(default=None, ge=1, le=100_000)
    density_per_mm2: float | None = Field(default=None, gt=0.0, le=100.0)
    min_spacing_mm: float = Field(gt=0.0, le=100.0)

    @model_validator(mode="after")
    def _count_or_density(self) -> PoissonDiskLayout:
        if (self.count is None) == (self.density_per_mm2 is None):
            raise ValueError("give exactly one of count or density_per_mm2")
        return self


class GridLayout(_Layout):
    layout: Literal["grid"]
    pitch_mm: float = Field(gt=0.0, le=100.0)
    jitter_mm: float = Field(default=0.0, ge=0.0, le=10.0, description="uniform +- in-plane jitter")


class HexagonalLayout(_Layout):
    layout: Literal["hexagonal"]
    pitch_mm: float = Field(gt=0.0, le=100.0)
    jitter_mm: float = Field(default=0.0, ge=0.0, le=10.0, description="uniform +- in-plane jitter")


class FileLayout(_Strict):
    """Positions from a CSV (``x_mm,y_mm,depth_mm`` header) or JSON (list of [x, y, depth]) file,
    in the gel frame's x, y and depth below the contact surface; relative paths are from the TOML file."""

    layout: Literal["file"]
    path: str
    radius_mm: float = Field(gt=0.005, le=5.0)


MarkerLayout = Annotated[
    Union[PoissonDiskLayout, GridLayout, HexagonalLayout, FileLayout], Field(discriminator="layout")
]


class Markers(_Strict):
    pigment: str = "uv_pigment"
    arrangement: MarkerLayout


class HardwareModel(_Strict):
    name: str
    gel: Gel
    backing: Backing
    housing: Housing = Housing()
    cameras: StereoRig
    markers: Markers
    lights: list[Light] = Field(min_length=1)

    @model_validator(mode="after")
    def _markers_fit(self) -> HardwareModel:
        a = self.markers.arrangement
        if isinstance(a, FileLayout):
            return self  # checked against the gel once the file is read
        t = self.gel.thickness_mm
        lo, hi = a.depth_mm - a.depth_jitter_mm, a.depth_mm + a.depth_jitter_mm
        if lo - a.radius_mm < 0.0 or hi + a.radius_mm > t:
            raise ValueError(
                f"markers.arrangement: markers of radius {a.radius_mm} mm at depth {lo:g}..{hi:g} mm do not fit "
                f"inside the {t} mm gel (allowed: radius <= depth <= {t} - radius)"
            )
        if 2 * a.margin_mm >= min(self.gel.size_mm):
            raise ValueError(f"markers.arrangement.margin_mm = {a.margin_mm} leaves no room on a {self.gel.size_mm} mm gel")
        return self
