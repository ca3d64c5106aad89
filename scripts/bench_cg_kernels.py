"""What one iteration of the device CG costs, kernel by kernel, on a scene's last converged Newton system (CUDA).

    .venv/bin/python scripts/bench_cg_kernels.py [scenes/press_slide.toml] [--frames 6]

Runs the scene's first frames on the GPU, keeps the last Newton system the device CG solved (physics/device_linear.py),
then:

1. each kernel of a CG iteration (physics/cg_kernels.py, coarse_space.py, sparse_product.py) launched 50 times in a
   CUDA graph, the graph replayed 20 times: microseconds per launch, back to back on the GPU. The matrix-vector
   product both ways: one 32-thread group per block row (``_block_row_product``, the CUDA product before
   BENCHMARKS.md ``fem_cg_unrolled_gpu``, and the CPU's) and the CUDA one (``_block_rows_product``: 8 rows of 16
   lanes per group), and two layouts the solver does not use, each checked against the library's product first: the
   float32 blocks stored entry by entry (9 arrays, so that each of a row's 9 loads is one coalesced run) and the
   vector gathered from a float32 copy (half the bytes per gathered entry), then both; then the other kernels and
   one whole iteration as captured (all with the state's set 0, which stays going on);
2. the system solved from 0 at Newton's forcing tolerance (1e-2) and the tight one (1e-4) with each product and 3
   and 6 iterations per pass of the CG's conditional graph loop (``definite_cg.UNROLL``, a multiple of the state's 3
   sets; 1, 2 and 4 before BENCHMARKS.md ``fem_cg_fused_gpu``): iterations and the best of three solves after a first
   one (which captures the graph); ``--rounds N`` runs these settings in turn N times.

Prints markdown tables. The machine's other load shows in the per-launch times; compare rows of one run.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer
import warp as wp
from warp.optim.linear import LinearOperator

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import cg_kernels, definite_cg, device_linear, sparse_product
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames

REPO = Path(__file__).resolve().parents[1]


def _last_system(scene: Path, frames: int, device: str = "cuda") -> dict:
    """Runs ``frames`` frames of the scene on ``device`` (device CG) and returns the last system the CG solved: the
    projected Hessian H, its right-hand side and the solver's kept device work (``DeviceWork``, ``_last_cg``)."""
    kept: dict = {}
    solve_cg = device_linear.DeviceSolves._solve_cg

    def keeping(self, H, rhs, rtol, exact_below, coarse_from_this=True, **kwargs):
        x = solve_cg(self, H, rhs, rtol, exact_below, coarse_from_this, **kwargs)
        if x is not None:
            kept.update(H=H, rhs=wp.clone(rhs), linear=self)
        return x

    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": device, "linear_solver": "cg"})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    device_linear.DeviceSolves._solve_cg = keeping
    try:
        for f in simulate_frames(setup, frames, StageClock()):
            print(f"frame {f.frame}: {f.solver['iterations']} Newton iterations", flush=True)
    finally:
        device_linear.DeviceSolves._solve_cg = solve_cg
    if not kept:
        raise typer.BadParameter(f"{scene}: no Newton system was solved on the device in {frames} frame(s)")
    return kept


def _per_launch_us(launch, device, launches: int = 50, replays: int = 20) -> float:
    """Microseconds per call of ``launch`` (graph-capturable), ``launches`` calls captured in one graph, replayed."""
    launch()
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        for _ in range(launches):
            launch()
    wp.capture_launch(capture.graph)
    wp.synchronize_device(device)
    start = time.perf_counter()
    for _ in range(replays):
        wp.capture_launch(capture.graph)
    wp.synchronize_device(device)
    return 1e6 * (time.perf_counter() - start) / (launches * replays)


def _row_per_group_operator(H, blocks) -> LinearOperator:
    """The product with one 32-thread group per block row on the same float32 blocks (``_block_row_product``)."""
    def matvec(x, y, z, alpha, beta):
        wp.launch_tiled(sparse_product._block_row_product, dim=[H.nrow], block_dim=32, device=H.device,
                        inputs=[H.offsets, H.row_counts, H.columns, blocks, x, wp.float64(alpha), y,
                                wp.float64(beta), z])

    operator = LinearOperator(H.shape, H.scalar_type, H.device, matvec)
    operator.graph_key = ("one row per group", H.nrow, blocks.ptr)
    return operator


