"""The inversion barrier's gradient and Hessian (elasticity.py), added only in the tets where it acts.

E_b = sum over tets and their check points q (the order-2 rule of elasticity.py's barrier, weights w_q, volume V) of
V w_q kappa b(J_q), kappa = ``barrier_stiffness`` mu, b = 0 for J >= j_hat. With g_a the gradient of node a's basis
function at q (10 nodes of a P2 tet: phi = l_i (2 l_i - 1) at vertex i, 4 l_i l_j at the edge (i, j) node; 4 of a P1
tet) the gradient of node a is

    sum_q V w_q kappa b'(J_q) cof(F_q) g_a,

and the Hessian's block of the tet's nodes (a, b), every pair of them coupling,

    V w_q [ kappa b''(J) (cof F g_a)(cof F g_b)^T + s C_ab ],   column j of C_ab = dcof(F)[e_j g_b^T] g_a,

with s = geometric kappa b'(J) (clamped with ``clamp``). Outside the tets with some J below j_hat both are 0.

- **Gradient** (``BarrierCheckPoints.add_gradient_to``): one thread per tet finds F at its check points from u,
  returns where every J is at least j_hat, and otherwise adds each of its nodes' parts atomically into the gradient.
  warp.fem's integration of the same integrand visited every node's check points at every gradient, about 0.2 ms of
  GPU time each on press_slide on an H100, where the barrier acts in few gradients (BENCHMARKS.md
  ``fem_barrier_gradient_gpu``).
- **Hessian** (``BarrierHessian.add_to``): F and (s, kappa b'') at each point come from
  ``elasticity.barrier_state_form``, which also marks the tets with some J below j_hat (``barrier_tets``); one thread
  per (tet, node pair) returns at once outside the marked tets and adds its block atomically into the sum. warp.fem's
  assembly of the integrand evaluated every tet's 100 blocks at 4 points and scattered them: on press_slide on an H100,
  1.3 ms of GPU time per Hessian where the barrier acted, about one in five; this, about 0.1 ms or less; the GPU's work
  per Newton iteration 0.94-0.97x (BENCHMARKS.md ``fem_barrier_hessian_gpu``).

On a GPU the order of two threads' adds into one entry varies from run to run (round-off in the last bits, as the CG's
sums); Warp's CPU runs the threads in one order. The check points (``BarrierCheckPoints.make``) are made from the
solver's tet geometry (volumetric_hessian.py ``TetGeometry``, shared with the volumetric Hessian: computing it again
had taken most of the barrier's set-up, 59 against 11 ms under cProfile on press_slide, BENCHMARKS.md
``fem_steady_state_gpu``) at the first gradient on a GPU, the Hessian's block places the first time the barrier acts
(``BarrierHessian.make``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp
from warp.sparse import BsrMatrix

from transtac_sim.physics.elasticity import cofactor, cofactor_delta, det_barrier
from transtac_sim.physics.sparse_product import block_index
from transtac_sim.physics.volumetric_hessian import TetGeometry

_f = wp.float64


@wp.func
def _basis_gradient(lam_grad: wp.array2d(dtype=wp.vec3d), t: int, node: wp.vec2i, bary: wp.vec4d, degree: int):
    """Gradient (1/mm) at barycentric point ``bary`` of tet t's basis function of a local node: vertex i (node =
    (i, i)) or edge (i, j) of a P2 tet, vertex i of a P1 one."""
    i = node[0]
    j = node[1]
    if degree == 1:
        return lam_grad[t, i]
    if i == j:
        return (_f(4.0) * bary[i] - _f(1.0)) * lam_grad[t, i]
    return _f(4.0) * (bary[i] * lam_grad[t, j] + bary[j] * lam_grad[t, i])


@wp.func
def _check_point_F(u: wp.array(dtype=wp.vec3d), nodes: wp.array2d(dtype=int), layout: wp.array(dtype=wp.vec2i),
                   lam_grad: wp.array2d(dtype=wp.vec3d), point: wp.vec4d, degree: int, t: int):
    """F = I + sum over tet t's nodes of u_b g_b^T at its check point ``point`` (barycentric)."""
    F = wp.identity(n=3, dtype=wp.float64)
    for b in range(layout.shape[0]):
        F += wp.outer(u[nodes[t, b]], _basis_gradient(lam_grad, t, layout[b], point, degree))
    return F


