"""A PNG of the gel mesh and marker layout: top view of the contact surface with the markers (coloured by
depth) and the contact region, and a side section showing the refinement through the thickness."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

from transtac_sim.meshing import MeshedGel  # noqa: E402
from transtac_sim.sensor.assembly import Sensor  # noqa: E402


def _face_edges(vertices: np.ndarray, faces: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    return vertices[e][:, :, list(axes)]


def save_mesh_figure(meshed: MeshedGel, sensor: Sensor, path: Path, title: str) -> Path:
    v, faces = meshed.mesh.vertices_mm, meshed.mesh.boundary_faces()
    w, h, t = sensor.gel_size_mm
    top = faces[np.all(v[faces][:, :, 2] == t, axis=1)]
    side = faces[np.all(v[faces][:, :, 1] == -h / 2, axis=1)]
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 8.6), gridspec_kw={"height_ratios": [h, 2.2 * t]})
    ax0.add_collection(LineCollection(_face_edges(v, top, (0, 1)), colors="0.75", linewidths=0.4))
    m = sensor.markers_rest_gel_mm
    depth = t - m[:, 2]
    sc = ax0.scatter(m[:, 0], m[:, 1], c=depth, cmap="viridis", s=14, zorder=3)
    for p in m:
        ax0.add_patch(Circle(p[:2], sensor.marker_radius_mm, fill=False, lw=0.5, color="k", zorder=4))
    if meshed.contact_region:
        x0, y0, x1, y1 = meshed.contact_region
        ax0.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="tab:red", lw=1.2, ls="--",
                                label="contact region (refined)"))
        ax0.legend(loc="upper right", fontsize=8)
    ax0.set(xlim=(-w / 2 - 0.5, w / 2 + 0.5), ylim=(h / 2 + 0.5, -h / 2 - 0.5), aspect="equal",
            xlabel="x (mm)", ylabel="y (mm)",
            title=f"{title}: contact surface z = {t:g} mm, {len(m)} markers (r = {sensor.marker_radius_mm} mm)")
    fig.colorbar(sc, ax=ax0, label="marker depth below surface (mm)", shrink=0.8)
    ax1.add_collection(LineCollection(_face_edges(v, side, (0, 2)), colors="0.4", linewidths=0.4))
    ax1.scatter(m[:, 0], m[:, 2], s=4, c="tab:green", label="markers (projected)")
    ax1.set(xlim=(-w / 2 - 0.5, w / 2 + 0.5), ylim=(-0.3, t + 0.3), aspect="equal", xlabel="x (mm)",
            ylabel="z (mm)", title=f"side face y = {-h / 2:g} mm: {meshed.quality.tets} tets, "
                                   f"min dihedral {meshed.quality.min_dihedral_deg:.1f} deg")
    ax1.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
