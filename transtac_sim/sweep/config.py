"""Sweep files (``scenes/sweeps/*.toml``): which parameters to vary, how to search them, and the benchmark
every point is scored on. Bad input is a ConfigError with one line naming the file and the key.

    name = "marker_density"
    seed = 0                        # render and sensor-noise seed of the benchmark frames

    [search]
    kind = "grid"                   # grid: every combination | random: `samples` draws
    # samples = 12                  # random only
    # seed = 0                      # random only

    [parameters]                    # a value (fixed), a list (grid: each; random: one at random) or, for a
    pattern = "irregular"           # number in a random search, {low = .., high = ..} (uniform; integer
    count = [40, 80, 120]           # for count and seed)
    depth_mm = [0.5, 1.5]

    [benchmark]
    frames = 3                      # frames per motion (the press of a slide or roll included)
    press_depth_mm = 0.8
    motions = [{ kind = "press", indenter = "sphere_r4" }, { kind = "press", indenter = "cone_r4_h6" },
               { kind = "slide", indenter = "flat_punch_r3", distance_mm = 1.5 },
               { kind = "roll", indenter = "cylinder_r3_l16", distance_mm = 2.0 }]

    [scene]                         # the benchmark scenes' hardware model and [mesh], [physics], [render]
    hardware = "transtac"           # tables, as in a scene file

Parameters (PARAMETERS below): the marker layout (``pattern`` irregular | poisson_disk | grid | hexagonal,
``count`` or ``density_per_mm2``, ``radius_mm``, ``depth_mm``, ``depth_jitter_mm``, ``min_spacing_mm``,
``margin_mm``, ``jitter_mm``, ``seed``), the gel (``thickness_mm``, ``youngs_modulus_mpa``), the camera
rig (``baseline_mm``) and the pipeline (``detector`` learned | blob, ``matcher`` delaunay | hungarian |
epipolar_nn). A lattice (grid, hexagonal) takes the pitch whose lattice has the count closest to
``count`` (the table records the real count) and must not be closer than ``min_spacing_mm``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from transtac_sim.config import ConfigError, load_hardware
from transtac_sim.config.errors import from_validation_error
from transtac_sim.config.hardware import GridLayout, HexagonalLayout, PoissonDiskLayout
from transtac_sim.config.loader import REPO_ROOT, read_toml
from transtac_sim.config.scene import Mesh, Physics, Render

LAYOUT_KEYS = ("pattern", "count", "density_per_mm2", "radius_mm", "depth_mm", "depth_jitter_mm",
               "min_spacing_mm", "margin_mm", "jitter_mm", "seed")
MECHANICAL_KEYS = ("thickness_mm", "youngs_modulus_mpa")
CAMERA_KEYS = ("baseline_mm",)
PIPELINE_KEYS = ("detector", "matcher")
PARAMETERS = LAYOUT_KEYS + MECHANICAL_KEYS + CAMERA_KEYS + PIPELINE_KEYS
PATTERNS = {"irregular": "poisson_disk", "poisson_disk": "poisson_disk", "grid": "grid", "hexagonal": "hexagonal"}
CHOICES = {"pattern": tuple(PATTERNS), "detector": ("learned", "blob"), "matcher": ("delaunay", "hungarian", "epipolar_nn")}
INTEGER = ("count", "seed")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Search(_Strict):
    kind: Literal["grid", "random"] = "grid"
    samples: int | None = Field(default=None, ge=1, le=100_000)
    seed: int = Field(default=0, ge=0)


class Motion(_Strict):
    """One benchmark sequence: ``indenter`` is a name in scenes/indenters/ or a mesh path (mm) relative
    to the sweep file."""

    kind: Literal["press", "slide", "roll"]
    indenter: str
    distance_mm: float = Field(default=1.5, gt=0.0, le=20.0, description="slide or roll distance")
    direction_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    start_xy_mm: tuple[float, float] = (0.0, 0.0)
    friction: float = Field(default=0.6, ge=0.0, le=5.0)


class Benchmark(_Strict):
    frames: int = Field(default=3, ge=2, le=100, description="frames per motion")
    press_depth_mm: float = Field(default=0.8, gt=0.0, le=5.0)
    motions: list[Motion] = Field(min_length=1, default_factory=lambda: [
        Motion(kind="press", indenter="sphere_r4"), Motion(kind="press", indenter="cone_r4_h6"),
        Motion(kind="slide", indenter="flat_punch_r3"), Motion(kind="roll", indenter="cylinder_r3_l16")])


class SceneBase(_Strict):
    hardware: str = "transtac"
    mesh: Mesh = Mesh(edge_mm=3.0, contact_edge_mm=1.2, refine_margin_mm=1.5)
    physics: Physics = Physics(degree=1)
    render: Render = Render()


class SweepFile(_Strict):
    name: str = Field(min_length=1)
    seed: int = Field(default=0, ge=0)
    search: Search = Search()
    parameters: dict[str, Any] = Field(min_length=1)
    benchmark: Benchmark = Benchmark()
    scene: SceneBase = SceneBase()


@dataclass(frozen=True)
class Point:
    """One point of the sweep: its parameter values (every parameter, defaults filled in)."""

    index: int
    values: dict
    id: str = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "id", f"p{self.index:03d}_{key_of(self.values)[:8]}")


@dataclass(frozen=True)
class Sweep:
    path: Path
    file: SweepFile
    points: list[Point]
    swept: list[str]  # the parameters that take more than one value


def key_of(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:20]


def _err(path: Path, key: str, msg: str) -> ConfigError:
    return ConfigError(path, [(key, msg)])


def _defaults(hardware: str, path: Path) -> dict:
    hw, _ = load_hardware(hardware, path.parent)
    a = hw.markers.arrangement
    d = {"pattern": "irregular", "count": 110, "density_per_mm2": None, "radius_mm": 0.25, "depth_mm": 0.6,
         "depth_jitter_mm": 0.0, "min_spacing_mm": 1.8, "margin_mm": 1.0, "jitter_mm": 0.0, "seed": 7,
         "thickness_mm": hw.gel.thickness_mm, "youngs_modulus_mpa": None, "baseline_mm": hw.cameras.baseline_mm,
         "detector": "learned", "matcher": "delaunay"}
    for k in ("radius_mm", "depth_mm", "depth_jitter_mm", "margin_mm", "seed", "min_spacing_mm", "count"):
        if getattr(a, k, None) is not None:
            d[k] = getattr(a, k)
    return d


def _check_value(path: Path, name: str, v, *, random: bool):
    key = f"parameters.{name}"
    if isinstance(v, dict):
        if not random:
            raise _err(path, key, "a {low, high} range needs [search] kind = \"random\"; give a list of values for a grid")
        if set(v) != {"low", "high"} or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v.values()):
            raise _err(path, key, f"a range is {{low = .., high = ..}} of numbers (got {v!r})")
        if name in CHOICES:
            raise _err(path, key, f"takes one of {', '.join(CHOICES[name])}, not a range")
        if v["low"] > v["high"]:
            raise _err(path, key, f"empty range: low {v['low']} > high {v['high']}")
        return v
    values = v if isinstance(v, list) else [v]
    if not values:
        raise _err(path, key, "empty range: the list has no values")
    for x in values:
        if name in CHOICES:
            if x not in CHOICES[name]:
                raise _err(path, key, f"{x!r} is not one of {', '.join(CHOICES[name])}")
        elif isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise _err(path, key, f"{x!r} is not a (finite) number")
        elif name in INTEGER and int(x) != x:
            raise _err(path, key, f"{x!r} is not a whole number")
    return values


def _expand(path: Path, f: SweepFile) -> list[dict]:
    random = f.search.kind == "random"
    specs = {k: _check_value(path, k, v, random=random) for k, v in f.parameters.items()}
    if random:
        if f.search.samples is None:
            raise _err(path, "search.samples", "a random search needs samples = N")
        rng = np.random.default_rng(f.search.seed)
        combos = []
        for _ in range(f.search.samples):
            c = {}
            for k, s in specs.items():
                if isinstance(s, dict):
                    x = float(rng.uniform(s["low"], s["high"]))
                    c[k] = int(round(x)) if k in INTEGER else x
                else:
                    c[k] = s[int(rng.integers(len(s)))]
            combos.append(c)
        return combos
    names = list(specs)
    return [dict(zip(names, combo, strict=True)) for combo in itertools.product(*(specs[n] for n in names))]


def lattice_pitch(pattern: str, count: int, size_mm: tuple[float, float], margin_mm: float) -> float:
    """The pitch whose square or hexagonal lattice in the free area has the count closest to ``count``."""
    from transtac_sim.sensor.layouts import lattice_xy

    cls = GridLayout if pattern == "grid" else HexagonalLayout

    def n(p: float) -> int:
        return len(lattice_xy(cls(layout=pattern, pitch_mm=p, radius_mm=0.1, depth_mm=1.0, margin_mm=margin_mm),
                              size_mm, np.random.default_rng(0)))

    lo, hi = 0.02, float(max(size_mm))
    for _ in range(50):  # the count falls as the pitch grows
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if n(mid) > count else (lo, mid)
    return min((lo, hi), key=lambda p: (abs(n(p) - count), -p))


def layout_of(values: dict, size_mm: tuple[float, float]):
    """The hardware-model marker layout (PoissonDiskLayout, GridLayout or HexagonalLayout) of a point."""
    pattern = PATTERNS[values["pattern"]]
    common = {k: values[k] for k in ("radius_mm", "depth_mm", "depth_jitter_mm", "margin_mm", "seed")}
    if pattern == "poisson_disk":
        amount = {"density_per_mm2": values["density_per_mm2"]} if values.get("density_per_mm2") else {"count": values["count"]}
        return PoissonDiskLayout(layout="poisson_disk", min_spacing_mm=values["min_spacing_mm"], **amount, **common)
    count = values["count"]
    if values.get("density_per_mm2"):
        w, h = size_mm[0] - 2 * values["margin_mm"], size_mm[1] - 2 * values["margin_mm"]
        count = max(1, round(values["density_per_mm2"] * w * h))
    pitch = lattice_pitch(pattern, int(count), size_mm, values["margin_mm"])
    cls = GridLayout if pattern == "grid" else HexagonalLayout
    return cls(layout=pattern, pitch_mm=pitch, jitter_mm=values["jitter_mm"], **common)


def _check_point(path: Path, values: dict, gel_size: tuple[float, float], swept: list[str]) -> None:
    """Raise a ConfigError naming the parameter of a point whose layout is invalid or does not fit."""
    from transtac_sim.sensor.layouts import marker_centres

    label = ", ".join(f"{k} = {values[k]}" for k in swept) or "the point"

    def blame(*keys: str) -> str:
        return "parameters." + next((k for k in keys if k in swept), keys[0])

    try:
        layout = layout_of(values, gel_size)
    except ValidationError as e:
        problem = from_validation_error(path, e).problems[0]
        key = problem[0].split(".")[0] if problem[0] else "pattern"
        raise _err(path, f"parameters.{key}", f"{label}: {problem[1]}") from None
    if getattr(layout, "pitch_mm", None) is not None and layout.pitch_mm < values["min_spacing_mm"] - 1e-9:
        raise _err(path, blame("count", "density_per_mm2", "min_spacing_mm"),
                   f"{label}: a {values['pattern']} lattice of {values['count']} markers has a pitch of "
                   f"{layout.pitch_mm:.2f} mm, closer than min_spacing_mm = {values['min_spacing_mm']}: "
                   "lower the count or the spacing")
    t = values["thickness_mm"]
    lo, hi = values["depth_mm"] - values["depth_jitter_mm"], values["depth_mm"] + values["depth_jitter_mm"]
    if lo - values["radius_mm"] < 0 or hi + values["radius_mm"] > t:
        raise _err(path, blame("depth_mm", "radius_mm", "thickness_mm", "depth_jitter_mm"),
                   f"{label}: markers of radius {values['radius_mm']} mm at depth {lo:g}..{hi:g} mm do not fit in "
                   f"the {t} mm gel")
    try:
        marker_centres(layout, gel_size, t, source=path)
    except ConfigError as e:
        raise _err(path, blame("count", "density_per_mm2", "min_spacing_mm", "margin_mm"),
                   f"{label}: {e.problems[0][1]}") from None


def load_sweep(path: str | Path) -> Sweep:
    """Read and check a sweep file and expand it into its points (each point's layout checked)."""
    path = Path(path).resolve()
    raw = read_toml(path)
    try:
        f = SweepFile.model_validate(raw)
    except ValidationError as e:
        err = from_validation_error(path, e)
        raise ConfigError(path, err.problems[:1]) from None
    unknown = [k for k in f.parameters if k not in PARAMETERS]
    if unknown:
        raise _err(path, f"parameters.{unknown[0]}", f"unknown parameter (known: {', '.join(PARAMETERS)})")
    if "count" in f.parameters and "density_per_mm2" in f.parameters:
        raise _err(path, "parameters.density_per_mm2", "give count or density_per_mm2, not both")
    for i, m in enumerate(f.benchmark.motions):
        try:
            indenter_mesh(m.indenter, path)
        except FileNotFoundError as e:
            raise _err(path, f"benchmark.motions[{i}].indenter", str(e)) from None
    defaults = _defaults(f.scene.hardware, path)
    hw, _ = load_hardware(f.scene.hardware, path.parent)
    gel_size = tuple(hw.gel.size_mm)
    combos = _expand(path, f)
    swept = [k for k in f.parameters if len({json.dumps(c[k]) for c in combos}) > 1]
    points, seen = [], set()
    for c in combos:
        values = {**defaults, **c}
        if "density_per_mm2" in c:
            values["count"] = None
        _check_point(path, values, gel_size, swept)
        k = key_of(values)
        if k in seen:  # a random search may draw the same point twice
            continue
        seen.add(k)
        points.append(Point(len(points), values))
    return Sweep(path, f, points, swept)


def indenter_mesh(name: str, sweep_path: Path) -> Path:
    """A motion's indenter mesh: a bare name in scenes/indenters/, else a path from the sweep file."""
    p = Path(name)
    for c in ([REPO_ROOT / "scenes" / "indenters" / f"{name}.stl"] if not p.suffix else []) + \
            ([p] if p.is_absolute() else [sweep_path.parent / p]):
        if c.is_file():
            return c.resolve()
    raise FileNotFoundError(f"no indenter mesh {name!r} (a name in scenes/indenters/ or an STL path from the sweep file)")
