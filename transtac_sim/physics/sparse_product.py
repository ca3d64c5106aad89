"""The Newton systems' matrix-vector product on the device, z = alpha A x + beta y for a 3x3-block CSR matrix, the
block-Jacobi preconditioner of such a matrix (``BlockJacobi``, the device CG's: definite_cg.py), and its blocks' keys
(``block_keys``: where the summed Hessian's parts go, hessian_assembly.py and volumetric_hessian.py).

The device CG (device_linear.py) spends most of its time in this product: on the press-and-slide Hessian (97k dofs, about
1.1M blocks of 3x3 float64, 80 MB) ``warp.sparse.bsr_mv`` took 123 us per call on an H100
(``scripts/fem_phase_profile.py --gpu-activity``, BENCHMARKS.md ``fem_spmv_gpu``), several times what reading the
blocks once costs. Warp's kernel gives each thread one scalar row and walks its blocks: neighbouring threads read
24-byte pieces of blocks 72 bytes apart, and a row's ~27 blocks are read one after another by one thread.

Here ``ROW_LANES`` threads share one block row: lane l takes blocks l, l + ROW_LANES, ... of the row, so they read
consecutive whole blocks (coalesced), and the lanes' 3-vectors are summed with a tile reduction; a thread block holds
``ROWS_PER_GROUP`` rows (``_block_rows_product``). With one 32-thread block per row (40 us per call on the same matrix,
23.6 us on its float32 copy) an SM held only half the threads it can (at most 32 resident thread blocks) and a row's
~27 blocks left many of its 32 lanes idle; 8 rows of 16 lanes in 128 threads take 17.9 us on the float32 copy (H100,
50 launches replayed in a graph; scripts/bench_cg_kernels.py, BENCHMARKS.md ``fem_cg_unrolled_gpu``). Same
arithmetic per block, another order of summation (results differ from ``bsr_mv`` by round-off). On the CPU, where Warp
runs a thread group as one thread, ``_block_row_product`` takes one row per group.

With ``single_precision`` the product reads a copy of the blocks rounded to float32 (40 instead of 80 MB per product
on press_slide) and does its arithmetic in float64: the device CG's matrix (device_linear.py). The rounding perturbs each
entry by at most 2^-24 of itself, and CG then solves the rounded system: its float64 relative residual can exceed
the tolerance by up to about the condition number times 2^-24. That changes Newton's step, not its solution, which
the float64 gradient decides; on press_slide the frames' markers agree with the float64 matrix's within the spread
of two float64 runs (BENCHMARKS.md ``fem_cg_float32_gpu``). The deviatoric term's product (energies and gradients,
assembly.py) stays float64.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp
from warp.optim.linear import LinearOperator
from warp.sparse import BsrMatrix

ROWS_PER_GROUP = wp.constant(8)  # block rows per thread block of the CUDA product
ROW_LANES = wp.constant(16)  # threads per block row there
GROUP_THREADS = wp.constant(8 * 16)  # ROWS_PER_GROUP * ROW_LANES (a tile's shape takes a constant, not a product)


@wp.func
def block_row_range(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), row: int):
    """(first, end) of block row ``row``'s blocks in a BSR matrix's ``columns`` and ``values``."""
    begin = offsets[row]
    end = offsets[row + 1]
    if row_counts:
        end = begin + row_counts[row]
    return wp.vec2i(begin, end)


@wp.func
def block_index(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                row: int, col: int):
    """The index of block (``row``, ``col``) among a BSR matrix's blocks, or -1 where it is not stored."""
    blocks_of_row = block_row_range(offsets, row_counts, row)
    for k in range(blocks_of_row[0], blocks_of_row[1]):
        if columns[k] == col:
            return k
    return -1


@wp.func
def diagonal_block(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                   row: int):
    """The index of block row ``row``'s diagonal block among a BSR matrix's blocks, or -1 where it has none."""
    return block_index(offsets, row_counts, columns, row, row)


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
    """z = alpha A x + beta y, one block row per thread group (the CPU's: Warp runs a group as one thread there)."""
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


