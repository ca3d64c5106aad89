"""What to simulate (files in ``scenes/*.toml``): the sensor, the indenters and their trajectories,
the meshing resolution, and the outputs asked for. Units: mm, degrees in files; poses in the gel frame
(see ``transtac_sim.config.hardware``)."""

from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from transtac_sim.config.fields import STRICT
from transtac_sim.config.hardware import MarkerLayout
from transtac_sim.config.randomize import Randomize
from transtac_sim.config.trajectory import Press, Segment


class _Strict(BaseModel):
    model_config = STRICT

class SensorRef(_Strict):
    hardware: str = "transtac"
    markers: MarkerLayout | None = Field(default=None, description="replaces the hardware model's layout")

class Mesh(_Strict):
    """Target tet edge lengths: ``edge_mm`` away from contact, ``contact_edge_mm`` in the contact region
    (the indenters' footprints over their trajectories, grown by ``refine_margin_mm``)."""

    edge_mm: float = Field(default=1.5, gt=0.05, le=50.0)
    contact_edge_mm: float = Field(default=0.6, gt=0.05, le=50.0)
    refine_margin_mm: float = Field(default=2.0, ge=0.0, le=100.0)

    @model_validator(mode="after")
    def _contact_finer(self) -> Mesh:
        if self.contact_edge_mm > self.edge_mm:
            raise ValueError(f"contact_edge_mm ({self.contact_edge_mm}) must be <= edge_mm ({self.edge_mm})")
        return self

