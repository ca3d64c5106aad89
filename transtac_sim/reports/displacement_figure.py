"""A PNG of one physics frame's displacement field, for people.

Top panel: the contact surface (z = thickness) seen from above, in the gel frame (x right, y down, mm,
rest positions), coloured by the magnitude of the surface displacement |u| (mm), with each marker's
in-plane displacement (u_x, u_y) drawn as an arrow from its rest position (arrow scale in the key).
Bottom panel: the section of the deformed gel by the plane y = y0 through the contact (``section_y``: the
centroid of the contact patch of the indenter pushing hardest, else the centre of its footprint), drawn at
deformed positions and coloured by the vertical displacement u_z (mm; negative = into the gel, towards the
cameras), with the indenters' section outlines; a dashed line marks y0 in the top panel and a cross each
indenter's contact centre. A contact-free scene has no mesh: both panels show the rest state and say so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from matplotlib.tri import Triangulation  # noqa: E402

from transtac_sim.indenters.placement import footprint_centre_xy  # noqa: E402
from transtac_sim.writer.atomic import atomic_write  # noqa: E402

FIGSIZE_IN = (8.0, 8.0)
DPI = 110
#: the PNG's size in pixels (width, height)
IMAGE_SIZE_PX = (round(FIGSIZE_IN[0] * DPI), round(FIGSIZE_IN[1] * DPI))
#: A gel surface point at most this far below (or anywhere above) an indenter's surface touches it (mm):
#: the solver leaves penetrations up to 0.02 mm.
CONTACT_GAP_MM = 0.05


@dataclass(frozen=True)
class IndenterView:
    name: str
    vertices_mm: np.ndarray  # (N, 3) in the indenter's own frame
    faces: np.ndarray  # (F, 3)
    pose: np.ndarray  # 4x4, indenter frame -> gel frame (mm)
    force_n: np.ndarray  # (3,) force on the gel

    def posed(self) -> np.ndarray:
        """Vertices (N, 3) in the gel frame (mm)."""
        return self.vertices_mm @ self.pose[:3, :3].T + self.pose[:3, 3]


def _slice_tets(x: np.ndarray, tets: np.ndarray, values: np.ndarray, y0: float):
    """Section of a tet mesh by the plane y = y0: points (P, 3), their interpolated ``values`` (P, ...)
    and triangles (T, 3) indexing the points. Linear interpolation along the cut edges."""
    s = x[:, 1] - y0
    s = np.where(s == 0.0, 1e-9, s)  # no vertex exactly on the plane
    neg = s[tets] < 0
    cut = neg.any(axis=1) & ~neg.all(axis=1)
    points, vals, tris = [], [], []

    def edge(a, b):
        t = s[a] / (s[a] - s[b])
        points.append(x[a] + t * (x[b] - x[a]))
        vals.append(values[a] + t * (values[b] - values[a]))
        return len(points) - 1

    for tet, n in zip(tets[cut], neg[cut], strict=True):
        lo, hi = tet[n], tet[~n]
        if len(lo) == 1 or len(hi) == 1:  # one vertex alone on its side: a triangle
            (a,), others = (lo, hi) if len(lo) == 1 else (hi, lo)
            tris.append([edge(a, b) for b in others])
        else:  # two and two: a quad, in cyclic order, as two triangles
            q = [edge(lo[0], hi[0]), edge(lo[0], hi[1]), edge(lo[1], hi[1]), edge(lo[1], hi[0])]
            tris += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    if not tris:
        return np.zeros((0, 3)), np.zeros((0,) + values.shape[1:]), np.zeros((0, 3), dtype=int)
    return np.array(points), np.array(vals), np.array(tris)


def _underside_z(v: np.ndarray, faces: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Lowest z (P,) of the triangle mesh (``v``, ``faces``) straight above or below each point ``xy`` (P, 2);
    +inf where the mesh does not cover the point. Only triangles facing down can be the underside."""
    tri = v[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # twice the signed xy area: < 0 when facing down
    tri = tri[area2 < 0]
    z = np.full(len(xy), np.inf)
    if len(tri) == 0:
        return z
    for t in np.array_split(tri, max(1, len(tri) // 256)):
        a, b, c = (t[None, :, i] for i in range(3))
        p = xy[:, None, :]

        def cross(u, w):
            return u[..., 0] * w[..., 1] - u[..., 1] * w[..., 0]

        d = cross(b[..., :2] - a[..., :2], c[..., :2] - a[..., :2])
        l1 = cross(b[..., :2] - p, c[..., :2] - p) / d
        l2 = cross(c[..., :2] - p, a[..., :2] - p) / d
        l3 = 1.0 - l1 - l2
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9)
        zt = np.where(inside, l1 * a[..., 2] + l2 * b[..., 2] + l3 * c[..., 2], np.inf)
        z = np.minimum(z, zt.min(axis=1))
    return z


def contact_centre_xy(indenter: IndenterView, surface_mm: np.ndarray) -> np.ndarray | None:
    """Centroid (x, y) of the gel surface points ``surface_mm`` (P, 3, deformed, gel frame, mm) that touch
    ``indenter``: not more than CONTACT_GAP_MM below its underside. None when none does."""
    v = indenter.posed()
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    near = surface_mm[np.all((surface_mm[:, :2] >= lo) & (surface_mm[:, :2] <= hi), axis=1)]
    if len(near) == 0:
        return None
    touching = near[_underside_z(v, np.asarray(indenter.faces), near[:, :2]) - near[:, 2] <= CONTACT_GAP_MM]
    return touching[:, :2].mean(axis=0) if len(touching) else None


def section_y(indenters: list[IndenterView], surface_mm: np.ndarray | None) -> tuple[float, str]:
    """(y0 in mm, gel frame; what it goes through) of the section: the contact centre of the indenter with
    the largest force, else the centre of its footprint (indenters/placement.py); y0 = 0 without indenters."""
    if not indenters:
        return 0.0, "the gel's centre"
    main = max(indenters, key=lambda i: float(np.linalg.norm(i.force_n)))
    centre = contact_centre_xy(main, surface_mm) if surface_mm is not None else None
    if centre is not None:
        return float(centre[1]), "the contact"
    return float(footprint_centre_xy(main.posed())[1]), f"{main.name}'s footprint (no contact)"


def _slice_surface(v: np.ndarray, faces: np.ndarray, y0: float) -> np.ndarray:
    """Segments (S, 2, 2) in (x, z) where the plane y = y0 cuts a triangle mesh."""
    s = v[:, 1] - y0
    s = np.where(s == 0.0, 1e-9, s)
    segs = []
    for f in faces:
        pts = [v[a] + s[a] / (s[a] - s[b]) * (v[b] - v[a]) for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))
               if (s[a] < 0) != (s[b] < 0)]
        if len(pts) == 2:
            segs.append([[p[0], p[2]] for p in pts])
    return np.array(segs).reshape(-1, 2, 2)


