"""Marker layouts: where the fluorescent markers sit in the gel.

Every generator returns marker centres (K, 3) in the gel frame (mm): x, y in the gel footprint and
z = thickness - depth. Layouts: ``poisson_disk`` (the irregular layout of the real sensor; scipy's
Poisson-disk sampler guarantees the minimum spacing), ``grid``, ``hexagonal``, and ``file`` (a CSV or
JSON of positions measured on a real sensor).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from scipy.stats import qmc

from transtac_sim.config.errors import ConfigError
from transtac_sim.config.hardware import (
    FileLayout,
    GridLayout,
    HexagonalLayout,
    MarkerLayout,
    PoissonDiskLayout,
)


def _free_area(size_mm: tuple[float, float], margin_mm: float) -> tuple[float, float]:
    return size_mm[0] - 2 * margin_mm, size_mm[1] - 2 * margin_mm


def _depths(layout, n: int, rng: np.random.Generator) -> np.ndarray:
    return layout.depth_mm + rng.uniform(-layout.depth_jitter_mm, layout.depth_jitter_mm, n)


def poisson_disk_xy(layout: PoissonDiskLayout, size_mm: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """In-plane centres (K, 2), no two closer than ``min_spacing_mm``, uniformly spread."""
    w, h = _free_area(size_mm, layout.margin_mm)
    count = layout.count if layout.count is not None else max(1, round(layout.density_per_mm2 * w * h))
    sampler = qmc.PoissonDisk(d=2, radius=layout.min_spacing_mm, l_bounds=[0, 0], u_bounds=[w, h], rng=rng)
    pts = sampler.fill_space()
    if len(pts) < count:
        raise ValueError(
            f"only {len(pts)} markers fit in {w:.1f} x {h:.1f} mm at min_spacing_mm = {layout.min_spacing_mm}; "
            f"asked for {count}: lower the count or the spacing"
        )
    pts = pts[rng.choice(len(pts), size=count, replace=False)]
    return pts - [w / 2, h / 2]


def lattice_xy(layout: GridLayout | HexagonalLayout, size_mm: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Square or hexagonal lattice of pitch ``pitch_mm``, centred on the gel, with optional jitter."""
    w, h = _free_area(size_mm, layout.margin_mm)
    p = layout.pitch_mm
    row_pitch = p if layout.layout == "grid" else p * np.sqrt(3) / 2
    rows = int(np.floor(h / row_pitch + 1e-9)) + 1
    pts = []
    for r in range(rows):
        shift = p / 2 if (layout.layout == "hexagonal" and r % 2) else 0.0
        cols = int(np.floor((w - shift) / p + 1e-9)) + 1
        pts += [(shift + c * p, r * row_pitch) for c in range(cols)]
    pts = np.asarray(pts, dtype=float)
    pts -= (pts.max(axis=0) + pts.min(axis=0)) / 2  # centre the lattice
    pts += rng.uniform(-layout.jitter_mm, layout.jitter_mm, pts.shape)
    return np.clip(pts, [-w / 2, -h / 2], [w / 2, h / 2])


def read_layout_file(path: Path) -> np.ndarray:
    """(K, 3) rows of x_mm, y_mm, depth_mm from a CSV (with that header) or JSON file."""
    if path.suffix.lower() == ".json":
        rows = json.loads(path.read_text())
        rows = [[r["x_mm"], r["y_mm"], r["depth_mm"]] if isinstance(r, dict) else r for r in rows]
    else:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            missing = {"x_mm", "y_mm", "depth_mm"} - set(reader.fieldnames or [])
            if missing:
                raise ValueError(f"CSV header lacks {sorted(missing)} (need x_mm,y_mm,depth_mm)")
            rows = [[float(r["x_mm"]), float(r["y_mm"]), float(r["depth_mm"])] for r in reader]
    arr = np.asarray(rows, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
        raise ValueError(f"expected a non-empty list of [x_mm, y_mm, depth_mm], got shape {arr.shape}")
    return arr


def marker_centres(
    layout: MarkerLayout,
    gel_size_mm: tuple[float, float],
    thickness_mm: float,
    *,
    source: str | Path = "<layout>",
    relative_to: Path | None = None,
) -> np.ndarray:
    """Marker centres (K, 3) in the gel frame for ``layout``; errors name ``source``."""
    try:
        if isinstance(layout, FileLayout):
            path = Path(layout.path)
            path = path if path.is_absolute() else (relative_to or Path.cwd()) / path
            xyd = read_layout_file(path)
            depth = xyd[:, 2]
            xy = xyd[:, :2]
        else:
            rng = np.random.default_rng(layout.seed)
            xy = poisson_disk_xy(layout, gel_size_mm, rng) if isinstance(layout, PoissonDiskLayout) else lattice_xy(layout, gel_size_mm, rng)
            depth = _depths(layout, len(xy), rng)
    except (ValueError, OSError) as e:
        raise ConfigError(source, [("markers", str(e))]) from None
    r = layout.radius_mm
    half = np.asarray(gel_size_mm) / 2 - r
    outside = np.flatnonzero((np.abs(xy) > half + 1e-9).any(axis=1) | (depth < r) | (depth > thickness_mm - r))
    if len(outside):
        i = outside[0]
        raise ConfigError(source, [(
            f"markers[{i}]",
            f"marker at x={xy[i, 0]:.3f}, y={xy[i, 1]:.3f}, depth={depth[i]:.3f} mm is outside the gel "
            f"(allowed: |x| <= {half[0]:.3f}, |y| <= {half[1]:.3f}, {r} <= depth <= {thickness_mm - r:.3f}); "
            f"{len(outside)} marker(s) outside in all",
        )])
    return np.column_stack([xy, thickness_mm - depth])
