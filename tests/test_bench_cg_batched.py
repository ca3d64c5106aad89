"""scripts/bench_cg_batched.py: its stacked matrix is diag(H, ..., H), so that the batched CG it times solves K copies
of one system."""

import sys
from pathlib import Path

import numpy as np
import warp as wp
from warp.sparse import bsr_from_triplets, bsr_mv

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from bench_cg_batched import stacked  # noqa: E402


def test_stacked_matrix_multiplies_each_copy_by_the_original():
    rng = np.random.default_rng(0)
    rows, columns = np.array([0, 0, 1, 2, 2, 3]), np.array([0, 3, 1, 0, 2, 3])
    H = bsr_from_triplets(4, 4, wp.array(rows, dtype=int, device="cpu"), wp.array(columns, dtype=int, device="cpu"),
                          wp.array(rng.normal(size=(6, 3, 3)), dtype=wp.mat33d, device="cpu"))
    copies = 3
    Hk = stacked(H, copies)
    assert (Hk.nrow, Hk.ncol, int(Hk.offsets.numpy()[-1])) == (12, 12, 18)
    x = rng.normal(size=(copies, 4, 3))
    y = bsr_mv(Hk, wp.array(x.reshape(-1, 3), dtype=wp.vec3d, device="cpu")).numpy().reshape(copies, 4, 3)
    for k in range(copies):
        expected = bsr_mv(H, wp.array(x[k], dtype=wp.vec3d, device="cpu")).numpy()
        np.testing.assert_allclose(y[k], expected, rtol=1e-12, atol=1e-12)
