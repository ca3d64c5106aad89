"""The assembled sensor: hardware model + materials + marker layout, with its cameras' calibration.

Frames (mm): the gel frame (origin at the centre of the bonded face, z away from the cameras, contact
surface at z = thickness) and the left camera's OpenCV frame, which differ by a translation only:
``x_left = x_gel + gel_origin_in_left_mm``. The right camera follows OpenCV's stereo convention,
``x_right = R @ x_left + T``.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import radians, tan
from pathlib import Path

import numpy as np

from transtac_sim.camera.model import image_border, invertible_rays
from transtac_sim.config import ConfigError, HardwareModel, load_hardware, load_material
from transtac_sim.config.hardware import Camera, MarkerLayout
from transtac_sim.config.materials import Dielectric, Diffuse, Elastomer, FluorescentPigment
from transtac_sim.rendering.inputs import CameraSpec
from transtac_sim.sensor.layouts import marker_centres


@dataclass(frozen=True)
class CameraCalibration:
    """One camera as OpenCV's calibration returns it: ``K`` (px), ``dist``, and ``R``, ``T`` (mm) from
    the left camera's frame to this camera's frame."""

    name: str
    model: str
    image_size: tuple[int, int]  # (width, height) px
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    T: np.ndarray


def camera_calibration(name: str, cam: Camera, R: np.ndarray, T: np.ndarray) -> CameraCalibration:
    """Intrinsics from the ideal field of view; the pixel centre convention is OpenCV's ((0, 0) is the
    centre of the top-left pixel), so the image centre is ((w - 1) / 2, (h - 1) / 2)."""
    w, h = cam.image_size
    f = (w / 2) / tan(radians(cam.hfov_deg) / 2)
    cx = (w - 1) / 2 + cam.principal_point_offset_px[0]
    cy = (h - 1) / 2 + cam.principal_point_offset_px[1]
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    return CameraCalibration(name, cam.model, (w, h), K, np.asarray(cam.distortion, float), R, T)


@dataclass(frozen=True)
class Sensor:
    hardware: HardwareModel
    gel: Elastomer
    backing: Dielectric
    housing: Diffuse
    pigment: FluorescentPigment
    marker_radius_mm: float
    markers_rest_gel_mm: np.ndarray  # (K, 3) marker centres in the gel frame
    gel_origin_in_left_mm: np.ndarray  # (3,)
    cameras: dict[str, CameraCalibration]

    @property
    def gel_size_mm(self) -> tuple[float, float, float]:
        w, h = self.hardware.gel.size_mm
        return (w, h, self.hardware.gel.thickness_mm)

    def gel_to_left(self, points_gel_mm: np.ndarray) -> np.ndarray:
        """Gel frame -> left camera frame (mm)."""
        return np.asarray(points_gel_mm) + self.gel_origin_in_left_mm

    def calibration_json(self) -> dict:
        """``calibration.json`` of the dataset contract (DESIGN.md section 4)."""
        left, right = self.cameras["left"], self.cameras["right"]
        return {
            "image_size": list(left.image_size),
            "model": left.model,
            "K_left": left.K.tolist(), "dist_left": left.dist.tolist(),
            "K_right": right.K.tolist(), "dist_right": right.dist.tolist(),
            "R": right.R.tolist(), "T": right.T.tolist(),
            "units": "mm",
        }

    def flat_stack_json(self) -> dict:
        """The flat layers in front of the cameras (backing, gel) as the perception package's refraction-aware
        triangulation reads them (``perception/stereo/triangulation.py``), left camera frame, mm."""
        h = self.hardware.backing.thickness_mm
        return {"point_mm": [0.0, 0.0, float(self.gel_origin_in_left_mm[2]) - h], "normal": [0.0, 0.0, 1.0],
                "backing_thickness_mm": h, "n_backing": self.backing.refractive_index,
                "n_gel": self.gel.refractive_index, "gel_thickness_mm": float(self.gel_size_mm[2])}


def _material(name: str, kind: type, source: Path, key: str, relative_to: Path):
    try:
        m = load_material(name, relative_to)
    except FileNotFoundError as e:
        raise ConfigError(source, [(key, str(e))]) from None
    if not isinstance(m, kind):
        raise ConfigError(source, [(key, f"{name!r} is a {m.kind} material; this part needs kind = {kind.__name__.lower()}")])
    return m


def build_sensor(hardware: str | Path = "transtac", marker_layout: MarkerLayout | None = None,
                 *, layout_source: str | Path | None = None, relative_to: Path | None = None,
                 marker_seed: int | None = None) -> Sensor:
    """Assemble a sensor from a hardware model (name or path), optionally with another marker layout
    and another seed for it."""
    hw, path = load_hardware(hardware, relative_to)
    here = path.parent
    layout = marker_layout or hw.markers.arrangement
    if marker_seed is not None and hasattr(layout, "seed"):
        layout = layout.model_copy(update={"seed": marker_seed})
    src = layout_source or path
    markers = marker_centres(layout, hw.gel.size_mm, hw.gel.thickness_mm, source=src,
                             relative_to=Path(src).parent if marker_layout else here)
    rig = hw.cameras
    R = np.eye(3)
    cameras = {
        "left": camera_calibration("left", rig.left, R, np.zeros(3)),
        "right": camera_calibration("right", rig.right, R, np.array([-rig.baseline_mm, 0.0, 0.0])),
    }
    for name, cam in cameras.items():
        try:
            invertible_rays(CameraSpec(cam.K, cam.dist, cam.image_size, model=cam.model), image_border(cam.image_size))
        except ValueError as e:
            raise ConfigError(path, [(f"cameras.{name}.distortion", str(e))]) from None
    origin = np.array([rig.baseline_mm / 2, 0.0, rig.distance_to_backing_mm + hw.backing.thickness_mm])
    return Sensor(
        hardware=hw,
        gel=_material(hw.gel.material, Elastomer, path, "gel.material", here),
        backing=_material(hw.backing.material, Dielectric, path, "backing.material", here),
        housing=_material(hw.housing.material, Diffuse, path, "housing.material", here),
        pigment=_material(hw.markers.pigment, FluorescentPigment, path, "markers.pigment", here),
        marker_radius_mm=layout.radius_mm,
        markers_rest_gel_mm=markers,
        gel_origin_in_left_mm=origin,
        cameras=cameras,
    )
