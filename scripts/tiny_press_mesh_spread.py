"""How much the checks of tests/test_simulate_cli.py vary with the mesh: fTetWild builds a different gel mesh
on every run, so this simulates frame 0 of the tiny press on N fresh meshes (an empty mesh cache each) and
prints, per mesh, the quantities that test bounds.

    .venv/bin/python scripts/tiny_press_mesh_spread.py [N]

Columns (mm unless stated): vertices; deepest vertex inside the sphere (pen, < 0 is a gap); the gap of the
vertex nearest the axis to depth0 - sag; largest |u| - depth0; largest marker |du|; P2-vs-P1 marker
difference as an L2 ratio and as a worst-marker ratio.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import tomllib
from pathlib import Path

import numpy as np
import typer

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "tests" / "fixtures" / "tiny_press.toml"
RADIUS = 4.0  # sphere_r4.stl
THICKNESS = 5.0


def one_mesh() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sim"
        subprocess.run([str(ROOT / ".venv" / "bin" / "transtac-sim"), "simulate", str(SCENE), "--out", str(out),
                        "--frames", "1"], env=dict(os.environ, TRANSTAC_SIM_CACHE=f"{tmp}/cache"),
                       capture_output=True, check=True)
        press = tomllib.loads(SCENE.read_text())["indenters"][0]
        seg = press["trajectory"][0]
        depth0 = (press["start_gap_mm"] + seg["depth_mm"]) / seg["frames"] - press["start_gap_mm"]
        mesh, frame = np.load(out / "mesh.npz"), np.load(out / "frames" / "000000.npz")
        rest, v, tets = mesh["vertices_mm"], frame["vertices_mm"], mesh["tets"]
        pose = frame["indenter_poses_mm"][0]
        bf = np.unique(mesh["boundary_faces"])
        top = bf[np.abs(rest[bf, 2] - THICKNESS) < 1e-9]
        r_xy = np.hypot(v[top, 0] - pose[0, 3], v[top, 1] - pose[1, 3])
        under = r_xy < RADIUS
        pen = (v[top][under, 2] - (pose[2, 3] - np.sqrt(RADIUS**2 - r_xy[under] ** 2))).max()
        i = np.argmin(r_xy)
        gap = abs((rest[top][i, 2] - v[top][i, 2]) - (depth0 - (RADIUS - np.sqrt(RADIUS**2 - r_xy[i] ** 2))))
        du = frame["markers_mm"] - mesh["markers_rest_mm"]
        interp = np.einsum("kj,kjc->kc", mesh["marker_barycentric"], (v - rest)[tets[mesh["marker_tets"]]])
        return (f"{len(rest):6d} {pen:+.4f} {gap:.4f} {np.abs(v - rest).max() - depth0:+.4f} {np.abs(du).max():.4f} "
                f"{np.linalg.norm(du - interp) / np.linalg.norm(du):.3f} {np.abs(du - interp).max() / np.abs(du).max():.3f}")


def main(meshes: int = typer.Argument(6, min=1, help="how many fresh meshes")) -> None:
    print("vertices pen gap max|u|-depth0 max|du| L2-ratio worst-ratio")
    for _ in range(meshes):
        print(one_mesh(), flush=True)


if __name__ == "__main__":
    typer.run(main)
