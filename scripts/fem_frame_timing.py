"""Seconds, Newton iterations and forces per FEM frame of a scene, as `generate` would solve it.

    .venv/bin/python scripts/fem_frame_timing.py tests/fixtures/tiny_press.toml [--degree 2] [--frames 2]
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import typer

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames


def main(scene: Path, degree: int = typer.Option(2, min=1, max=2), frames: int = typer.Option(2, min=1)) -> None:
    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"degree": degree})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    clock, t0 = StageClock(), time.perf_counter()
    print(f"{scene} on a {os.cpu_count()}-core CPU, P{degree}, {frames} frame(s)")
    for f in simulate_frames(setup, frames, clock):
        s = f.solver
        print(f"frame {f.frame}: {s['seconds']:.1f} s, {s['iterations']} Newton iterations, residual {s['residual']:.2e} N, "
              f"min det F {s['min_det_f']:.3f}, forces {[x.round(4).tolist() for x in f.forces_n]} N "
              f"(wall {time.perf_counter() - t0:.1f} s)", flush=True)
    print({k: round(v, 2) for k, v in clock.seconds.items()})


if __name__ == "__main__":
    typer.run(main)
