"""scripts/fem_det_f_sites.py's mesh helpers against hand-made tets."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from fem_det_f_sites import boundary_vertices, tet_quality  # noqa: E402


def test_tet_quality_is_one_for_a_regular_tet_and_falls_for_a_flat_one():
    regular = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
    flat = regular * np.array([1.0, 1.0, 0.05])
    q = tet_quality(np.vstack([regular, flat]), np.array([[0, 1, 2, 3], [4, 5, 6, 7]]))
    assert q[0] == pytest.approx(1.0) and 0.0 < q[1] < 0.2


def test_boundary_vertices_of_two_tets_and_of_an_inner_vertex():
    assert boundary_vertices(np.array([[0, 1, 2, 3], [1, 2, 3, 4]])).all()  # every vertex is on a free face
    # a vertex surrounded by 4 tets (a subdivided tet's centre 4) lies on no free face
    around = np.array([[4, 1, 2, 3], [0, 4, 2, 3], [0, 1, 4, 3], [0, 1, 2, 4]])
    assert boundary_vertices(around).tolist() == [True, True, True, True, False]