@wp.kernel(enable_backward=False)
def _split_entries(blocks: wp.array(dtype=wp.mat33f), entries: wp.array2d(dtype=wp.float32)):
    """entries[3 i + j, k] = blocks[k][i, j]: the float32 blocks stored entry by entry."""
    k = wp.tid()
    B = blocks[k]
    for i in range(3):
        for j in range(3):
            entries[3 * i + j, k] = B[i, j]


@wp.func
def _block_times(blocks: wp.array(dtype=wp.mat33f), k: int, x: wp.vec3d):
    """Block k of the float32 blocks times x, in float64."""
    return wp.mat33d(blocks[k]) * x


@wp.func
def _block_times(entries: wp.array2d(dtype=wp.float32), k: int, x: wp.vec3d):  # noqa: F811 (a Warp overload)
    """Block k of the blocks stored entry by entry (entries[3 i + j, k]) times x, in float64."""
    return wp.vec3d(
        wp.float64(entries[0, k]) * x[0] + wp.float64(entries[1, k]) * x[1] + wp.float64(entries[2, k]) * x[2],
        wp.float64(entries[3, k]) * x[0] + wp.float64(entries[4, k]) * x[1] + wp.float64(entries[5, k]) * x[2],
        wp.float64(entries[6, k]) * x[0] + wp.float64(entries[7, k]) * x[1] + wp.float64(entries[8, k]) * x[2])