class Indenter(_Strict):
    """A rigid indenter. ``mesh`` is an STL/OBJ/PLY path relative to the scene file, in ``units``.
    Its start: turned by ``rotation_deg`` (x, then y, then z, about the mesh origin), its ``anchor`` at
    ``start_xy_mm`` and its lowest point ``start_gap_mm`` above the contact surface. ``anchor``:
    ``"footprint"`` (default) is the centre of the part a press touches (the xy centre of the body within
    0.5 mm of its lowest point, transtac_sim/indenters/placement.py), ``"origin"`` the mesh file's origin.
    Poses (``pose_mm``) map the mesh file's frame either way, and ``rotate`` / ``roll`` segments turn about
    its origin. ``texture = "speckle"`` modulates its white-light colour by a 3D noise of feature size
    ``texture_scale_mm`` fixed to the body (per mesh vertex: use a finely tessellated mesh); an indenter
    whose trajectory only holds above the surface never touches the gel, so its scene needs no FEM."""

    name: str = Field(min_length=1)
    mesh: str
    units: Literal["mm", "m", "inch"]
    anchor: Literal["footprint", "origin"] = Field(
        default="footprint", description="the point placed at start_xy_mm: the footprint's centre or the mesh origin")
    start_xy_mm: tuple[float, float] = (0.0, 0.0)
    start_gap_mm: float = Field(default=0.5, ge=-100.0, le=100.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    friction: float = Field(default=0.5, ge=0.0, le=5.0)
    color_rgb: tuple[float, float, float] = (0.75, 0.75, 0.75)
    texture: Literal["none", "speckle"] = Field(
        default="none", description="speckle: a random pattern fixed to the body (features for dense stereo)")
    texture_scale_mm: float = Field(default=1.0, gt=0.05, le=50.0, description="the speckle's feature size")
    trajectory: list[Segment] = Field(min_length=1)

class Outputs(_Strict):
    cameras: list[Literal["left", "right"]] = Field(default=["left", "right"], min_length=1)
    illuminations: list[Literal["uv", "white"]] = Field(default=["uv", "white"])
    aovs: list[Literal["depth"]] = Field(default_factory=list)
    labels: bool = True
    frame_rate_hz: float = Field(default=30.0, gt=0.0, le=10_000.0, description="time_s of frame i is i / rate")

class Physics(_Strict):
    """FEM settings (see transtac_sim.physics): element order, Newton tolerance, device, linear solver."""

    degree: Literal[1, 2] = Field(default=2, description="1: linear tets (fast, stiffer); 2: quadratic (accurate)")
    newton_tol_mm: float = Field(default=1e-4, gt=0.0, le=1.0)
    newton_force_rtol: float = Field(
        default=3e-3, ge=0.0, le=0.1, description="Newton also converges where the force left unbalanced (N, the norm "
        "over the free nodes) is at most this fraction of the normal load on the gel's support, once friction's lag is "
        "settled, whatever its step's length (SolverSettings.newton_force_rtol); 0: the step-length test alone. 3e-3 "
        "on press_slide (H100s): 0.68-0.90x the physics seconds, markers 0.002 mm further from a finer mesh's "
        "(0.05 mm away with either); 1e-2 raised their RMS error by a quarter (BENCHMARKS.md fem_force_test_default)")
    newton_no_progress_steps: int = Field(
        default=30, ge=0, le=1000, description="a load step that can still be halved is given up and solved in halves "
        "once Newton has taken this many steps since the lowest force imbalance of the step (SolverSettings."
        "newton_no_progress_steps): next to elements flattened towards det F = 0 Newton can creep along the inversion "
        "barrier up to its iteration cap; 0: never. Each frame's labels.json lists its failed steps and why "
        "(solver.failed_steps; BENCHMARKS.md fem_no_progress_gpu)")
    device: Literal["auto", "cpu", "cuda"] = "auto"
    friction_slip_mm: float = Field(
        default=0.05, gt=0.0, le=1.0, description="friction smoothing: a sticking point moves up to this far against "
        "the indenter (an elastic stretch, kept from frame to frame) before friction reaches mu times the pressure "
        "(0.01: stricter sticking, about 1.5x the Newton iterations; 0.2: on train_random 0.9x the Newton iterations, "
        "its markers moved by up to 0.33 mm and its forces by up to 47 %; BENCHMARKS.md "
        "fem_friction_smoothing_train_random_gpu)")
    friction_lag_moves: int = Field(
        default=4, ge=1, le=50, description="friction's normal pressure and tangent plane are lagged and moved to "
        "the current state at most this often per load step: on press_slide 4 match a converged lag's friction forces "
        "within 0.05 %, 1 takes 0.7-0.75x the Newton iterations with friction within 2 %. A lag cut short can land "
        "anywhere on its path (the tiny mesh's last slide frame: 35 % off with 4, 81 % with 8, 4 % with 1; converged "
        "with 16), and where it does not converge more moves can make a frame fail (BENCHMARKS.md "
        "fem_friction_lag_moves, fem_friction_lag_cap_gpu). The frame's solver record says what the lag leaves "
        "unbalanced (friction_lag_residual_n, N)")
    linear_solver: Literal["auto", "direct", "cg"] = Field(
        default="auto", description="direct: sparse Cholesky/LU on the host; cg: Warp's CG on the device; "
        "auto: cg on a GPU, else direct")
    coarse_cell_mm: float = Field(
        default=3.0, ge=0.0, le=100.0, description="the device CG's two-level preconditioner: the rigid-body modes "
        "of aggregates of nodes are solved for directly, as many aggregates as the gel has cells of about this size "
        "(at most sqrt(nodes)), each holding the same number of nodes (transtac_sim/physics/coarse_space.py); "
        "0: block-Jacobi alone")


class Render(_Strict):
    """Render and camera-model settings. Exposures map linear radiance (mW/(mm^2 sr)) to full scale."""

    spp: int = Field(default=16, ge=1, le=65536)
    max_depth: int = Field(default=10, ge=2, le=64)
    variant: str | None = Field(default=None, description="Mitsuba variant; default cuda_ad_rgb if a GPU, else llvm_ad_rgb")
    exposure_uv: float = Field(default=60.0, gt=0.0, le=1e6)
    exposure_white: float = Field(default=12.0, gt=0.0, le=1e6)
    ambient_white: float = Field(default=0.02, ge=0.0, le=100.0)
    distortion: bool = True
    vignetting: float = Field(default=1.0, ge=0.0, le=1.0)
    noise: bool = True
    quantize: bool = True


class Scene(_Strict):
    name: str = Field(min_length=1, description="also the default output folder's name (out/<name>/...)")
    seed: int = Field(default=0, ge=0)
    sequences: int = Field(default=1, ge=1, le=1_000_000, description="sequences in a generated dataset")
    sensor: SensorRef = SensorRef()
    mesh: Mesh = Mesh()
    indenters: list[Indenter] = Field(default_factory=list)
    outputs: Outputs = Outputs()
    physics: Physics = Physics()
    render: Render = Render()
    randomize: Randomize | None = None

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, name: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
            raise ValueError("the scene's name names its default output folders: letters, digits, '.', '_' and '-', "
                             "starting with a letter or digit")
        return name

    @model_validator(mode="after")
    def _unique_names(self) -> Scene:
        names = [i.name for i in self.indenters]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"indenter names must be unique; repeated: {sorted(dup)}")
        return self

    @property
    def frame_count(self) -> int:
        """Frames in the sequence: the longest indenter trajectory (1 for a contact-free scene)."""
        return max((sum(s.frames for s in i.trajectory) for i in self.indenters), default=1)

    def depth_problems(self, gel_thickness_mm: float) -> list[tuple[str, str]]:
        """``(key, what is wrong)`` for each press depth, or randomised range of them, that reaches the backing
        through a gel this thick (the gel is known once the scene is assembled: transtac_sim.scene_setup)."""
        t = gel_thickness_mm

        def through(depth: float) -> str:
            return f"{depth} mm reaches through the {t} mm gel (allowed: < {t})"

        problems = [(f"indenters[{i}].trajectory[{k}].depth_mm", through(s.depth_mm))
                    for i, ind in enumerate(self.indenters) for k, s in enumerate(ind.trajectory)
                    if isinstance(s, Press) and s.depth_mm is not None and s.depth_mm >= t]
        r = self.randomize
        if r is not None and r.press_depth_mm is not None and r.press_depth_mm[1] >= t:
            problems.append(("randomize.press_depth_mm", f"high {through(r.press_depth_mm[1])}"))
        return problems