@wp.kernel(enable_backward=False, module="unique")  # its own module: its tiles are sized for its launch's block
def _block_rows_product(
    offsets: wp.array(dtype=int),
    row_counts: wp.array(dtype=int),
    columns: wp.array(dtype=int),
    blocks: wp.array(dtype=Any),
    x: wp.array(dtype=wp.vec3d),
    alpha: wp.float64,
    y: wp.array(dtype=wp.vec3d),
    beta: wp.float64,
    z: wp.array(dtype=wp.vec3d),
    rows: int,
):
    """z = alpha A x + beta y for A's ``rows`` block rows (its ``offsets`` may be longer), ``ROWS_PER_GROUP`` of them
    per thread group of ``ROWS_PER_GROUP * ROW_LANES`` threads, ``ROW_LANES`` per row (CUDA); the lanes' sums are
    reduced row by row from shared memory."""
    group, lane = wp.tid()
    row = group * ROWS_PER_GROUP + lane // ROW_LANES
    inside = row < rows
    partial = wp.vec3d()
    if inside:
        blocks_of_row = block_row_range(offsets, row_counts, row)
        for k in range(blocks_of_row[0] + lane % ROW_LANES, blocks_of_row[1], ROW_LANES):
            partial += wp.mat33d(blocks[k]) * x[columns[k]]
    lanes = wp.tile_empty(shape=GROUP_THREADS, dtype=wp.vec3d, storage="shared")
    wp.tile_assign(lanes, wp.tile(partial, preserve_type=True))
    sums = wp.tile_sum(wp.tile_reshape(lanes, shape=(ROWS_PER_GROUP, ROW_LANES)), axis=1)
    total = sums[lane // ROW_LANES]
    if inside and lane % ROW_LANES == 0:
        value = alpha * total
        if beta != wp.float64(0.0):
            value += beta * y[row]
        z[row] = value


@wp.kernel(enable_backward=False)
def _round_to_float32(entries: wp.array(dtype=wp.float64), rounded: wp.array(dtype=wp.float32)):
    """The blocks' entries rounded to float32, one thread per entry (both arrays flat views of the blocks, so that the
    loads and stores are coalesced): on press_slide's Newton systems on an H100 0.49-0.52x the time of one thread per
    mat33d block (BENCHMARKS.md ``fem_cg_fused_gpu``)."""
    i = wp.tid()
    rounded[i] = wp.float32(entries[i])


def _check_float32_buffer(A: BsrMatrix, rounded: wp.array) -> None:
    if len(rounded) < len(A.values):
        raise ValueError(f"float32 buffer of {len(rounded)} blocks for a matrix of {len(A.values)}")


def round_to_float32(A: BsrMatrix, rounded: wp.array) -> None:
    """A's blocks rounded to float32 into ``rounded`` (mat33f, at least as many blocks as A.values; launch only)."""
    _check_float32_buffer(A, rounded)
    wp.launch(_round_to_float32, dim=9 * len(A.values), device=A.device,
              inputs=[A.values.view(wp.float64).flatten(), rounded.view(wp.float32).flatten()])


def block_row_operator(A: BsrMatrix, single_precision: bool = False, rounded: wp.array | None = None,
                       round_now: bool = True) -> LinearOperator:
    """``A`` (3x3 float64 blocks) as a ``warp.optim.linear`` operator whose product is ``_block_row_product``;
    graph-capturable (one launch, no allocation). ``single_precision``: the product reads A's blocks rounded to float32,
    copied here into ``rounded`` where it is given (``round_to_float32``; later changes to A are not seen), or, with
    ``round_now`` False, already copied there by the caller. The operator's ``graph_key`` names the arrays its product
    reads (definite_cg.py reuses a graph captured with the same ones)."""
    if A.block_shape != (3, 3) or A.scalar_type != wp.float64:
        raise ValueError(f"expected 3x3 float64 blocks, got {A.block_shape} {A.scalar_type}")
    blocks = A.values
    if single_precision:
        if rounded is None and not round_now:
            raise ValueError("round_now=False needs the rounded blocks")
        blocks = rounded if rounded is not None else wp.empty(len(A.values), dtype=wp.mat33f, device=A.device)
        _check_float32_buffer(A, blocks)
        if round_now:
            round_to_float32(A, blocks)

    if A.device.is_cuda:
        kernel, groups, threads, rows = (_block_rows_product, (A.nrow + ROWS_PER_GROUP - 1) // ROWS_PER_GROUP,
                                         GROUP_THREADS, [A.nrow])
    else:
        kernel, groups, threads, rows = _block_row_product, A.nrow, 32, []

    def matvec(x, y, z, alpha, beta):
        wp.launch_tiled(kernel, dim=[groups], block_dim=threads, device=A.device,
                        inputs=[A.offsets, A.row_counts, A.columns, blocks, x, wp.float64(alpha), y,
                                wp.float64(beta), z, *rows])

    operator = LinearOperator(A.shape, A.scalar_type, A.device, matvec)
    row_counts = A.row_counts.ptr if A.row_counts is not None else None
    operator.graph_key = (A.nrow, A.offsets.ptr, row_counts, A.columns.ptr, blocks.ptr)
    return operator


@wp.kernel(enable_backward=False)
def _inverse_diagonal(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                      blocks: wp.array(dtype=wp.mat33d), inverse: wp.array(dtype=wp.mat33d)):
    row = wp.tid()
    k = diagonal_block(offsets, row_counts, columns, row)
    if k >= 0:
        inverse[row] = wp.inverse(blocks[k])
    else:  # a row without a diagonal block: not preconditioned
        inverse[row] = wp.identity(n=3, dtype=wp.float64)


@wp.kernel(enable_backward=False)
def _apply_blocks(inverse: wp.array(dtype=wp.mat33d), x: wp.array(dtype=wp.vec3d), y: wp.array(dtype=wp.vec3d),
                  z: wp.array(dtype=wp.vec3d), alpha: wp.float64, beta: wp.float64):
    i = wp.tid()
    value = alpha * (inverse[i] * x[i])
    if beta != wp.float64(0.0):
        value += beta * y[i]
    z[i] = value


def invert_diagonal(A: BsrMatrix, inverse: wp.array) -> None:
    """The inverses of A's 3x3 diagonal blocks into ``inverse`` (one per block row; launch only)."""
    wp.launch(_inverse_diagonal, dim=A.nrow, device=A.device,
              inputs=[A.offsets, A.row_counts, A.columns, A.values, inverse])


class BlockJacobi(LinearOperator):
    """The block-Jacobi preconditioner of a 3x3-block matrix: the inverses of its diagonal blocks
    (``inverse_blocks``, written into ``inverse`` where given, or, with ``invert_now`` False, already written there by
    the caller with ``invert_diagonal``), usable as a ``warp.optim.linear`` operator too."""

    def __init__(self, A: BsrMatrix, inverse: wp.array | None = None, invert_now: bool = True):
        if inverse is None and not invert_now:
            raise ValueError("invert_now=False needs the inverse blocks")
        self.inverse_blocks = inverse if inverse is not None else wp.empty(A.nrow, dtype=wp.mat33d, device=A.device)
        if invert_now:
            invert_diagonal(A, self.inverse_blocks)

        def matvec(x, y, z, alpha, beta):
            wp.launch(_apply_blocks, dim=A.nrow, device=A.device,
                      inputs=[self.inverse_blocks, x, y, z, wp.float64(alpha), wp.float64(beta)])

        super().__init__(A.shape, A.scalar_type, A.device, matvec)


def block_keys(M: BsrMatrix) -> np.ndarray:
    """row * ncol + column of each block of M, in storage order (read back from M's device)."""
    offsets = M.offsets.numpy()
    rows = np.repeat(np.arange(M.nrow, dtype=np.int64), np.diff(offsets))
    return rows * M.ncol + M.columns.numpy()[:offsets[-1]]
