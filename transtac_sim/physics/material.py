"""Linear-elastic constants and their stable Neo-Hookean counterparts.

A material is given by Young's modulus ``E`` (MPa = N/mm^2) and Poisson's ratio ``nu``. The Lame
constants are ``mu = E / (2 (1 + nu))`` and ``lambda = E nu / ((1 + nu)(1 - 2 nu))``.

The stable Neo-Hookean energy density (Smith et al. 2018, "Stable Neo-Hookean Flesh Simulation",
Sec. 3.2) is, with ``I_C = |F|^2`` and ``J = det F``,

    Psi(F) = mu/2 (I_C - 3) + lam/2 (J - alpha)^2,   lam = lambda + mu,   alpha = 1 + mu / lam.

It is defined for every F (inverted elements included), is stress free at F = I, and matches Hooke's
law (mu, lambda) for small strains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ElasticMaterial:
    """Isotropic material: Young's modulus (MPa) and Poisson ratio (-)."""

    young_mpa: float
    poisson: float

    def __post_init__(self) -> None:
        if not self.young_mpa > 0.0:
            raise ValueError(f"Young's modulus must be > 0 MPa, got {self.young_mpa}")
        if not -1.0 < self.poisson < 0.5:
            raise ValueError(f"Poisson ratio must be in (-1, 0.5), got {self.poisson}")

    @property
    def mu(self) -> float:
        return self.young_mpa / (2.0 * (1.0 + self.poisson))

    @property
    def lame_lambda(self) -> float:
        return self.young_mpa * self.poisson / ((1.0 + self.poisson) * (1.0 - 2.0 * self.poisson))


def neo_hookean_parameters(materials: ElasticMaterial | list[ElasticMaterial], material_index: np.ndarray | None,
                           tet_count: int) -> np.ndarray:
    """Per-tet ``(mu, lam)`` of the stable Neo-Hookean energy, shape (tet_count, 2), float64.

    ``materials`` is one material for every tet, or a list indexed by ``material_index`` (one int per tet).
    """
    if isinstance(materials, ElasticMaterial):
        materials = [materials]
        material_index = np.zeros(tet_count, dtype=np.int64)
    elif material_index is None:
        if len(materials) != 1:
            raise ValueError("several materials need a material_index per tet")
        material_index = np.zeros(tet_count, dtype=np.int64)
    material_index = np.asarray(material_index, dtype=np.int64)
    if material_index.shape != (tet_count,):
        raise ValueError(f"material_index must have shape ({tet_count},), got {material_index.shape}")
    if material_index.min() < 0 or material_index.max() >= len(materials):
        raise ValueError("material_index refers to a material that is not in the list")
    table = np.array([[m.mu, m.lame_lambda + m.mu] for m in materials], dtype=np.float64)
    return table[material_index]
