"""Newton iterations and friction forces against how often friction's lag is moved per load step.

    .venv/bin/python scripts/fem_friction_lag_moves.py [SCENE] [--trajectory-from scenes/press_slide.toml]
        [--frames 8] [--moves 1,2,4,12] [--benchmarks] [--md-out FILE]
    python scripts/fem_friction_lag_moves.py scenes/train_random.toml --sequence 2 --moves 1,4,12

Friction's normal pressure and tangent plane are lagged (contact.py) and moved to the current state at most
``[physics] friction_lag_moves`` times per load step (friction_lag.py ``_move_lag``). Each move costs Newton a few
iterations; fewer moves leave the friction force further from the fixed point of the lag. This solves the same
frames with each count in ``--moves`` (default: the tiny test mesh with the press-and-slide motion, friction 0.5)
and reports, per count, the Newton iterations and seconds of the frames and the largest difference of the
tangential (friction) and normal force from the run with the most moves, on the frames where the indenter slides,
the largest marker position difference from that run over all frames, and the largest imbalance the lag leaves at a
frame's solution (``SolverRecord.friction_lag_residual_n``: where it is not small, the most-moves run is no converged
reference either). ``--sequence I`` solves sequence I of a randomised scene (its own indenter and motion) instead of
the scene with ``--trajectory-from``'s motion.
``--benchmarks`` writes the table into BENCHMARKS.md, section ``--section`` (default ``fem_friction_lag_moves``, this
CPU's; the GPU's is ``fem_friction_lag_moves_gpu``).
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402
from fem_frame_timing import run  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def force_differences(forces: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """Largest relative difference (over frames) of the tangential and of the normal force of indenter 0 from the
    reference run's, each relative to the reference's largest tangential or normal force over the frames."""
    t, t_ref = np.linalg.norm(forces[:, :2], axis=1), np.linalg.norm(reference[:, :2], axis=1)
    n, n_ref = forces[:, 2], reference[:, 2]
    return (float(np.max(np.abs(t - t_ref)) / max(np.max(t_ref), 1e-12)),
            float(np.max(np.abs(n - n_ref)) / max(np.max(np.abs(n_ref)), 1e-12)))


def main(scene: Path = typer.Argument(REPO / "tests" / "fixtures" / "tiny_press.toml"),
         trajectory_from: Path | None = typer.Option(REPO / "scenes" / "press_slide.toml"),
         frames: int = typer.Option(8, min=1), moves: str = typer.Option("1,2,4,12"),
         sequence: int | None = typer.Option(None, min=0, help="solve this sequence of a randomised scene (its own "
                                              "motion: --trajectory-from is not used)"),
         benchmarks: bool = typer.Option(False, help="write the table into BENCHMARKS.md"),
         section: str = typer.Option("fem_friction_lag_moves"),
         md_out: Path | None = typer.Option(None, help="also write the table to this file")) -> None:
    counts = sorted(int(m) for m in moves.split(","))
    if sequence is not None:
        trajectory_from = None
    # a first frame compiles the elastic and contact kernels; it has no friction, so on a machine without Warp's kernel
    # cache the first count's seconds still include compiling the friction kernels
    run(scene, 2, 1, trajectory_from, sequence)
    runs = {m: run(scene, 2, frames, trajectory_from, sequence, friction_lag_moves=m) for m in counts}
    ref = np.array([f[0] for f in runs[counts[-1]]["forces_n"]])
    ref_markers = np.array(runs[counts[-1]]["markers_mm"])
    friction = np.linalg.norm(ref[:, :2], axis=1)
    sliding = friction > 0.1 * np.max(friction)  # frames whose friction force is at least 10 % of the largest
    device = runs[counts[-1]]["device"]
    lines = [f"Machine: {machine_name(device)}. Command: `python {' '.join(sys.argv)}` "
             f"({runs[counts[-1]]['scene']}, P2, {frames} frames; {int(sliding.sum())} of them with a friction force). "
             f"Force differences: the largest over the sliding frames, relative to the largest force of the "
             f"{counts[-1]}-move run.", "",
             "| lag moves per step | Newton iterations, all frames | per frame | sliding frames | seconds, all frames "
             "| friction force vs most moves | normal force vs most moves | friction force per sliding frame (N) "
             "| markers vs most moves (mm) | largest lag residual (N) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for m, r in runs.items():
        forces = np.array([f[0] for f in r["forces_n"]])
        dt, dn = force_differences(forces[sliding], ref[sliding])
        its = r["iterations"]
        lines.append(f"| {m} | {sum(its)} | {', '.join(map(str, its))} | "
                     f"{sum(i for i, s in zip(its, sliding, strict=True) if s)} | {sum(r['seconds']):.1f} | "
                     f"{100 * dt:.2f} % | {100 * dn:.2f} % | "
                     f"{', '.join(f'{x:.3f}' for x in np.linalg.norm(forces[sliding, :2], axis=1))} | "
                     f"{np.max(np.linalg.norm(np.array(r['markers_mm']) - ref_markers, axis=-1)):.4f} | "
                     f"{max(r['lag_residual_n']):.2g} |")
    publish("\n".join(lines), md_out, benchmarks, section)
    print("median Newton iterations per frame:", {m: statistics.median(r["iterations"]) for m, r in runs.items()})


if __name__ == "__main__":
    typer.run(main)
