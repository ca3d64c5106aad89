"""The volumetric term's Hessian, assembled tet by tet into the summed Newton matrix (hessian_assembly.py).

E_vol = sum_tets V lam/2 (J - alpha)^2 with J = det F at one point per tet, the centroid (elasticity.py). With
g_a the gradient of node a's basis function at the centroid and b_a = cof(F) g_a, the 3x3 block of nodes (a, b) is

    V [ lam b_a b_b^T + s_h C_ab ],   column j of C_ab = dcof(F)[e_j g_b^T] g_a   (elasticity.cofactor_delta),

s_h the pressure lam (J - alpha) times ``geometric``, clamped to mu / sigma_max(F) (half that in tets where the barrier
acts) with ``clamp``: elasticity.py's module docstring says why. At the centroid the P2 vertex functions have zero
gradient (phi = l (2 l - 1) with l = 1/4), so only a tet's 6 edge nodes couple, each edge node's g the sum of its two
vertices' barycentric gradients: 36 blocks a tet (P1: its 4 vertices, 16 blocks).

warp.fem's generic assembly evaluated the integrand once per pair of the tet's 10 nodes, for blocks most of which are
zero: with this assembly instead, a Newton Hessian of the tiny press fixture (3267 tets) took 35 instead of 68 ms on the
2-core CPU (scripts/fem_phase_profile.py, BENCHMARKS.md ``fem_host_path_cpu``). Here one thread per tet computes F,
cof(F) and s_h (``_tet_states``), one thread per block writes the block on a GPU, one per tet on the CPU
(``_tet_blocks``), then one thread per receiving block of the sum adds them in a fixed order (a list made once): the
same sums in a deterministic order on every device. With one thread per tet writing all its blocks, the GPU ran 22k
threads on press_slide, each writing 2.6 kB of blocks that its neighbours' lay 2.6 kB away (BENCHMARKS.md
``fem_tet_blocks_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp
from warp.sparse import BsrMatrix

from transtac_sim.physics.elasticity import cofactor, cofactor_delta, pressure_bound
from transtac_sim.physics.sparse_product import block_keys

_f = wp.float64


@wp.kernel(enable_backward=False)
def _tet_states(u: wp.array(dtype=wp.vec3d), nodes: wp.array2d(dtype=int), grads: wp.array2d(dtype=wp.vec3d),
                params: wp.array(dtype=wp.vec2d), geometric: wp.float64, clamp: int,
                barrier_tets: wp.array(dtype=wp.int32), F_tet: wp.array(dtype=wp.mat33d),
                cof_tet: wp.array(dtype=wp.mat33d), s_tet: wp.array(dtype=wp.float64)):
    """Tet t's F, cof(F) and s_h at its centroid (the blocks' common factors, ``_tet_blocks``)."""
    t = wp.tid()
    F = wp.identity(n=3, dtype=wp.float64)
    for a in range(nodes.shape[1]):
        F += wp.outer(u[nodes[t, a]], grads[t, a])
    mu = params[t][0]
    lam = params[t][1]
    p = lam * (wp.determinant(F) - _f(1.0) - mu / lam)
    if clamp != 0:
        bound = pressure_bound(F, mu)
        if barrier_tets[t] != 0:
            bound = _f(0.5) * bound
        p = wp.clamp(p, -bound, bound)
    F_tet[t] = F
    cof_tet[t] = cofactor(F)
    s_tet[t] = geometric * p


@wp.kernel(enable_backward=False)
def _tet_blocks(grads: wp.array2d(dtype=wp.vec3d), volume: wp.array(dtype=wp.float64), params: wp.array(dtype=wp.vec2d),
                F_tet: wp.array(dtype=wp.mat33d), cof_tet: wp.array(dtype=wp.mat33d), s_tet: wp.array(dtype=wp.float64),
                per_thread: int, blocks: wp.array(dtype=wp.mat33d)):
    """blocks[(t K + a) K + b]: the volumetric Hessian block of tet t's coupled nodes a, b (K of them), ``per_thread``
    consecutive blocks of a tet per thread (on a GPU 1: neighbouring threads write neighbouring blocks)."""
    t, chunk = wp.tid()
    K = grads.shape[1]
    F = F_tet[t]
    cof = cof_tet[t]
    s = s_tet[t]
    lam = params[t][1]
    V = volume[t]
    for pair in range(chunk * per_thread, (chunk + 1) * per_thread):
        a = pair // K
        ga = grads[t, a]
        gb = grads[t, pair - a * K]
        ba = cof * ga
        bb = cof * gb
        c0 = lam * bb[0] * ba + s * (cofactor_delta(F, wp.outer(wp.vec3d(_f(1.0), _f(0.0), _f(0.0)), gb)) * ga)
        c1 = lam * bb[1] * ba + s * (cofactor_delta(F, wp.outer(wp.vec3d(_f(0.0), _f(1.0), _f(0.0)), gb)) * ga)
        c2 = lam * bb[2] * ba + s * (cofactor_delta(F, wp.outer(wp.vec3d(_f(0.0), _f(0.0), _f(1.0)), gb)) * ga)
        blocks[t * K * K + pair] = V * wp.matrix_from_cols(c0, c1, c2)


@wp.kernel(enable_backward=False)
def _add_gathered(targets: wp.array(dtype=int), offsets: wp.array(dtype=int), sources: wp.array(dtype=int),
                  blocks: wp.array(dtype=wp.mat33d), total: wp.array(dtype=wp.mat33d)):
    """total[targets[r]] += the sum of blocks[sources[offsets[r]:offsets[r + 1]]], in that order."""
    r = wp.tid()
    acc = wp.mat33d()
    for q in range(offsets[r], offsets[r + 1]):
        acc += blocks[sources[q]]
    total[targets[r]] = total[targets[r]] + acc


@dataclass(frozen=True)
class TetGeometry:
    """A mesh's tets as the tet-by-tet terms (this module's Hessian, barrier_terms.py's gradient and Hessian) see them,
    made once per mesh (``of``; host arrays): each tet's nodes in the P1 or P2 warp.fem space (tets, 4 or 10) and their
    local layout (per local node (i, j): the vertex i where i = j, else the midpoint of edge (i, j)), the gradients of
    its barycentric coordinates (tets, 4, 3; 1/mm) and its volume (mm^3)."""

    element_nodes: np.ndarray
    layout: list[tuple[int, int]]
    lam_grad: np.ndarray
    volume: np.ndarray

    @staticmethod
    def of(space, vertices_mm: np.ndarray, tets: np.ndarray) -> TetGeometry:
        """``space``: the P1 or P2 warp.fem space of the mesh ``vertices_mm``, ``tets`` (positively oriented, as the
        solver keeps them)."""
        return TetGeometry(*element_node_layout(space, vertices_mm, tets), *barycentric_gradients(vertices_mm, tets))


@dataclass(frozen=True)
class VolumetricHessian:
    """What the tet-by-tet assembly needs, made once per mesh (``make``): each tet's coupled nodes and their basis
    gradients at the centroid (1/mm), its volume (mm^3), and where its blocks go in the summed matrix."""

    nodes: wp.array  # (tets, K) int: node indices (warp.fem space numbering)
    grads: wp.array  # (tets, K) vec3d
    volume: wp.array  # (tets,) float64
    targets: wp.array  # receiving blocks of the sum
    offsets: wp.array  # per receiving block, its range in ``sources``
    sources: wp.array  # indices into the per-tet blocks
    blocks: wp.array  # (tets K K) mat33d work space
    F_tet: wp.array  # (tets,) mat33d work space: F at the centroid, cof(F), s_h (``_tet_states``)
    cof_tet: wp.array
    s_tet: wp.array

    @staticmethod
    def make(geometry: TetGeometry, total: BsrMatrix, device) -> VolumetricHessian:
        """``geometry``: the mesh's tets (``TetGeometry.of``); ``total``: a matrix with the sum's sparsity (every pair
        of nodes of a tet)."""
        element_nodes, layout, lam_grad, volume = geometry.element_nodes, geometry.layout, geometry.lam_grad, \
            geometry.volume
        coupled = [local for local, (i, j) in enumerate(layout) if len(layout) == 4 or i != j]
        nodes = element_nodes[:, coupled]
        grads = np.stack([lam_grad[:, i] + (lam_grad[:, j] if j != i else 0.0) for i, j in
                          (layout[local] for local in coupled)], axis=1)
        K = nodes.shape[1]
        slot = _block_slots(total, np.repeat(nodes, K, axis=1).reshape(-1), np.tile(nodes, (1, K)).reshape(-1))
        order = np.argsort(slot, kind="stable")
        targets, counts = np.unique(slot[order], return_counts=True)

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=device)

        return VolumetricHessian(
            nodes=arr(nodes.astype(np.int32), int), grads=arr(grads, wp.vec3d), volume=arr(volume, wp.float64),
            targets=arr(targets.astype(np.int32), int),
            offsets=arr(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32), int),
            sources=arr(order.astype(np.int32), int), blocks=wp.empty(len(slot), dtype=wp.mat33d, device=device),
            F_tet=wp.empty(len(nodes), dtype=wp.mat33d, device=device),
            cof_tet=wp.empty(len(nodes), dtype=wp.mat33d, device=device),
            s_tet=wp.empty(len(nodes), dtype=wp.float64, device=device))

    def add_to(self, total: BsrMatrix, u: wp.array, params: wp.array, geometric: float, clamp: int,
               barrier_tets: wp.array) -> None:
        """Adds the volumetric Hessian at displacement ``u`` (dof values, mm) to ``total``'s blocks, in place."""
        device = total.values.device
        tets, K = self.nodes.shape
        wp.launch(_tet_states, dim=tets, device=device,
                  inputs=[u, self.nodes, self.grads, params, wp.float64(geometric), int(clamp), barrier_tets,
                          self.F_tet, self.cof_tet, self.s_tet])
        per_thread = 1 if device.is_cuda else K * K  # Warp's CPU runs the threads one after another
        wp.launch(_tet_blocks, dim=(tets, K * K // per_thread), device=device,
                  inputs=[self.grads, self.volume, params, self.F_tet, self.cof_tet, self.s_tet, per_thread,
                          self.blocks])
        wp.launch(_add_gathered, dim=len(self.targets), device=device,
                  inputs=[self.targets, self.offsets, self.sources, self.blocks, total.values])


def barycentric_gradients(vertices_mm: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the gradients of each tet's 4 barycentric coordinates, (tets, 4, 3), 1/mm; each tet's volume, mm^3)."""
    corners = vertices_mm[tets]  # (tets, 4, 3)
    edges = corners[:, 1:] - corners[:, :1]
    inverse = np.linalg.inv(edges.transpose(0, 2, 1))  # rows: gradients of barycentric coordinates 1-3
    return np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1), np.abs(np.linalg.det(edges)) / 6.0


def element_node_layout(space, vertices_mm: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """(each tet's nodes in the P1 or P2 warp.fem ``space``, (tets, 4 or 10); per local node (i, j): the vertex i of the
    tet where i = j, else the midpoint of its edge (i, j)), found by position in the first tet and checked in all."""
    element_nodes = space.topology.element_node_indices().numpy()
    X = space.node_positions().numpy()
    corners = vertices_mm[tets]  # (tets, 4, 3)
    count = element_nodes.shape[1]
    if count not in (4, 10):
        raise ValueError(f"expected P1 or P2 tets (4 or 10 nodes), got {count}")
    layout = []
    for x in X[element_nodes[0]]:
        found = [(i, j) for i in range(4) for j in range(i, 4) if np.allclose(x, 0.5 * (corners[0, i] + corners[0, j]))]
        if len(found) != 1:
            raise RuntimeError("unexpected node layout in the warp.fem space")
        layout.append(found[0])
    for local, (i, j) in enumerate(layout):  # the same local layout in every tet
        expected = 0.5 * (corners[:, i] + corners[:, j])
        if not np.allclose(X[element_nodes[:, local]], expected, atol=1e-9 * (1.0 + np.abs(vertices_mm).max())):
            raise RuntimeError("unexpected node layout in the warp.fem space")
    return element_nodes, layout


def _block_slots(total: BsrMatrix, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The indices among ``total``'s stored blocks of the blocks (rows[k], cols[k]) (block rows and columns); an error
    where one is not stored."""
    keys = block_keys(total)
    want = rows.astype(np.int64) * total.ncol + cols.astype(np.int64)
    slot = np.searchsorted(keys, want)
    if np.any(slot >= len(keys)) or np.any(keys[np.minimum(slot, len(keys) - 1)] != want):
        raise RuntimeError("a Hessian block lies outside the elements' sparsity")
    return slot