@wp.kernel(enable_backward=False)
def _add_barrier_gradient(u: wp.array(dtype=wp.vec3d), nodes: wp.array2d(dtype=int), layout: wp.array(dtype=wp.vec2i),
                          lam_grad: wp.array2d(dtype=wp.vec3d), volume: wp.array(dtype=wp.float64),
                          points: wp.array(dtype=wp.vec4d), weights: wp.array(dtype=wp.float64), degree: int,
                          params: wp.array(dtype=wp.vec2d), stiffness: wp.float64, j_hat: wp.float64,
                          g: wp.array(dtype=wp.vec3d)):
    """g[nodes[t, a]] += the barrier's gradient of tet t's node a, sum_q V w_q kappa b'(J_q) cof(F_q) g_a, for each
    node a of tet t where some J_q of tet t is below j_hat (nothing elsewhere): one thread per tet, which returns once
    it has found every J_q at least j_hat (the usual case)."""
    t = wp.tid()
    acts = wp.int32(0)
    for q in range(points.shape[0]):
        if wp.determinant(_check_point_F(u, nodes, layout, lam_grad, points[q], degree, t)) < j_hat:
            acts = wp.int32(1)
    if acts == 0:
        return
    scale = stiffness * params[t][0] * volume[t]
    for a in range(layout.shape[0]):
        part = wp.vec3d()
        for q in range(points.shape[0]):
            F = _check_point_F(u, nodes, layout, lam_grad, points[q], degree, t)
            part += weights[q] * det_barrier(wp.determinant(F), j_hat)[1] * (
                cofactor(F) * _basis_gradient(lam_grad, t, layout[a], points[q], degree))
        wp.atomic_add(g, nodes[t, a], scale * part)


@wp.kernel(enable_backward=False)
def _add_barrier_blocks(barrier_tets: wp.array(dtype=wp.int32), layout: wp.array(dtype=wp.vec2i),
                        lam_grad: wp.array2d(dtype=wp.vec3d), volume: wp.array(dtype=wp.float64),
                        points: wp.array(dtype=wp.vec4d), weights: wp.array(dtype=wp.float64), degree: int,
                        F_qp: wp.array(dtype=wp.mat33d), b_qp: wp.array(dtype=wp.vec2d),
                        slots: wp.array2d(dtype=int), total: wp.array(dtype=wp.mat33d)):
    """total[slots[t, a K + b]] += the barrier's block of tet t's nodes (a, b), summed over its check points, where the
    barrier acts in tet t."""
    t, pair = wp.tid()
    if barrier_tets[t] == 0:
        return
    K = layout.shape[0]
    Q = points.shape[0]
    a = pair // K
    b = pair - a * K
    block = wp.mat33d()
    for q in range(Q):
        F = F_qp[t * Q + q]
        s = b_qp[t * Q + q]  # (geometric kappa b' (clamped), kappa b'')
        ga = _basis_gradient(lam_grad, t, layout[a], points[q], degree)
        gb = _basis_gradient(lam_grad, t, layout[b], points[q], degree)
        cof = cofactor(F)
        ba = cof * ga
        bb = cof * gb
        c0 = s[1] * bb[0] * ba + s[0] * (cofactor_delta(F, wp.outer(wp.vec3d(_f(1.0), _f(0.0), _f(0.0)), gb)) * ga)
        c1 = s[1] * bb[1] * ba + s[0] * (cofactor_delta(F, wp.outer(wp.vec3d(_f(0.0), _f(1.0), _f(0.0)), gb)) * ga)
        c2 = s[1] * bb[2] * ba + s[0] * (cofactor_delta(F, wp.outer(wp.vec3d(_f(0.0), _f(0.0), _f(1.0)), gb)) * ga)
        block += weights[q] * wp.matrix_from_cols(c0, c1, c2)
    wp.atomic_add(total, slots[t, pair], volume[t] * block)


@wp.kernel(enable_backward=False)
def _find_slots(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                nodes: wp.array2d(dtype=int), slots: wp.array2d(dtype=int)):
    """slots[t, a K + b] = the index of block (nodes[t, a], nodes[t, b]) among the matrix's blocks (-1: not stored)."""
    t, pair = wp.tid()
    K = nodes.shape[1]
    a = pair // K
    slots[t, pair] = block_index(offsets, row_counts, columns, nodes[t, a], nodes[t, pair - a * K])


