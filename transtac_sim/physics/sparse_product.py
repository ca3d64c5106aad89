"""The Newton systems' matrix-vector product on the device: z = alpha A x + beta y for a 3x3-block CSR matrix.

The device CG (linear.py) spends most of its time in this product: on the press-and-slide Hessian (97k dofs, about
1.1M blocks of 3x3 float64, 80 MB) ``warp.sparse.bsr_mv`` took 123 us per call on an H100
(``scripts/fem_phase_profile.py --gpu-activity``, BENCHMARKS.md ``fem_spmv_gpu``), several times what reading the
blocks once costs. Warp's kernel gives each thread one scalar row and walks its blocks: neighbouring threads read
24-byte pieces of blocks 72 bytes apart, and a row's ~35 blocks are read one after another by one thread.

Here a group of ``LANES`` threads (one warp) shares one block row: lane l takes blocks l, l + LANES, ... of the
row, so the warp reads consecutive whole blocks (coalesced), and the lanes' 3-vectors are summed with a tile
reduction: 40 us per call on the same matrix. Same arithmetic per block, another order of summation (results differ
from ``bsr_mv`` by round-off). The stride is ``wp.block_dim()``, not ``LANES``: on the CPU Warp runs a group with
fewer threads.

With ``single_precision`` the product reads a copy of the blocks rounded to float32 (40 instead of 80 MB per product
on press_slide) and does its arithmetic in float64: the device CG's matrix (linear.py). The rounding perturbs each
entry by at most 2^-24 of itself, and CG then solves the rounded system: its float64 relative residual can exceed
the tolerance by up to about the condition number times 2^-24. That changes Newton's step, not its solution, which the float64 gradient decides; on press_slide the frames' markers
agree with the float64 matrix's within the spread of two float64 runs (BENCHMARKS.md ``fem_cg_float32_gpu``). The
deviatoric term's product (energies and gradients, assembly.py) stays float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp
from warp.optim.linear import LinearOperator
from warp.sparse import BsrMatrix

LANES = 32  # threads per block row: one warp


@wp.func
def block_row_range(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), row: int):
    """(first, end) of block row ``row``'s blocks in a BSR matrix's ``columns`` and ``values``."""
    begin = offsets[row]
    end = offsets[row + 1]
    if row_counts:
        end = begin + row_counts[row]
    return wp.vec2i(begin, end)


@wp.func
def diagonal_block(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                   row: int):
    """The index of block row ``row``'s diagonal block among a BSR matrix's blocks, or -1 where it has none."""
    blocks_of_row = block_row_range(offsets, row_counts, row)
    for k in range(blocks_of_row[0], blocks_of_row[1]):
        if columns[k] == row:
            return k
    return -1


@wp.kernel(enable_backward=False)
def _block_row_product(
    offsets: wp.array(dtype=int),
    row_counts: wp.array(dtype=int),
    columns: wp.array(dtype=int),
    blocks: wp.array(dtype=Any),
    x: wp.array(dtype=wp.vec3d),
    alpha: wp.float64,
    y: wp.array(dtype=wp.vec3d),
    beta: wp.float64,
    z: wp.array(dtype=wp.vec3d),
):
    row, lane = wp.tid()
    blocks_of_row = block_row_range(offsets, row_counts, row)
    partial = wp.vec3d()
    for k in range(blocks_of_row[0] + lane, blocks_of_row[1], wp.block_dim()):
        partial += wp.mat33d(blocks[k]) * x[columns[k]]
    total = wp.tile_sum(wp.tile(partial, preserve_type=True))
    if lane == 0:
        value = alpha * total[0]
        if beta != wp.float64(0.0):
            value += beta * y[row]
        z[row] = value


@wp.kernel(enable_backward=False)
def _round_to_float32(blocks: wp.array(dtype=wp.mat33d), rounded: wp.array(dtype=wp.mat33f)):
    k = wp.tid()
    rounded[k] = wp.mat33f(blocks[k])


def block_row_operator(A: BsrMatrix, single_precision: bool = False,
                       rounded: wp.array | None = None) -> LinearOperator:
    """``A`` (3x3 float64 blocks) as a ``warp.optim.linear`` operator whose product is ``_block_row_product``;
    graph-capturable (one launch, no allocation). ``single_precision``: the product reads A's blocks rounded to float32,
    copied here into ``rounded`` where it is given and large enough (later changes to A are not seen). The operator's
    ``graph_key`` names the arrays its product reads (definite_cg.py reuses a graph captured with the same ones)."""
    if A.block_shape != (3, 3) or A.scalar_type != wp.float64:
        raise ValueError(f"expected 3x3 float64 blocks, got {A.block_shape} {A.scalar_type}")
    blocks = A.values
    if single_precision:
        if rounded is not None and len(rounded) < len(A.values):
            raise ValueError(f"float32 buffer of {len(rounded)} blocks for a matrix of {len(A.values)}")
        blocks = rounded if rounded is not None else wp.empty(len(A.values), dtype=wp.mat33f, device=A.device)
        wp.launch(_round_to_float32, dim=len(A.values), device=A.device, inputs=[A.values, blocks])

    def matvec(x, y, z, alpha, beta):
        wp.launch_tiled(_block_row_product, dim=[A.nrow], block_dim=LANES, device=A.device,
                        inputs=[A.offsets, A.row_counts, A.columns, blocks, x, wp.float64(alpha), y,
                                wp.float64(beta), z])

    operator = LinearOperator(A.shape, A.scalar_type, A.device, matvec)
    row_counts = A.row_counts.ptr if A.row_counts is not None else None
    operator.graph_key = (A.nrow, A.offsets.ptr, row_counts, A.columns.ptr, blocks.ptr)
    return operator


SLICE_ROWS = 32  # block rows per slice of the sliced layout (a warp's worth of rows)
SORT_WINDOW = 4096  # block rows sorted by their block count within windows of this many (less padding, rows kept near)


@dataclass
class SlicedLayout:
    """A 3x3-block CSR sparsity re-laid out in slices of ``SLICE_ROWS`` block rows (sliced ELLPACK, rows sorted by
    their block count within windows of ``SORT_WINDOW`` rows, SELL-C-sigma): the row at position q = s * SLICE_ROWS + r
    is ``row_at[q]`` (-1 past the last row), and slot ``slice_start[s] + j * SLICE_ROWS + r`` holds its block j
    (``columns`` -1 where it has fewer blocks than the slice's ``width``), so the threads of neighbouring positions read
    neighbouring blocks at each step. ``source``/``target``: each stored CSR block's index and its slot."""

    key: tuple
    positions: int
    row_at: wp.array
    source: wp.array
    target: wp.array
    columns: wp.array
    slice_start: wp.array
    width: wp.array
    blocks: wp.array  # mat33f per slot, 0 on the padding


def sliced_layout(A: BsrMatrix) -> SlicedLayout:
    """The sliced layout of A's sparsity (host work, once per sparsity) with a float32 block buffer."""
    offsets = A.offsets.numpy()
    counts = A.row_counts.numpy() if A.row_counts else np.diff(offsets)
    nrow = A.nrow
    slices = -(-nrow // SLICE_ROWS)
    order = np.concatenate([w + np.argsort(-counts[w:w + SORT_WINDOW], kind="stable")
                            for w in range(0, nrow, SORT_WINDOW)]).astype(np.int64)
    position = np.empty(nrow, dtype=np.int64)
    position[order] = np.arange(nrow)
    row_at = np.full(slices * SLICE_ROWS, -1, dtype=np.int64)
    row_at[:nrow] = order
    padded = np.zeros(slices * SLICE_ROWS, dtype=np.int64)
    padded[:nrow] = counts[order]
    width = padded.reshape(slices, SLICE_ROWS).max(axis=1)
    slice_start = np.concatenate([[0], np.cumsum(width * SLICE_ROWS)])
    rows = np.repeat(np.arange(nrow), counts)
    j = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    source = np.repeat(offsets[:-1], counts) + j
    q = position[rows]
    target = slice_start[q // SLICE_ROWS] + j * SLICE_ROWS + q % SLICE_ROWS
    columns = np.full(slice_start[-1], -1, dtype=np.int32)
    columns[target] = A.columns.numpy()[source]
    device = A.device

    def ints(a):
        return wp.array(np.asarray(a, dtype=np.int32), dtype=int, device=device)

    return SlicedLayout(_sparsity_key(A), len(row_at), ints(row_at), ints(source), ints(target), ints(columns),
                        ints(slice_start[:-1]), ints(width),
                        wp.zeros(int(slice_start[-1]), dtype=wp.mat33f, device=device))


def _sparsity_key(A: BsrMatrix) -> tuple:
    return (A.nrow, A.offsets.ptr, A.row_counts.ptr if A.row_counts is not None else None, A.columns.ptr)


@wp.kernel(enable_backward=False)
def _scatter_rounded(values: wp.array(dtype=wp.mat33d), source: wp.array(dtype=int), target: wp.array(dtype=int),
                     blocks: wp.array(dtype=wp.mat33f)):
    t = wp.tid()
    blocks[target[t]] = wp.mat33f(values[source[t]])


@wp.kernel(enable_backward=False)
def _sliced_product(row_at: wp.array(dtype=int), slice_start: wp.array(dtype=int), width: wp.array(dtype=int),
                    columns: wp.array(dtype=int), blocks: wp.array(dtype=wp.mat33f), x: wp.array(dtype=wp.vec3d),
                    alpha: wp.float64, y: wp.array(dtype=wp.vec3d), beta: wp.float64, z: wp.array(dtype=wp.vec3d)):
    """One thread per (position, component): z[row][c] = alpha (A x)[row][c] + beta y[row][c], row = row_at[position]."""
    i = wp.tid()
    q = i // 3
    c = i - 3 * q
    row = row_at[q]
    if row < 0:
        return
    s = q // SLICE_ROWS
    base = slice_start[s] + q - SLICE_ROWS * s
    total = wp.float64(0.0)
    for j in range(width[s]):
        p = base + j * SLICE_ROWS
        col = columns[p]
        if col >= 0:
            b = blocks[p]
            v = x[col]
            total += wp.float64(b[c, 0]) * v[0] + wp.float64(b[c, 1]) * v[1] + wp.float64(b[c, 2]) * v[2]
    value = alpha * total
    if beta != wp.float64(0.0):
        value += beta * y[row][c]
    z[row][c] = value


def sliced_operator(A: BsrMatrix, layout: SlicedLayout | None = None) -> LinearOperator:
    """``A`` rounded to float32 in the sliced layout (``layout``, made here where not given or of another sparsity),
    as a ``warp.optim.linear`` operator (float64 arithmetic, as ``block_row_operator(single_precision=True)``)."""
    if layout is None or layout.key != _sparsity_key(A):
        layout = sliced_layout(A)
    wp.launch(_scatter_rounded, dim=len(layout.source), device=A.device,
              inputs=[A.values, layout.source, layout.target, layout.blocks])

    def matvec(x, y, z, alpha, beta):
        wp.launch(_sliced_product, dim=3 * layout.positions, device=A.device,
                  inputs=[layout.row_at, layout.slice_start, layout.width, layout.columns, layout.blocks, x,
                          wp.float64(alpha), y, wp.float64(beta), z])

    operator = LinearOperator(A.shape, A.scalar_type, A.device, matvec)
    operator.graph_key = (*layout.key, layout.blocks.ptr)
    operator.layout = layout
    return operator
