"""Plain inputs of the renderer and the labeller: numpy arrays, millimetres, all positions in the LEFT
camera's OpenCV frame (x right, y down, z forward from the left camera's centre).

The sensor is static (``SensorScene``: built once per sequence); what moves per frame is ``FrameState``
(the gel's surface vertices, the marker centres and shapes, the indenters' vertices; topology fixed).
Radiances are in arbitrary linear units (the camera model's exposure maps them to pixel values).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CameraSpec:
    """One camera: OpenCV intrinsics and distortion, image size, and extrinsics x_cam = R x_left + T (mm).

    ``model`` is ``"pinhole"`` (``dist`` = k1, k2, p1, p2, k3) or ``"fisheye"`` (``dist`` = k1..k4)."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]  # (width, height) px
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    model: str = "pinhole"

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in the left frame (mm)."""
        return -np.asarray(self.R).T @ np.asarray(self.T, float)


@dataclass
class GelSpec:
    """Closed triangle surface of the gel volume (outward normals). Its bonded face is the planar part at
    the smallest z (on the backing, never moves); the rest (sides, contact face) may deform."""

    vertices: np.ndarray  # (V, 3) rest (or first-frame) positions
    faces: np.ndarray  # (F, 3)
    ior: float = 1.41
    absorption_rgb_per_mm: tuple[float, float, float] = (0.002, 0.002, 0.003)
    absorption_uv_per_mm: float = 0.02

    @property
    def bonded_z(self) -> float:
        return float(np.asarray(self.vertices)[:, 2].min())


@dataclass
class BackingSpec:
    """Clear rigid backing as an axis-aligned box [lo, hi] (mm); its face z = hi[2] carries the gel."""

    lo: np.ndarray
    hi: np.ndarray
    ior: float = 1.49
    absorption_uv_per_mm: float = 0.05


@dataclass
class Pigment:
    """Fluorescent marker pigment. White light: a pale, semi-transparent diffuse body (``white_opacity``
    in [0, 1]). UV: absorbs ``uv_absorptance`` of the 365 nm light reaching it and re-emits
    ``quantum_yield`` of it with the linear RGB colour ``emission_rgb`` (luminance-normalised)."""

    white_rgb: tuple[float, float, float] = (0.8, 0.85, 0.7)
    white_opacity: float = 0.25
    uv_absorptance: float = 0.6
    quantum_yield: float = 0.8
    emission_rgb: tuple[float, float, float] = (0.35, 1.0, 0.25)


@dataclass
class MarkerSpec:
    """Markers: spheres of ``radius`` mm at ``centres`` (K, 3), optionally deformed into ellipsoids by
    per-marker deformation gradients ``deformation`` (K, 3, 3): surface point = c + F (r n)."""

    centres: np.ndarray
    radius: float
    pigment: Pigment = field(default_factory=Pigment)
    deformation: np.ndarray | None = None


@dataclass
class IndenterSpec:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3), outward normals
    rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    albedo: np.ndarray | None = None  # (V, 3) per-vertex colour under white light (a texture); None: rgb


@dataclass
class LightSpec:
    """Rectangular LED strip (one-sided Lambertian area light). ``kind`` is ``"uv"`` or ``"white"``;
    ``radiance`` is in the light's band (365 nm for UV, grey visible for white); ``size`` = (along
    ``u_axis``, across) mm."""

    kind: str
    centre: np.ndarray
    normal: np.ndarray
    size: tuple[float, float]
    radiance: float
    u_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))


@dataclass
class HousingSpec:
    """Matte black diffuse meshes around the cameras (list of (vertices, faces))."""

    meshes: list[tuple[np.ndarray, np.ndarray]]
    reflectance: float = 0.03


@dataclass
class SensorScene:
    cameras: dict[str, CameraSpec]
    gel: GelSpec
    backing: BackingSpec
    housing: HousingSpec
    markers: MarkerSpec
    lights: list[LightSpec]
    indenters: list[IndenterSpec] = field(default_factory=list)
    uv_visible_leak: float = 1e-3  # visible radiance of a UV strip per unit of its UV radiance
    ambient_white: float = 0.0  # radiance of the room around the sensor under white light


@dataclass
class FrameState:
    """What changes per frame; None keeps the scene's current value."""

    gel_vertices: np.ndarray | None = None  # (V, 3), same topology as GelSpec.faces
    marker_centres: np.ndarray | None = None  # (K, 3)
    marker_deformation: np.ndarray | None = None  # (K, 3, 3)
    indenter_vertices: list[np.ndarray] | None = None  # one (V_i, 3) per indenter


ILLUMINATIONS = ("uv", "white")
AOVS = ("depth",)


@dataclass
class RenderRequest:
    cameras: tuple[str, ...] = ("left", "right")
    illuminations: tuple[str, ...] = ILLUMINATIONS
    aovs: tuple[str, ...] = ()

    def __post_init__(self):
        bad = set(self.illuminations) - set(ILLUMINATIONS) | set(self.aovs) - set(AOVS)
        if bad:
            raise ValueError(f"unknown illuminations/AOVs {sorted(bad)}")


@dataclass
class RenderSettings:
    spp: int = 16
    max_depth: int = 8  # longest path (1: emitters seen directly; 3: a marker seen through backing and bond)
    rr_depth: int = 2  # Russian roulette from this depth (kills paths dimmed by the black housing early)
    sampler: str = "multijitter"  # stratified pixel samples: ~1.5x less image and centroid noise than
    # "independent" at the same cost; it may round spp up a little (32 -> 35): ``Renderer.spp`` says
    variant: str | None = None  # None: cuda_ad_rgb when there is a GPU, else llvm_ad_rgb
