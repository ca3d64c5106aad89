"""What an iteration of a batched device CG would cost: K copies of a scene's last Newton system in one block-diagonal
system (CUDA by default).

    .venv/bin/python scripts/bench_cg_batched.py [scenes/press_slide.toml] [--frames 6] [--batches 1,2,4,8]

Issue 12 asks for several sequences solved in one batched solve, so that small meshes fill the GPU. The Newton systems
of a batch of K sequences are one block-diagonal system, which the device CG (physics/definite_cg.py) solves as it
solves one: each iteration launches the same kernels over K times the rows. This script runs the scene's first frames
on the device (scripts/bench_cg_kernels.py ``_last_system``), stacks its last Newton system K times (``stacked``) and
solves it from 0 at Newton's forcing tolerance (1e-2) and the tight one (1e-4) with block-Jacobi (the coarse level is
left out for every K, so that the rows compare like with like): iterations, and the best of three solves after a
first one that captures the graph. The copies are one system K times over, so the batch takes the iterations of one.

The other side of the trade: in lockstep a batch's frame takes its slowest sequence's Newton iterations
(``scripts/bench_generate.py --summarize``: ``lockstep_ratio``). A batched solver does fewer GPU seconds per Newton
system than K separate solves where K t(1) / t(K) here exceeds that ratio. Prints a markdown table.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import typer
import warp as wp
from warp.sparse import BsrMatrix, bsr_from_triplets

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cg_kernels import _last_system  # noqa: E402

from transtac_sim.physics import cg_kernels, definite_cg, sparse_product  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def stacked(H: BsrMatrix, copies: int) -> BsrMatrix:
    """The block-diagonal matrix diag(H, ..., H) of ``copies`` copies of H (square, 3x3 blocks), on H's device."""
    nnz = int(H.offsets.numpy()[-1])
    rows = np.repeat(np.arange(H.nrow), np.diff(H.offsets.numpy()))
    columns = H.columns.numpy()[:nnz]
    shift = np.repeat(np.arange(copies) * H.nrow, nnz)
    device = H.device
    return bsr_from_triplets(copies * H.nrow, copies * H.ncol,
                             wp.array(np.tile(rows, copies) + shift, dtype=int, device=device),
                             wp.array(np.tile(columns, copies) + shift, dtype=int, device=device),
                             wp.array(np.tile(H.values.numpy()[:nnz], (copies, 1, 1)), dtype=H.values.dtype,
                                      device=device),
                             prune_numerical_zeros=False)


def main(scene: Path = typer.Argument(REPO / "scenes" / "press_slide.toml"), frames: int = typer.Option(6, min=2),
         batches: str = typer.Option("1,2,4,8", help="numbers of copies K, comma-separated"),
         device: str = typer.Option("cuda", help="cuda (what the question is about), or cpu to try the script")):
    sizes = [int(k) for k in batches.split(",")]
    if min(sizes) < 1 or sizes[0] != 1:
        raise typer.BadParameter(f"--batches must start with 1 (the single system) and be >= 1, got {batches}")
    if device == "cuda" and not wp.get_cuda_device_count():
        raise typer.BadParameter("no CUDA device (pass --device cpu to try the script)")
    kept = _last_system(scene, frames, device)
    H, rhs = kept["H"], kept["rhs"].numpy()
    print(f"\n{scene}, frame {frames - 1}'s last Newton system on {wp.get_device(H.device).name}: {H.nrow} block rows, "
          f"{int(H.offsets.numpy()[-1])} blocks; block-Jacobi, no coarse level\n")
    print("| K copies | block rows | rtol | CG iterations | ms per solve | us per iteration | K t(1) / t(K) |")
    print("|---|---|---|---|---|---|---|")
    single: dict[float, float] = {}
    for k in sizes:
        Hk = stacked(H, k)
        A = sparse_product.block_row_operator(Hk, single_precision=True)
        M = sparse_product.BlockJacobi(Hk)
        b = wp.array(np.tile(rhs, (k, 1)), dtype=wp.vec3d, device=H.device)
        x = wp.zeros_like(b)
        workspace = cg_kernels.CgWorkspace(len(b), H.device)
        for rtol in (1e-2, 1e-4):
            seconds = []
            for _ in range(4):
                x.zero_()
                wp.synchronize_device(H.device)
                start = time.perf_counter()
                result = definite_cg.definite_cg(A, b, x, rtol, 5000, M, workspace=workspace)
                wp.synchronize_device(H.device)
                seconds.append(time.perf_counter() - start)
            best = min(seconds[1:])
            single.setdefault(rtol, best)
            print(f"| {k} | {Hk.nrow} | {rtol:g} | {result.iterations} | {1e3 * best:.2f} | "
                  f"{1e6 * best / max(result.iterations, 1):.1f} | {k * single[rtol] / best:.2f} |", flush=True)


if __name__ == "__main__":
    typer.run(main)
