"""Quasi-static frames: minimise elastic + contact + friction energy with Newton and a line search.

Each frame moves the indenters from the previous poses to new ones. The solver minimises
E(u) = E_el(u) + E_contact(u) (see elasticity.py, contact.py) over the displacement u (mm) of a P1 or P2
tet mesh, with u = 0 on the fixed components (default: every vertex with z <= tol, the bonded face).

This module: the discretisation (Warp FEM spaces, quadratures, fixed dofs) and the indenters' structs. The frame API
(start, a frame in load sub-steps halved where one fails, snapshot and restore) is in load_stepping.py; the assembly of
E and its gradient in assembly.py, of its Hessian in hessian_assembly.py; the displacement at points inside the tets
(markers) in point_displacement.py. The Newton iteration of one (sub)step is in newton.py: warm start from the
extrapolated last increment, friction's lag and the contact stiffness updated inside Newton, a line search that never
accepts an inverted element, and a convergence test on the estimated Newton step.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import warp as wp
import warp.fem as fem
from scipy.spatial import cKDTree

from transtac_sim.physics import contact, indenter_query
from transtac_sim.physics.assembly import Assembly
from transtac_sim.physics.contact_prediction import ContactPrediction
from transtac_sim.physics.contact_records import ContactRecords
from transtac_sim.physics.contact_sides import ContactSides
from transtac_sim.physics.hessian_assembly import HessianAssembly
from transtac_sim.physics.indenter import RigidIndenter
from transtac_sim.physics.linear import LinearSolver
from transtac_sim.physics.load_stepping import LoadStepping
from transtac_sim.physics.material import ElasticMaterial, neo_hookean_parameters
from transtac_sim.physics.newton import NewtonSteps
from transtac_sim.physics.point_displacement import PointDisplacement
from transtac_sim.physics.reductions import negated_free_buffer, reduction_buffer
from transtac_sim.physics.replay import GraphCache
from transtac_sim.physics.settings import (  # noqa: F401 (re-exported: the solver's API)
    FailedStep,
    FrameResult,
    IndenterStartsInsideGel,
    SolverDidNotConverge,
    SolverRecord,
    SolverSettings,
)
from transtac_sim.physics.warm_start import WarmStart


class QuasiStaticSolver(LoadStepping, Assembly, HessianAssembly, ContactRecords, NewtonSteps, WarmStart,
                        ContactPrediction, PointDisplacement):
    """Quasi-static hyperelastic gel pressed by rigid indenters; numpy in, numpy out.

    vertices_mm (N,3), tets (M,4); ``materials`` one ElasticMaterial or a list indexed by
    ``material_index`` (M,); ``fixed`` bool (N,) or (N,3) per-vertex (per-component) Dirichlet mask
    (u = 0), default z <= settings.fixed_z_tol_mm.
    """

    def __init__(
        self,
        vertices_mm: np.ndarray,
        tets: np.ndarray,
        materials: ElasticMaterial | list[ElasticMaterial],
        indenters: list[RigidIndenter],
        settings: SolverSettings = SolverSettings(),
        device: str = "cpu",
        material_index: np.ndarray | None = None,
        fixed: np.ndarray | None = None,
    ):
        self.settings = settings
        self.device = wp.get_device(device)
        self.indenters = list(indenters)
        V = np.ascontiguousarray(vertices_mm, dtype=np.float64)
        T = np.ascontiguousarray(tets, dtype=np.int32).copy()
        e = V[T[:, 1:]] - V[T[:, :1]]
        vol = np.einsum("ij,ij->i", np.cross(e[:, 0], e[:, 1]), e[:, 2])
        if np.any(np.abs(vol) < 1e-14 * np.max(np.abs(vol))):
            raise ValueError("tet mesh has degenerate (zero-volume) tets")
        self._flipped = vol < 0
        T[self._flipped] = T[self._flipped][:, [0, 2, 1, 3]]
        self.vertices_mm, self.tets = V, T
        fixed_vertices = self._fixed_vertex_mask(fixed)
        self._params_np = neo_hookean_parameters(materials, material_index, len(T))

        with wp.ScopedDevice(self.device):
            self._geo = fem.Tetmesh(wp.array(T, dtype=int), wp.array(V, dtype=wp.vec3d))
            self._space = fem.make_polynomial_space(self._geo, degree=settings.degree, dtype=wp.vec3d)
            self._cells = fem.Cells(self._geo)
            self._sides, side_vertices = self._touchable_sides(fixed_vertices)
            self._q_dev = fem.RegularQuadrature(self._cells, order=2 * (settings.degree - 1))
            self._q_vol = fem.RegularQuadrature(self._cells, order=0)
            self._q_det = fem.RegularQuadrature(self._cells, order=2)
            corder = settings.contact_quadrature_order or 2 * settings.degree
            self._q_contact = fem.RegularQuadrature(self._sides, order=corder)
            self._contact_sides = ContactSides(self._space, self._sides, side_vertices, corder, self.device)
            self._params = wp.array(self._params_np, dtype=wp.vec2d)
            self.u = self._space.make_field()  # current
            self.u_prev = self._space.make_field()  # start of the current (sub)step
            self.u_lag = self._space.make_field()  # friction lag
            self._u_try = self._space.make_field()
            self._node_positions = self._space.node_positions()  # (nodes,) vec3d, mm
            self._test = fem.make_test(self._space, domain=self._cells)
            self._trial = fem.make_trial(self._space, domain=self._cells)
            self._side_test = fem.make_test(self._space, domain=self._sides)
            n_det = self._q_det.total_point_count()
            self._F_det = wp.empty(n_det, dtype=wp.mat33d)
            self._b_det = wp.empty(n_det, dtype=wp.vec2d)
            self._barrier_tets = wp.zeros(len(T), dtype=wp.int32)  # 1 where the barrier acts (hessian_assembly.py)
            n_contact = self._q_contact.total_point_count() * len(self.indenters)
            self._contact_state = contact.ContactState()
            for name, dtype in (("lag_g", wp.float64), ("lag_n", wp.vec3d), ("normal", wp.vec3d),
                                ("k_normal", wp.float64), ("k_slip", wp.float64), ("k_slip_dir", wp.float64),
                                ("slip_dir", wp.vec3d), ("stick", wp.vec3d), ("stick_next", wp.vec3d)):
                setattr(self._contact_state, name, wp.zeros(n_contact, dtype=dtype))
            self._contact_state.traction = wp.zeros(self._q_contact.total_point_count(), dtype=wp.vec3d)

        self._node_of_vertex, fixed_nodes = self._map_nodes(fixed_vertices)
        method = settings.linear_solver
        if method == "auto":
            method = "cg" if self.device.is_cuda else "direct"
        coarse = method == "cg" and settings.coarse_cell_mm is not None  # the device CG's coarse level only
        self._linear = LinearSolver(method, fixed_nodes, self.device,
                                    node_positions_mm=self._node_positions.numpy() if coarse else None,
                                    coarse_cell_mm=settings.coarse_cell_mm if coarse else None)
        self._fixed_nodes = fixed_nodes
        self._fixed_mask = wp.array(fixed_nodes.astype(np.float64), dtype=wp.vec3d, device=self.device)  # 1: fixed

        self.contact_stiffness = settings.contact_stiffness or self._default_contact_stiffness()
        self._meshes = [ind.warp_mesh(self.device) for ind in self.indenters]
        self._normals: dict[tuple, tuple[wp.array, wp.array]] = {}  # ``_feature_normals`` by indenters chosen
        self._structs: dict[tuple, indenter_query.Indenters] = {}  # ``_indenter_struct`` by (role, indenters chosen)
        self._poses: list[np.ndarray] | None = None
        self._barrier_energy: float | None = 0.0  # the barrier's energy at the last ``_gradient``'s u (None: not read)
        self._contact_stale: bool | None = None  # the contact side subset misses stiff sides (None: not read)
        self._energy_sum = wp.zeros(1, dtype=wp.float64, device=self.device)  # ``_energy``'s total (N mm)
        self._det_work = (wp.empty(self._q_det.total_point_count(), dtype=wp.float64, device=self.device),
                          reduction_buffer(3, self.device))  # ``_min_det``'s det F and extremes
        # the line-search trial's alpha and du's row among the linear solver's kept solutions, as the host writes them
        # (pinned on a GPU: the trial's graph copies them in at each replay) and on the device (trial_point.py)
        self._trial_host = wp.zeros(2, dtype=wp.float64, device="cpu", pinned=self.device.is_cuda)
        self._trial_step = wp.zeros(2, dtype=wp.float64, device=self.device)
        self._g = wp.empty_like(self.u.dof_values)  # ``_gradient``'s result (N per node)
        self._barrier_sum = wp.zeros(1, dtype=wp.float64, device=self.device)  # the barrier's energy at ``_gradient``
        self._lag_work = reduction_buffer(2, self.device)  # friction_lag.py ``_launch_lag_change``
        self._rhs = wp.empty_like(self.u.dof_values)  # -g on the free dofs (newton.py ``_read_gradient``)
        self._gradient_read = negated_free_buffer(5, self.device)  # |g|, the load and what is read with them
        # filled by ``_launch_wrench`` (contact_records.py)
        self._wrench_work = wp.zeros(6 * len(self.indenters), dtype=wp.float64, device=self.device)
        st = self._contact_state  # friction's lag kept while ``_launch_friction_lag_residual`` moves it
        self._lag_kept = (wp.empty_like(st.lag_g), wp.empty_like(st.lag_n))
        self._penetration_work = (wp.empty(self._q_contact.total_point_count(), dtype=wp.float64, device=self.device),
                                  reduction_buffer(3, self.device))  # ``_max_penetration``'s values and extremes
        self._free_norm_work = (wp.empty_like(self._g), negated_free_buffer(0, self.device))  # ``_free_norm``'s
        # u and friction's stretch at a frame's start, put back where the frame fails (``solve_frame``)
        self._frame_start = (wp.empty_like(self.u.dof_values), wp.empty_like(self._contact_state.stick_next))
        self._stiff_work = wp.empty(self._q_contact.total_point_count(), dtype=wp.int8, device=self.device)  # 1: stiff
        self._graphs = GraphCache(self.device)  # the solver's launch sequences as CUDA graphs (replay.py)
        self._dev = None  # the deviatoric term's constant Hessian and gradient at u = 0 (assembly.py ``_deviatoric``)
        self._H_parts: dict = {}  # its parts that change with u, assembled in place (``_assemble``)
        self._tet_geometry = None  # the tets as the tet-by-tet terms see them (volumetric_hessian.py), on first use
        self._volumetric = None  # the tet-by-tet volumetric Hessian's set-up (volumetric_hessian.py), made on first use
        self._barrier_points = None  # the barrier's tets and check points on the device (barrier_terms.py), first use
        self._barrier_hessian = None  # the barrier Hessian's block places (barrier_terms.py), the first time it acts
        self._H = None  # the summed Hessian (``_hessian``), and each part's places in it (``_sum_slots``)
        self._H_slots: dict = {}
        self._increment: tuple[wp.array, np.ndarray, float] | None = None  # last (du, pose step, penetration)
        self.stats: Counter = Counter()  # per frame: backtracks, stiffness_raises, warm_starts, lag_updates
        self.frame_index = 0

    # -- set-up helpers -------------------------------------------------------------------------
    def _fixed_vertex_mask(self, fixed) -> np.ndarray:
        """The (N,3) per-component Dirichlet mask of the vertices: ``fixed`` as given, default z <= fixed_z_tol_mm."""
        V = self.vertices_mm
        if fixed is None:
            fixed = V[:, 2] <= self.settings.fixed_z_tol_mm
        fixed = np.asarray(fixed, dtype=bool)
        if fixed.ndim == 1:
            fixed = np.repeat(fixed[:, None], 3, axis=1)
        if fixed.shape != V.shape:
            raise ValueError(f"fixed mask must be (N,) or (N,3), got {fixed.shape}")
        return fixed

    def _touchable_sides(self, fixed_vertices: np.ndarray) -> tuple[fem.GeometryDomain, np.ndarray]:
        """The boundary sides contact is integrated over, and their vertex indices (sides, 3): all but those whose
        three vertices are fixed in every component (the bonded face: it cannot move, and no indenter reaches it
        through the gel). On a slab that is about half the boundary, and every contact kernel (a mesh query per
        quadrature point) does half the work."""
        sides = fem.BoundarySides(self._geo)
        # boundary side i is face _boundary_face_indices[i] of the Tetmesh (what its boundary_side_index returns)
        faces = self._geo.face_vertex_indices.numpy()[self._geo._boundary_face_indices.numpy()]
        held = fixed_vertices.all(axis=1)[faces].all(axis=1)
        if not held.any():
            return sides, faces
        return (fem.Subdomain(sides, element_indices=wp.array(np.flatnonzero(~held).astype(np.int32), dtype=int)),
                faces[~held])

    def _map_nodes(self, fixed: np.ndarray):
        """(node of each vertex, the (nodes, 3) Dirichlet mask of the FE nodes) from the vertices' mask ``fixed``;
        a P2 edge node is fixed where both its vertices are."""
        V, T = self.vertices_mm, self.tets
        nodes = self._node_positions.numpy()
        tree = cKDTree(nodes)
        scale = np.ptp(V, axis=0).max()
        dist, node_of_vertex = tree.query(V)
        if np.max(dist) > 1e-9 * scale:
            raise RuntimeError("could not match mesh vertices to FE nodes")
        fixed_nodes = np.zeros((len(nodes), 3), dtype=bool)
        fixed_nodes[node_of_vertex] = fixed
        if self.settings.degree == 2:
            edges = np.unique(np.sort(T[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]].reshape(-1, 2), axis=1), axis=0)
            dist, node_of_edge = tree.query(0.5 * (V[edges[:, 0]] + V[edges[:, 1]]))
            if np.max(dist) > 1e-9 * scale:
                raise RuntimeError("could not match mesh edges to FE nodes")
            fixed_nodes[node_of_edge] = fixed[edges[:, 0]] & fixed[edges[:, 1]]
        if not fixed_nodes.any():
            raise ValueError("no fixed degree of freedom: the gel would float freely")
        return node_of_vertex, fixed_nodes

    def _default_contact_stiffness(self) -> float:
        """Penalty stiffness (N/mm^3) = stiffness_factor * E / (h / degree), from the surface that can be touched.

        E ~ 3 mu (the upper bound of 2 mu (1 + nu)) is the stiffest material among the tets with a vertex on
        the top face, and h the 10th percentile of the edge lengths of the top face: a stiff backing that no
        indenter reaches does not stiffen the penalty, and on a graded mesh the fine cells under the contact
        region set it, not the coarse outer ones."""
        V, T = self.vertices_mm, self.tets
        on_top = V[:, 2] >= V[:, 2].max() - 1e-9
        top_tets = on_top[T].any(axis=1)
        pairs = T[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]].reshape(-1, 2)
        top_edges = pairs[on_top[pairs].all(axis=1)]
        if not top_edges.size:
            top_edges, top_tets = pairs, np.ones(len(T), dtype=bool)
        h = float(np.percentile(np.linalg.norm(V[top_edges[:, 1]] - V[top_edges[:, 0]], axis=1), 10))
        e_top = 3.0 * float(np.max(self._params_np[top_tets, 0]))
        return self.settings.stiffness_factor * e_top / (h / self.settings.degree)

    def _feature_normals(self, which: tuple[int, ...]) -> tuple[wp.array, wp.array]:
        """The indenters ``which``'s face, vertex and edge normals (``RigidIndenter.feature_normals``, 7 per face, one
        mesh after another) and where each mesh's start, on the device; made once per choice."""
        if which not in self._normals:
            normals = [self.indenters[i].feature_normals() for i in which]
            self._normals[which] = (
                wp.array(np.concatenate(normals).reshape(-1, 3), dtype=wp.vec3d, device=self.device),
                wp.array(np.cumsum([0] + [7 * len(n) for n in normals[:-1]]), dtype=int, device=self.device))
        return self._normals[which]

    def _indenter_struct(self, poses, prev_poses, which: list[int] | None = None,
                         role: str = "step") -> indenter_query.Indenters:
        """The indenters ``which`` (default all) at ``poses``, having moved from ``prev_poses`` (one each), with the
        current contact stiffness. One struct per ``role`` and choice of indenters is kept for the solver's life and
        its pose arrays are written in place: the CUDA graphs that bake the struct in (replay.py) then replay the
        next load step with its poses instead of being captured anew. Newton's load step has the role "step", the
        step's first friction lag at the previous poses "lag", ``start``'s check of each indenter "probe"; a struct
        handed out earlier for the same role takes the new poses too."""
        which = list(range(len(self.indenters))) if which is None else which
        key = (role, tuple(which))
        s = self._structs.get(key)
        if s is None:
            s = self._structs[key] = self._new_indenter_struct(which)
        s.pose.assign(np.stack(poses))
        s.pose_inv.assign(np.stack([np.linalg.inv(P) for P in poses]))
        s.relative.assign(np.stack([P @ np.linalg.inv(Q) for P, Q in zip(poses, prev_poses, strict=True)]))
        s.stiffness = self.contact_stiffness
        return s

    def _new_indenter_struct(self, which: list[int]) -> indenter_query.Indenters:
        """``_indenter_struct``'s struct for the indenters ``which``, without poses."""
        chosen = [self.indenters[i] for i in which]
        s = indenter_query.Indenters()
        dev = self.device
        s.mesh = wp.array([self._meshes[i].id for i in which], dtype=wp.uint64, device=dev)
        s.pose, s.pose_inv, s.relative = (wp.empty(len(which), dtype=wp.mat44d, device=dev) for _ in range(3))
        s.max_dist = wp.array([2.0 * i.bounding_radius_mm + 1.0 for i in chosen], dtype=wp.float64, device=dev)
        pad = [1.0e-6 * (1.0 + i.bounding_radius_mm) for i in chosen]  # float32 vertices: a box a little larger
        s.box_lo = wp.array([i.vertices_mm.min(axis=0) - d for i, d in zip(chosen, pad, strict=True)],
                            dtype=wp.vec3d, device=dev)
        s.box_hi = wp.array([i.vertices_mm.max(axis=0) + d for i, d in zip(chosen, pad, strict=True)],
                            dtype=wp.vec3d, device=dev)
        s.normals, s.normals_start = self._feature_normals(tuple(which))
        s.friction = wp.array([i.friction for i in chosen], dtype=wp.float64, device=dev)
        s.count = len(chosen)
        s.slip_eps = self.settings.slip_eps_mm
        return s
