"""``transtac-sim``: the command line. Each subcommand runs the stages its output needs."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from transtac_sim.config import ConfigError
from transtac_sim.perception_cli import register as register_perception
from transtac_sim.sweep.cli import register as register_sweep

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Simulate the TransTac tactile sensor and generate labelled stereo datasets.")
console = Console()

SceneArg = typer.Argument(..., exists=False, help="scene file, e.g. scenes/press_slide.toml")


def _load(scene: Path):
    from transtac_sim.scene_setup import load_setup

    try:
        return load_setup(scene)
    except ConfigError as e:
        console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
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
    tab.add_row("stages", ", ".join(["mesh, physics" if setup.has_contact else "(no mesh or physics: no contact)",
                                     "render" if o.illuminations or o.aovs else "(no render)",
                                     "labels" if o.labels else "(no labels)"]))
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


@app.command()
def render(scene: Path = SceneArg,
           frame: int = typer.Option(0, "--frame", min=0, help="frame of the scene's sequence to render"),
           out: Path = typer.Option(None, help="output folder (default out/<scene name>/render/<frame>)")) -> None:
    """Render one frame (physics of the frames before it included): the asked-for images, labels.json, and
    a contact sheet with the labels drawn over the images."""
    import json

    from transtac_sim.dataset.frame_writer import FrameOutput, write_frame_files
    from transtac_sim.dataset.randomize import sequence_variant
    from transtac_sim.dataset.render_stage import FrameRenderer
    from transtac_sim.dataset.sequence import StageClock, frame_labels, frame_seed
    from transtac_sim.reports.contact_sheet import annotate, save_contact_sheet
    from transtac_sim.simulation import SimulationFailed, simulate_frames

    setup = _load(scene)
    sc = setup.scene
    if setup.has_contact and frame >= sc.frame_count:
        console.print(f"[bold red]error:[/] --frame {frame}: the trajectory has {sc.frame_count} frames (0..{sc.frame_count - 1})", soft_wrap=True)
        raise typer.Exit(2)
    out = out or Path("out") / sc.name / "render" / f"{frame:06d}"
    clock = StageClock()
    t0 = time.perf_counter()
    try:
        with console.status(f"physics of frames 0..{frame}" if setup.has_contact else "rest state (no contact)"):
            phys = list(simulate_frames(setup, frame + 1, clock))[-1]
    except SimulationFailed as e:
        console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
        raise typer.Exit(1) from None
    with console.status("rendering"):
        renderer = FrameRenderer(setup, sequence_variant(sc, 0), clock, phys.rest_vertices_gel_mm, phys.surface_faces)
        images, depth, views = renderer.render(phys, seed=frame_seed(sc.seed, 0, frame))
    labels = frame_labels("render", frame, frame / sc.outputs.frame_rate_hz, setup, phys, views)
    write_frame_files(out, FrameOutput("render", frame, labels, images, depth))
    tiles = [(f"{cam} {ill}", annotate(img, labels, cam, scale=1) if views else img) for (cam, ill), img in sorted(images.items())]
    sheet = save_contact_sheet(tiles, out / "contact_sheet.png", columns=max(1, len(sc.outputs.illuminations))) if tiles else None
    (out / "timings.json").write_text(json.dumps(clock.seconds, indent=1))
    console.print(f"[bold]{sc.name}[/] frame {frame}: {len(images)} image(s), {len(labels['markers'])} markers labelled "
                  f"in {time.perf_counter() - t0:.1f} s ({', '.join(f'{k} {v:.1f} s' for k, v in clock.seconds.items())})")
    console.print(f"  wrote {out}/ (images, labels.json){', ' + str(sheet) if sheet else ''}")


def _interrupted(e: BaseException | None) -> bool:
    """Whether ``e`` is, or was caused by, a KeyboardInterrupt (Ctrl-C)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