def save_displacement_figure(path: Path, *, title: str, frame: int, gel_size_mm: tuple[float, float, float],
                             markers_rest_mm: np.ndarray, markers_mm: np.ndarray,
                             rest_vertices_mm: np.ndarray | None = None, vertices_mm: np.ndarray | None = None,
                             tets: np.ndarray | None = None, boundary_faces: np.ndarray | None = None,
                             indenters: list[IndenterView] = ()) -> Path:
    """Write the figure described in the module docstring to ``path`` (PNG, IMAGE_SIZE_PX); gel frame, mm.
    Without ``vertices_mm`` (contact-free scene) it shows the rest state."""
    w, h, t = gel_size_mm
    rest = vertices_mm is None
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=FIGSIZE_IN, gridspec_kw={"height_ratios": [h, 2.4 * t]})
    xlim = (-w / 2 - 0.5, w / 2 + 0.5)
    forces = "; ".join(f"{i.name}: F = ({i.force_n[0]:.3f}, {i.force_n[1]:.3f}, {i.force_n[2]:.3f}) N"
                       for i in indenters)
    fig.suptitle(f"{title}, frame {frame}" + (f"\n{forces}" if forces else ""), fontsize=10)
    du = markers_mm - markers_rest_mm
    if rest:
        ax0.add_patch(Rectangle((-w / 2, -h / 2), w, h, fill=False, ec="0.4"))
        ax0.scatter(markers_rest_mm[:, 0], markers_rest_mm[:, 1], s=10, c="tab:green", label="markers")
        ax0.text(0, 0, "no contact: rest state", ha="center", va="center", fontsize=14, color="0.3")
        ax0.legend(loc="upper right", fontsize=8)
    else:
        u = vertices_mm - rest_vertices_mm
        top = boundary_faces[np.all(np.abs(rest_vertices_mm[boundary_faces][:, :, 2] - t) < 1e-6, axis=1)]
        tri = Triangulation(rest_vertices_mm[:, 0], rest_vertices_mm[:, 1], top)
        mag = np.linalg.norm(u, axis=1)
        pc = ax0.tripcolor(tri, mag, shading="gouraud", cmap="viridis", vmin=0.0, vmax=max(mag.max(), 1e-9))
        fig.colorbar(pc, ax=ax0, label="surface |u| (mm)", shrink=0.85)
        ax0.triplot(tri, color="w", lw=0.15, alpha=0.5)
        longest = float(np.linalg.norm(du[:, :2], axis=1).max())
        scale = longest / 3.0 if longest > 0 else 1.0  # the longest arrow is drawn 3 mm long
        ax0.scatter(markers_rest_mm[:, 0], markers_rest_mm[:, 1], s=6, c="tab:red", zorder=3)
        ax0.quiver(markers_rest_mm[:, 0], markers_rest_mm[:, 1], du[:, 0], du[:, 1], color="tab:red",
                   angles="xy", scale_units="xy", scale=scale, width=0.004, zorder=4)
        top_now = vertices_mm[np.unique(top)]
        for ind in indenters:
            centre = contact_centre_xy(ind, top_now)
            ax0.plot(*(centre if centre is not None else footprint_centre_xy(ind.posed())), "w+", ms=10, mew=1.5)
    y0, through = section_y(list(indenters), None if rest else top_now)
    if not rest:
        ax0.axhline(y0, color="w", lw=0.6, ls="--")
    ax0.set(xlim=xlim, ylim=(h / 2 + 0.5, -h / 2 - 0.5), aspect="equal", xlabel="x (mm)", ylabel="y (mm)")
    arrows = "" if rest else f"; red arrows: markers' in-plane displacement x {1 / scale:.3g}"
    ax0.set_title(f"contact surface z = {t:g} mm (rest positions){arrows}\n"
                  f"markers' max |u| {np.linalg.norm(du, axis=1).max():.4f} mm", fontsize=9)

    if rest:
        ax1.add_patch(Rectangle((-w / 2, 0), w, t, fill=False, ec="0.4"))
        ax1.scatter(markers_rest_mm[:, 0], markers_rest_mm[:, 2], s=6, c="tab:green")
        ax1.text(0, t / 2, "no contact: rest state", ha="center", va="center", fontsize=12, color="0.3")
        ax1.set_title("side view (markers projected on y = 0)", fontsize=9)
    else:
        pts, vals, tris = _slice_tets(rest_vertices_mm, tets, u, y0)
        if len(tris):
            deformed = pts + vals
            uz = vals[:, 2]
            lim = max(float(np.abs(uz).max()), 1e-9)
            pc = ax1.tripcolor(Triangulation(deformed[:, 0], deformed[:, 2], tris), uz, shading="gouraud",
                               cmap="RdBu_r", vmin=-lim, vmax=lim)
            fig.colorbar(pc, ax=ax1, label="u_z (mm)", shrink=0.9)
        for ind in indenters:
            segs = _slice_surface(ind.posed(), ind.faces, y0)
            ax1.add_collection(LineCollection(segs, colors="k", linewidths=1.0))
        ax1.axhline(t, color="0.5", lw=0.6, ls="--")
        ax1.set_title(f"section y = {y0:.2f} mm through {through}, deformed, coloured by u_z "
                      f"(min u_z {u[:, 2].min():.3f} mm)", fontsize=9)
    ax1.set(xlim=xlim, ylim=(-0.3, t + 1.5), aspect="equal", xlabel="x (mm)", ylabel="z (mm)")
    fig.tight_layout()
    atomic_write(Path(path), lambda f: fig.savefig(f, format="png", dpi=DPI))
    plt.close(fig)
    return Path(path)
