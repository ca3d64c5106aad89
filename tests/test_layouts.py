"""Marker layouts: spacing, pitch, counts, and layouts read from files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from transtac_sim.config.hardware import FileLayout, GridLayout, HexagonalLayout, PoissonDiskLayout
from transtac_sim.sensor.layouts import marker_centres

GEL = ((32.0, 24.0), 5.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_poisson_disk_respects_min_spacing_and_count(seed: int):
    lay = PoissonDiskLayout(layout="poisson_disk", count=110, min_spacing_mm=1.8, radius_mm=0.25, depth_mm=0.6,
                            depth_jitter_mm=0.1, seed=seed)
    p = marker_centres(lay, *GEL)
    assert len(p) == 110
    assert pdist(p[:, :2]).min() >= 1.8
    assert np.all(np.abs(p[:, 0]) <= 15.0) and np.all(np.abs(p[:, 1]) <= 11.0)  # 1 mm margin
    assert np.all((5.0 - p[:, 2] >= 0.5 - 1e-12) & (5.0 - p[:, 2] <= 0.7 + 1e-12))
    # same seed, same layout; another seed, another layout
    assert np.array_equal(p, marker_centres(lay, *GEL))


def test_poisson_disk_density():
    lay = PoissonDiskLayout(layout="poisson_disk", density_per_mm2=0.1, min_spacing_mm=1.5, radius_mm=0.2, depth_mm=1.0)
    assert len(marker_centres(lay, *GEL)) == round(0.1 * 30 * 22)


def test_grid_and_hexagonal_pitch():
    g = marker_centres(GridLayout(layout="grid", pitch_mm=2.0, radius_mm=0.2, depth_mm=1.0), *GEL)
    assert len(g) == 16 * 12 and pdist(g[:, :2]).min() == pytest.approx(2.0)
    assert g[:, 0].mean() == pytest.approx(0.0) and g[:, 1].mean() == pytest.approx(0.0)
    h = marker_centres(HexagonalLayout(layout="hexagonal", pitch_mm=2.0, radius_mm=0.2, depth_mm=1.0), *GEL)
    d = np.sort(np.linalg.norm(h[:, None, :2] - h[None, :, :2], axis=-1), axis=1)
    interior = (np.abs(h[:, 0]) < 12) & (np.abs(h[:, 1]) < 8)
    assert np.allclose(d[interior, 1:7], 2.0)  # six neighbours at the pitch


def test_layout_from_csv_and_json(tmp_path):
    rows = [[0.0, 0.0, 0.5], [3.0, -2.0, 1.0], [-10.0, 5.5, 0.8]]
    (tmp_path / "l.json").write_text(json.dumps(rows))
    (tmp_path / "l.csv").write_text("x_mm,y_mm,depth_mm\n" + "\n".join(",".join(map(str, r)) for r in rows))
    for name in ("l.json", "l.csv"):
        p = marker_centres(FileLayout(layout="file", path=name, radius_mm=0.25), *GEL, relative_to=tmp_path)
        assert np.allclose(p, [[r[0], r[1], 5.0 - r[2]] for r in rows])
