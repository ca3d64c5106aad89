"""scripts/study_cg_preconditioners.py on the tiny press fixture: its copy of the device CG's preconditioner takes the
device CG's iterations (the baseline its other columns are read against), and the preconditioners it compares are
symmetric positive definite (the CG it runs them in assumes so)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import study_cg_preconditioners as study  # noqa: E402

FIXTURE = Path(__file__).parent / "fixtures" / "tiny_press.toml"


@pytest.fixture(scope="module")
def systems():
    kept, solver = study._systems(FIXTURE, 1)
    return kept, solver


def test_the_copy_of_the_device_preconditioner_takes_the_device_iterations(systems):
    """Within 2 iterations or 10 %: the device CG multiplies by the matrix rounded to float32, the copy in float64, and
    at the tight tolerance (1e-4) that moves the count by a few (fTetWild meshes the fixture anew on a cold cache, not
    the same mesh twice: on one mesh, on the 2-core CPU, this test failed with 110 against 106). Without the coarse level
    block-Jacobi takes about twice the iterations (BENCHMARKS.md ``fem_coarse_level_gpu``)."""
    kept, solver = systems
    assert len(kept) >= 3
    for s in kept[1:4]:  # the first system is solved before the coarse inverse exists (made from it)
        name, (M, products) = next(iter(study._preconditioners(s, solver).items()))
        assert name.startswith("two-level (the device CG's")
        assert products == 1
        assert abs(study._pcg(s.H, s.b, M, s.rtol) - s.device_iterations) <= max(2, 0.1 * s.device_iterations)


def test_the_compared_preconditioners_are_symmetric_positive_definite(systems):
    kept, solver = systems
    s = kept[2]
    free = 1.0 - solver._fixed_nodes.reshape(-1).astype(float)
    rng = np.random.default_rng(1)
    u, v = (rng.standard_normal(len(s.b)) * free for _ in range(2))
    for name, (M, _) in study._preconditioners(s, solver).items():
        Mu, Mv = M(u), M(v)
        assert abs(u @ Mv - v @ Mu) <= 1e-9 * np.sqrt((u @ Mu) * (v @ Mv)), name
        assert u @ Mu > 0.0 and v @ Mv > 0.0, name