@app.command()
def generate(scene: Path = SceneArg,
             out: Path = typer.Option(..., "--out", help="dataset folder (created; an unfinished one is resumed)"),
             frames: int = typer.Option(None, min=1, help="frames per sequence (default: the whole trajectory)"),
             seed: int = typer.Option(None, min=0, help="replace the scene's seed"),
             sequences: int = typer.Option(None, min=1, help="replace the scene's sequence count"),
             workers: int = typer.Option(1, min=1, help="parallel sequences (processes, or Ray tasks; with "
                                                         "GPUs, workers / GPUs per GPU); on train_random 8 with --mps "
                                                         "gave 12,582 frames per hour on one H100, and 16 Ray "
                                                         "workers under MPS 23,835 on two H200s (BENCHMARKS.md)"),
             executor: str = typer.Option("local", help="local | ray"),
             address: str = typer.Option(None, help="Ray cluster address (default: start a local Ray)"),
             retry_failed: bool = typer.Option(False, help="on resume, solve again the sequences whose frame failed "
                                                           "in an earlier run (default: keep those failures)"),
             mps: bool = typer.Option(False, help="run the workers under CUDA MPS (started and stopped by this "
                                                  "command; the local executor, or Ray without --address), so that "
                                                  "their GPU kernels run side by side")) -> None:
    """Generate a labelled stereo dataset (DESIGN.md section 4); re-running resumes an interrupted run."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from transtac_sim.dataset.generate import generate as run
    from transtac_sim.gpu_sharing import MpsUnavailable

    if executor not in ("local", "ray"):
        console.print(f"[bold red]error:[/] --executor {executor!r}: allowed local, ray", soft_wrap=True)
        raise typer.Exit(2)
    t0 = time.perf_counter()
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                  TextColumn("{task.fields[rate]}"), TimeRemainingColumn(), console=console) as progress:
        task = progress.add_task(f"generating {scene.name}", total=None, rate="")

        def on_frames(done: int, total: int) -> None:
            minutes = (time.perf_counter() - t0) / 60
            progress.update(task, completed=done, total=total, rate=f"{done / minutes:.1f} frames/min")

        try:
            report = run(scene, out, frames=frames, seed=seed, sequences=sequences, workers=workers,
                         executor=executor, address=address, on_frames=on_frames, retry_failed=retry_failed,
                         mps=mps)
        except (ConfigError, MpsUnavailable) as e:
            console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
            raise typer.Exit(2) from None
        except (KeyboardInterrupt, RuntimeError) as e:  # Ctrl-C inside Mitsuba comes back as its RuntimeError
            if not _interrupted(e):
                raise
            console.print(f"interrupted: the complete frames in {out} are kept; the same command resumes the run")
            raise typer.Exit(130) from None
    tab = Table(title=f"dataset {report.root}", show_header=False)
    redone = f", {len(report.frames_redone)} damaged and written again" if report.frames_redone else ""
    tab.add_row("frames", f"{report.frames_done} done ({report.frames_skipped} already there{redone}), "
                          f"{len(report.frames_failed)} failed")
    for f in report.frames_failed[:5]:
        tab.add_row("  failed", f"{f['sequence']}/{f['frame']:06d}: {f.get('reason', '')}")
    for f in report.frames_redone[:5]:
        tab.add_row("  written again", f)
    tab.add_row("stages", ", ".join(report.stages_run))
    tab.add_row("seconds per stage", ", ".join(f"{k} {v:.1f}" for k, v in report.timings.items()))
    tab.add_row("coco", ", ".join(f"{k}: {v} images" for k, v in report.coco_images.items()) or "(no UV labels asked)")
    tab.add_row("contact sheet", str(report.contact_sheet))
    tab.add_row("total", f"{report.seconds:.1f} s")
    if report.gpus_used:
        tab.add_row("GPUs (Ray ids)", ", ".join(report.gpus_used))
    console.print(tab)
    if report.frames_failed:
        raise typer.Exit(1)


@app.command()
def simulate(scene: Path = SceneArg,
             out: Path = typer.Option(..., "--out", help="output folder (new, empty, or an earlier simulate run of this scene)"),
             frames: int = typer.Option(None, min=1, help="frames to simulate (default: the whole trajectory)"),
             overwrite: bool = typer.Option(False, "--overwrite", help="write into a folder that holds other files")) -> None:
    """Run the physics alone: per frame the deformed gel mesh, marker positions, indenter poses and forces
    and the solver record, a summary, and a picture of the last frame's displacement field."""
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from transtac_sim.writer.physics_frames import OutputFolderInUse, frame_count, simulate_to_folder

    setup = _load(scene)
    total = frame_count(setup, frames)
    if frames and frames > total:
        console.print(f"note: the trajectory has {total} frames; simulating {total}")
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                  TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), console=console) as progress:
        what = "physics" if setup.has_contact else "rest state (no contact)"
        task = progress.add_task(f"{what} of {setup.scene.name}", total=total, rate="")
        spent: list[float] = []

        def on_frame(done: int, total: int, seconds: float) -> None:
            spent.append(seconds)
            progress.update(task, completed=done, rate=f"{seconds:.1f} s/frame (mean {sum(spent) / len(spent):.1f})")

        try:
            report = simulate_to_folder(setup, out, frames=frames, overwrite=overwrite, on_frame=on_frame)
        except OutputFolderInUse as e:
            console.print(f"[bold red]error:[/] {e}", soft_wrap=True)
            raise typer.Exit(2) from None
    if report.failure:
        k = report.failure["frame"]
        kept = f"kept frames 0..{k - 1} in {out}" if k else f"no frame written to {out}"
        console.print("[bold red]error:[/] " + escape(f"{setup.scene.name}: frame {k} failed: {report.failure['message']} "
                                                     f"({kept}; see summary.json)"), soft_wrap=True)
        raise typer.Exit(1)
    console.print(f"[bold]{setup.scene.name}[/]: {report.frames_written} frame(s) in {report.seconds:.1f} s "
                  f"({', '.join(f'{k} {v:.1f} s' for k, v in report.timings.items())}); max |F| "
                  f"{report.max_force_n:.3f} N, max marker displacement {report.max_marker_displacement_mm:.4f} mm")
    console.print(f"  wrote {out}/mesh.npz, frames/000000..{report.frames_written - 1:06d} (.npz, .json), "
                  f"summary.json, {report.figure.name if report.figure else '(no picture)'}")


@app.command()
def validate(dataset: Path = typer.Argument(..., help="dataset folder")) -> None:
    """Check a dataset against the contract: files present, labels consistent with images and ids."""
    from transtac_sim.dataset.validate import validate_dataset

    problems = validate_dataset(dataset)
    for p in problems[:50]:
        console.print(f"[red]  {p}[/]")
    if problems:
        console.print(f"[bold red]{len(problems)} problem(s)[/] in {dataset}")
        raise typer.Exit(1)
    console.print(f"[bold green]valid[/]: {dataset}")


register_perception(app)
register_sweep(app)

if __name__ == "__main__":
    app()