@dataclass(frozen=True)
class BarrierCheckPoints:
    """The tets and the barrier's check points as its kernels see them, made once per mesh (``make``), on the device:
    each tet's nodes and their local layout, barycentric gradients (1/mm) and volume (mm^3), the check points
    (barycentric) and weights (fractions of the volume)."""

    nodes: wp.array  # (tets, K) int: node indices (warp.fem space numbering)
    layout: wp.array  # (K,) vec2i: local node -> (i, j), see volumetric_hessian.TetGeometry
    lam_grad: wp.array  # (tets, 4) vec3d
    volume: wp.array  # (tets,) float64
    points: wp.array  # (Q,) vec4d
    weights: wp.array  # (Q,) float64
    degree: int

    @staticmethod
    def make(geometry: TetGeometry, quadrature, device) -> BarrierCheckPoints:
        """``geometry``: the mesh's tets (volumetric_hessian.py ``TetGeometry``); ``quadrature``: the barrier's regular
        quadrature on its cells (whose point t Q + q is tet t's q-th, as in
        ``barrier_state_form``'s arrays)."""
        reference = np.asarray(quadrature.points, dtype=np.float64)  # (Q, 3): barycentric coordinates 1-3
        points = np.concatenate([1.0 - reference.sum(axis=1, keepdims=True), reference], axis=1)
        weights = np.asarray(quadrature.weights, dtype=np.float64)
        tet_count, K = geometry.element_nodes.shape
        if quadrature.total_point_count() != tet_count * len(weights):
            raise ValueError(f"{quadrature.total_point_count()} check points for {tet_count} tets of {len(weights)}")

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=device)

        return BarrierCheckPoints(nodes=arr(geometry.element_nodes.astype(np.int32), int),
                                  layout=arr(np.array(geometry.layout, dtype=np.int32), wp.vec2i),
                                  lam_grad=arr(geometry.lam_grad, wp.vec3d), volume=arr(geometry.volume, wp.float64),
                                  points=arr(points, wp.vec4d), weights=arr(weights, wp.float64),
                                  degree=1 if K == 4 else 2)

    def add_gradient_to(self, g: wp.array, u: wp.array, params: wp.array, stiffness: float, j_hat: float) -> None:
        """Adds the barrier's gradient at displacement ``u`` (dof values, mm) to ``g`` (N, vec3d per node), in place:
        stiffness mu b'(J) with mu the first of each tet's ``params``, j_hat the barrier's threshold on det F."""
        wp.launch(_add_barrier_gradient, dim=self.nodes.shape[0], device=g.device,
                  inputs=[u, self.nodes, self.layout, self.lam_grad, self.volume, self.points, self.weights,
                          self.degree, params, wp.float64(stiffness), wp.float64(j_hat), g])


@dataclass(frozen=True)
class BarrierHessian:
    """Where each tet's blocks of the barrier's Hessian go in the summed matrix (``make``, the first time the barrier
    acts), with the check points they are summed over."""

    check: BarrierCheckPoints
    slots: wp.array  # (tets, K K) int: the sum's block of tet t's nodes (a, b) at [t, a K + b]

    @staticmethod
    def make(check: BarrierCheckPoints, total: BsrMatrix, device) -> BarrierHessian:
        """``check``: the mesh's tets and check points; ``total``: a matrix with the sum's sparsity (every pair of
        nodes of a tet)."""
        tet_count, K = check.nodes.shape
        slots = wp.empty((tet_count, K * K), dtype=int, device=device)  # on the device: 21,890 x 100 on press_slide
        wp.launch(_find_slots, dim=slots.shape, device=device,
                  inputs=[total.offsets, total.row_counts, total.columns, check.nodes, slots])
        if slots.numpy().min() < 0:
            raise RuntimeError("a barrier Hessian block lies outside the elements' sparsity")
        return BarrierHessian(check=check, slots=slots)

    def add_to(self, total: BsrMatrix, F_qp: wp.array, b_qp: wp.array, barrier_tets: wp.array) -> None:
        """Adds the barrier's Hessian to ``total``'s blocks, in place, in the tets marked in ``barrier_tets``, from the
        check points' F and (s, kappa b'') of ``elasticity.barrier_state_form``."""
        c = self.check
        wp.launch(_add_barrier_blocks, dim=self.slots.shape, device=total.values.device,
                  inputs=[barrier_tets, c.layout, c.lam_grad, c.volume, c.points, c.weights, c.degree,
                          F_qp, b_qp, self.slots, total.values])
