"""Error against run time of the device linear solvers on the Newton systems of a real scene.

    python scripts/bench_linear_solvers.py [--scene scenes/press_slide.toml] [--frames 3] [--systems 8]
        [--device cuda] [--md-out FILE] [--benchmarks]

Solves the scene's first ``--frames`` frames with the CG path (``linear_solver = "cg"``) and keeps
``--systems`` of the Newton systems it met (every fifth, then evenly spread; each as the solver hands it to CG: the summed
Hessian with the fixed dofs projected out, and the right-hand side). Each kept system is then solved
by conjugate gradients with each preconditioner and relative tolerance below; per combination: median CG
iterations, median milliseconds per solve (preconditioner set-up included, device synchronised) and the
median relative error |x - x_ref| / |x_ref| against a reference solve (block-Jacobi, tolerance 1e-10).
CG stops at 5000 iterations: a median of 5000 means that combination did not converge.

Preconditioners: ``block_jacobi`` (3x3 blocks, today's default), ``fsaiK`` (Warp's adaptive factorized
sparse approximate inverse with at most K entries per factor row: two sparse products per application).
BENCHMARKS.md section ``linear_solvers_<device>`` with ``--benchmarks``.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import typer
import warp as wp
from warp.optim.linear import FSAI, cg, preconditioner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402

from transtac_sim.dataset.sequence import StageClock  # noqa: E402
from transtac_sim.physics import device_linear  # noqa: E402
from transtac_sim.physics.linear import LinearSolver  # noqa: E402
from transtac_sim.scene_setup import load_setup  # noqa: E402
from transtac_sim.simulation import simulate_frames  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PRECONDITIONERS = ("block_jacobi", "fsai8", "fsai16", "fsai32")
TOLERANCES = (1e-8, 1e-4, 1e-2)


def record_systems(scene: Path, frames: int, device: str, every: int = 5, keep: int = 40) -> list[tuple]:
    """(H, b) of every ``every``-th CG solve of the frames (at most ``keep``), as copies on the device."""
    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": device, "linear_solver": "cg"})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    systems, merge_seconds, met = [], [], [0]
    original = LinearSolver._solve_cg

    def recording(self, H, rhs, *args, **kwargs):
        met[0] += 1
        if (met[0] - 1) % every or len(systems) >= keep:  # keep a spread of them (each is ~0.4 GB at 10^5 dofs)
            return original(self, H, rhs, *args, **kwargs)
        wp.synchronize_device()
        t0 = time.perf_counter()
        K = wp.sparse.bsr_copy(H)  # the solver projects H in place: keep a projected copy, as CG receives it
        device_linear.project_fixed(K, self._fixed, device_linear.fixed_blocks(K, self._fixed.numpy() > 0.5))
        b = wp.array(rhs.numpy() * (self._fixed.numpy() < 0.5), dtype=wp.vec3d, device=rhs.device)  # (I - P) rhs
        wp.synchronize_device()
        merge_seconds.append(time.perf_counter() - t0)
        systems.append((K, b))
        return original(self, H, rhs, *args, **kwargs)

    LinearSolver._solve_cg = recording
    try:
        for f in simulate_frames(setup, frames, StageClock()):
            print(f"frame {f.frame}: {f.solver['seconds']:.2f} s, {f.solver['iterations']} Newton iterations",
                  flush=True)
    finally:
        LinearSolver._solve_cg = original
    print(f"copying and projecting a Newton matrix: median {1000 * statistics.median(merge_seconds):.1f} ms",
          flush=True)
    return systems


def make_preconditioner(name: str, H):
    if name == "block_jacobi":
        return preconditioner(H, ptype="block_jacobi_direct")
    return FSAI(H, max_row_size=int(name.removeprefix("fsai")))


def timed_solve(H, b, name: str, tol: float, maxiter: int = 5000) -> tuple[np.ndarray, int, float]:
    """Solution, CG iterations (maxiter where CG did not reach ``tol``) and seconds, set-up included."""
    wp.synchronize_device()
    t0 = time.perf_counter()
    M = make_preconditioner(name, H)
    x = wp.zeros_like(b)
    iters, err, atol = cg(H, b, x, tol=tol, maxiter=maxiter, M=M, check_every=25)
    wp.synchronize_device()
    return x.numpy().reshape(-1), int(iters), time.perf_counter() - t0


def main(scene: Path = typer.Option(ROOT / "scenes" / "press_slide.toml"), frames: int = typer.Option(3, min=1),
         systems: int = typer.Option(8, min=1), device: str = typer.Option("cuda"),
         md_out: Path | None = typer.Option(None), benchmarks: bool = typer.Option(False)) -> None:
    kept = record_systems(scene, frames, device)
    picks = np.unique(np.linspace(0, len(kept) - 1, min(systems, len(kept))).round().astype(int))
    print(f"{len(kept)} systems kept; comparing on {len(picks)} of them ({kept[0][0].shape[0]} dofs)", flush=True)
    for name in PRECONDITIONERS:  # compile and warm up each kernel once
        _, iters, seconds = timed_solve(*kept[picks[0]], name, 1e-2)
        print(f"warm-up {name}: {iters} iterations, {seconds:.2f} s", flush=True)
    rows = {}
    for k in picks:
        H, b = kept[k]
        ref, iters, seconds = timed_solve(H, b, "block_jacobi", 1e-10, maxiter=20000)
        print(f"system {k}: reference {iters} iterations, {seconds:.2f} s", flush=True)
        for name in PRECONDITIONERS:
            for tol in TOLERANCES:
                x, iters, seconds = timed_solve(H, b, name, tol)
                err = float(np.linalg.norm(x - ref) / max(np.linalg.norm(ref), 1e-300))
                rows.setdefault((name, tol), []).append((iters, seconds, err))
                print(f"  {name} tol {tol:g}: {iters} iterations, {1000 * seconds:.1f} ms, error {err:.2e}", flush=True)
    lines = [f"`python scripts/bench_linear_solvers.py --scene {scene.relative_to(ROOT) if scene.is_absolute() else scene} "
             f"--frames {frames} --systems {systems} --device {device}` on {machine_name('cuda' if 'cuda' in device else 'cpu')}: {len(picks)} Newton "
             f"systems of {kept[0][0].shape[0]} dofs (spread over the CG solves of {frames} frames), medians.",
             "", "| preconditioner | CG tolerance | CG iterations | ms per solve | relative error of du |",
             "|---|---|---|---|---|"]
    for (name, tol), r in rows.items():
        it, s, e = zip(*r, strict=True)
        lines.append(f"| {name} | {tol:g} | {statistics.median(it):g} | {1000 * statistics.median(s):.1f} | "
                     f"{statistics.median(e):.2e} |")
    publish("\n".join(lines), md_out, benchmarks, f"linear_solvers_{'gpu' if 'cuda' in device else 'cpu'}")


if __name__ == "__main__":
    typer.run(main)