@wp.kernel(enable_backward=False, module="unique")
def _layout_rows_product(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                         matrix: Any, x: wp.array(dtype=Any), z: wp.array(dtype=wp.vec3d), rows: int):
    """z = A x as ``sparse_product._block_rows_product`` (8 rows of 16 lanes per group) on A's float32 blocks as
    ``matrix`` stores them (``_block_times``: one mat33f per block, or entry by entry, so that each of the 9 loads of a
    row's 16 lanes is one coalesced run), gathering x as given (vec3d, or a vec3f copy)."""
    group, lane = wp.tid()
    row = group * sparse_product.ROWS_PER_GROUP + lane // sparse_product.ROW_LANES
    inside = row < rows
    partial = wp.vec3d()
    if inside:
        blocks_of_row = sparse_product.block_row_range(offsets, row_counts, row)
        for k in range(blocks_of_row[0] + lane % sparse_product.ROW_LANES, blocks_of_row[1], sparse_product.ROW_LANES):
            partial += _block_times(matrix, k, wp.vec3d(x[columns[k]]))
    lanes = wp.tile_empty(shape=sparse_product.GROUP_THREADS, dtype=wp.vec3d, storage="shared")
    wp.tile_assign(lanes, wp.tile(partial, preserve_type=True))
    sums = wp.tile_sum(wp.tile_reshape(lanes, shape=(sparse_product.ROWS_PER_GROUP, sparse_product.ROW_LANES)), axis=1)
    total = sums[lane // sparse_product.ROW_LANES]
    if inside and lane % sparse_product.ROW_LANES == 0:
        z[row] = total


def _layout_products(H, blocks, p) -> tuple[dict, wp.array]:
    """Launches of the experimental product layouts (not the solver's) on H's float32 ``blocks``, for z = A p, and
    the array they write z into."""
    entries = wp.empty((9, H.nnz), dtype=wp.float32, device=H.device)
    wp.launch(_split_entries, dim=H.nnz, device=H.device, inputs=[blocks, entries])
    p32 = wp.array(p.numpy().astype(np.float32), dtype=wp.vec3f, device=H.device)
    out = wp.empty_like(p)
    groups = (H.nrow + sparse_product.ROWS_PER_GROUP - 1) // sparse_product.ROWS_PER_GROUP
    structure = [H.offsets, H.row_counts, H.columns]

    def launch(matrix, vector):
        return lambda: wp.launch_tiled(_layout_rows_product, dim=[groups], block_dim=sparse_product.GROUP_THREADS,
                                       device=H.device, inputs=[*structure, matrix, vector, out, H.nrow])

    return {"product, blocks entry by entry (experimental)": launch(entries, p),
            "product, float32 copy of the vector (experimental)": launch(blocks, p32),
            "product, both (experimental)": launch(entries, p32)}, out


def main(scene: Path = typer.Argument(REPO / "scenes" / "press_slide.toml"), frames: int = typer.Option(6, min=2),
         rounds: int = typer.Option(1, min=1, help="times the solve table's settings are run in turn")):
    if not wp.get_cuda_device_count():
        raise typer.BadParameter("needs a CUDA device")
    kept = _last_system(scene, frames)
    H, linear = kept["H"], kept["linear"]
    work, device, n = linear._work, H.device, H.nrow
    A, M = linear._last_cg  # the library's product on the float32 blocks, and block-Jacobi
    coarse = work.coarse if work.coarse is not None and work.coarse.ready else None
    products = {"one row per 32-thread group": _row_per_group_operator(H, work.rounded), "8 rows of 16 lanes": A}
    print(f"\n{scene}, frame {frames - 1}'s last system on {wp.get_device(device).name}: {n} block rows, {H.nnz} blocks, "
          f"coarse unknowns {coarse.size if coarse else 0}\n")

    ws = work.cg
    p, q, r, z = ws.p, ws.q, ws.r, ws.z
    for v in (p, r, z):
        wp.copy(v, kept["rhs"])
    x = wp.clone(kept["rhs"])
    A.matvec(p, q, q, 1.0, 0.0)
    state = ws.state
    # set 0 going on, its r . z positive, p . q = 1e300 and the previous set's r . z 1e150: every kernel does its work
    # (alpha = 1e-150 and beta = r . z / 1e150 keep the vectors' sizes over the repeated launches)
    values = np.zeros(cg_kernels.STATE_SIZE)
    values[[cg_kernels.ACTIVE, cg_kernels.PQ, cg_kernels.RZ, 2 * cg_kernels.SET_SIZE + cg_kernels.RZ,
            cg_kernels.MAXITER]] = (1.0, 1e300, 1.0, 1e150, 1e9)
    state.assign(values)

    def step_precondition():  # set 0, as the first iteration of a pass
        cg_kernels.launch_step_precondition(ws, 0, x, M.inverse_blocks, coarse)

    def coarse_product():
        coarse.apply_inverse(state, cg_kernels.RZ)

    def step_p():
        cg_kernels.launch_p_update(ws, 0, coarse, first=False)

    def iteration():
        A.matvec(p, q, q, 1.0, 0.0)
        cg_kernels.add_dot(p, q, state, cg_kernels.PQ)
        step_precondition()
        if coarse:
            coarse_product()
        step_p()

    kernels = {f"product, {name}": (lambda op=op: op.matvec(p, q, q, 1.0, 0.0)) for name, op in products.items()}
    layouts, layout_out = _layout_products(H, work.rounded, p)
    A.matvec(p, q, q, 1.0, 0.0)
    for name, launch in layouts.items():  # each against the library's product
        launch()
        print(f"{name}: largest difference from the library's product {np.abs(layout_out.numpy() - q.numpy()).max():.2e}"
              f" (its largest entry {np.abs(q.numpy()).max():.2e})")
    kernels |= layouts
    kernels |= {"p . q": lambda: cg_kernels.add_dot(p, q, state, cg_kernels.PQ),
                "x, r update, z = M r, r . z, abs(r)^2" + (", P^T r" if coarse else ""): step_precondition}
    if coarse:
        kernels |= {"coarse: A_c^-1 P^T r": coarse_product}
    kernels |= {"p update and stop test": step_p, "one whole iteration (8 rows of 16 lanes)": iteration}
    print("| kernel | us per launch |\n|---|---|")
    for name, launch in kernels.items():
        print(f"| {name} | {_per_launch_us(launch, device):.1f} |", flush=True)

    print("\n| round | product | iterations per loop pass | rtol | CG iterations | ms per solve | us per iteration |")
    print("|---|---|---|---|---|---|---|")
    unroll = definite_cg.UNROLL
    try:
        for round_, passes in ((k, passes) for k in range(1, rounds + 1) for passes in (3, 6)):
            definite_cg.UNROLL = passes
            for name, op in products.items():
                workspace = cg_kernels.CgWorkspace(n, device)
                for rtol in (1e-2, 1e-4):
                    seconds = []
                    for _ in range(4):
                        x.zero_()
                        wp.synchronize_device(device)
                        start = time.perf_counter()
                        result = definite_cg.definite_cg(op, kept["rhs"], x, rtol, 5000, M, workspace=workspace,
                                                         coarse=coarse)
                        wp.synchronize_device(device)
                        seconds.append(time.perf_counter() - start)
                    best = min(seconds[1:])
                    print(f"| {round_} | {name} | {passes} | {rtol:g} | {result.iterations} | {1e3 * best:.2f} | "
                          f"{1e6 * best / max(result.iterations, 1):.1f} |", flush=True)
    finally:
        definite_cg.UNROLL = unroll


if __name__ == "__main__":
    typer.run(main)
