"""Quasi-static FEM of the gel (Warp FEM): stable Neo-Hookean P1/P2 tets, rigid mesh indenters with
penalty contact and smoothed Coulomb friction, Newton with line search and adaptive sub-stepping."""

import logging
import os

import warp as wp

from transtac_sim.physics.indenter import RigidIndenter
from transtac_sim.physics.material import ElasticMaterial
from transtac_sim.physics.solver import (
    FailedStep,
    FrameResult,
    IndenterStartsInsideGel,
    QuasiStaticSolver,
    SolverDidNotConverge,
    SolverRecord,
    SolverSettings,
)

# Warp reports every kernel module it loads; users see that as noise. TRANSTAC_SIM_WARP_VERBOSE=1 keeps it.
if os.environ.get("TRANSTAC_SIM_WARP_VERBOSE", "") != "1":
    wp.config.log_level = logging.WARNING

__all__ = [
    "ElasticMaterial",
    "FailedStep",
    "FrameResult",
    "IndenterStartsInsideGel",
    "QuasiStaticSolver",
    "RigidIndenter",
    "SolverDidNotConverge",
    "SolverRecord",
    "SolverSettings",
]
