"""``transtac-sim``: the command line. Each subcommand runs the stages its output needs."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from transtac_sim.config import ConfigError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Simulate the TransTac tactile sensor and generate labelled stereo datasets.")
console = Console()

SceneArg = typer.Argument(..., exists=False, help="scene file, e.g. scenes/quickstart.toml")


def _load(scene: Path):
    from transtac_sim.scene_setup import load_setup

    try:
        return load_setup(scene)
    except ConfigError as e:
        console.print(f"[bold red]error:[/] {e}")
        raise typer.Exit(2) from None


@app.command()
def info(scene: Path = SceneArg) -> None:
    """Print what a scene resolves to: sensor, markers, cameras, indenters, frames, outputs."""
    setup = _load(scene)
    s, sc = setup.sensor, setup.scene
    w, h, t = s.gel_size_mm
    tab = Table(title=f"scene {sc.name!r} ({setup.path})", show_header=False)
    tab.add_row("hardware", s.hardware.name)
    tab.add_row("gel", f"{w:g} x {h:g} x {t:g} mm, {s.gel.name}: E = {s.gel.youngs_modulus_mpa} MPa, "
                       f"nu = {s.gel.poisson_ratio}, n = {s.gel.refractive_index}")
    tab.add_row("backing", f"{s.hardware.backing.thickness_mm} mm {s.backing.name}")
    m = s.markers_rest_gel_mm
    tab.add_row("markers", f"{len(m)} x r = {s.marker_radius_mm} mm, depth {t - m[:, 2].max():.2f}..{t - m[:, 2].min():.2f} mm, "
                           f"pigment {s.pigment.name}")
    for c in s.cameras.values():
        tab.add_row(f"camera {c.name}", f"{c.model} {c.image_size[0]}x{c.image_size[1]}, f = {c.K[0, 0]:.1f} px, "
                                        f"T = {c.T.tolist()} mm")
    for ind in setup.indenters:
        segs = ", ".join(f"{g.kind}({g.frames})" for g in ind.config.trajectory)
        tab.add_row(f"indenter {ind.config.name}", f"{ind.config.mesh} ({ind.config.units}), "
                    f"{ind.mesh.mesh.extents.round(2).tolist()} mm, friction {ind.config.friction}: {segs}"
                    + (f" [repaired: {'; '.join(ind.mesh.repairs)}]" if ind.mesh.repairs else ""))
    tab.add_row("frames", str(sc.frame_count))
    o = sc.outputs
    tab.add_row("outputs", f"cameras {o.cameras}, illuminations {o.illuminations}, aovs {o.aovs}, labels {o.labels}")
    tab.add_row("stages", ", ".join(["mesh", "physics" if setup.has_contact else "(no physics: no contact)",
                                     "render" if o.illuminations or o.aovs else "(no render)"]))
    console.print(tab)


@app.command()
def mesh(scene: Path = SceneArg,
         out: Path = typer.Option(None, help="output folder (default out/<scene name>/mesh)"),
         cache: bool = typer.Option(True, help="reuse a cached mesh with the same inputs")) -> None:
    """Mesh the gel, embed the markers, and write the mesh, the markers, a summary and a layout PNG."""
    from transtac_sim.meshing import mesh_gel
    from transtac_sim.reports.mesh_figure import save_mesh_figure
    from transtac_sim.writer.atomic import write_json, write_npz

    t0 = time.perf_counter()
    setup = _load(scene)
    out = out or Path("out") / setup.scene.name / "mesh"
    with console.status("meshing the gel (pytetwild)..."):
        meshed = mesh_gel(setup, use_cache=cache)
    g, emb, q = meshed.mesh, meshed.markers, meshed.quality
    write_npz(out / "gel_mesh.npz", vertices_mm=g.vertices_mm, tets=g.tets)
    markers = [{"id": i, "xyz_rest_gel_mm": p.tolist(), "tet": int(k), "barycentric": b.tolist()}
               for i, (p, k, b) in enumerate(zip(setup.sensor.markers_rest_gel_mm, emb.tet_index, emb.barycentric, strict=True))]
    write_json(out / "markers.json", {"frame": "gel", "units": "mm", "markers": markers})
    png = save_mesh_figure(meshed, setup.sensor, out / "layout.png", setup.scene.name)
    summary = {"scene": setup.scene.name, "quality": q.as_dict(), "contact_region_mm": meshed.contact_region,
               "cache_key": meshed.cache_key, "cache_hit": meshed.cache_hit, "mesh_seconds": meshed.seconds,
               "total_seconds": time.perf_counter() - t0, "markers": len(markers)}
    write_json(out / "summary.json", summary)
    console.print(f"[bold]{setup.scene.name}[/]: {q.tets} tets, {q.vertices} vertices, {len(markers)} markers embedded")
    console.print(f"  quality: min dihedral {q.min_dihedral_deg:.1f} deg, max dihedral {q.max_dihedral_deg:.1f} deg, "
                  f"aspect ratio max {q.max_aspect_ratio:.2f} / mean {q.mean_aspect_ratio:.2f}")
    console.print(f"  time: {meshed.seconds:.2f} s meshing ({'cache hit' if meshed.cache_hit else 'built'}), "
                  f"{summary['total_seconds']:.2f} s total")
    console.print(f"  wrote {out}/gel_mesh.npz, markers.json, summary.json, {png.name}")


if __name__ == "__main__":
    app()
