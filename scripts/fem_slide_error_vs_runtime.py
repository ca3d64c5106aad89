"""FEM error against run time on a press-and-slide scene with friction: contact mesh size x lag moves x load steps x
Newton's force test x friction's smoothing.

    .venv/bin/python scripts/fem_slide_error_vs_runtime.py [--scene scenes/press_slide.toml] [--frames 10]
        [--settings 1.2/4,1.0/4,0.8/4,0.8/1,0.65/4,0.5/4,0.4/4] [--reference 0.3/4] [--device cpu|cuda]
        [--friction MU] [--friction-slip-mm MM] [--no-friction-memory] [--suffix S] [--mesh-only | --replot]
        [--no-write]

``scripts/fem_error_vs_runtime.py`` measures a frictionless press on a structured quarter block; datasets are made of
presses *and slides* with friction, on fTetWild meshes of the whole gel. This script solves a scene as ``generate``
does, once per setting EDGE/LAGS[/SPLIT[/RTOL[/SLIP]]]:
- ``[mesh] contact_edge_mm`` = EDGE, the element size over the contact region (mm);
- ``[physics] friction_lag_moves`` = LAGS, friction's lag moves per load step (newton.py);
- SPLIT (default 1): every trajectory segment's frames times SPLIT, each frame then solved in SPLIT load steps on the
  same mesh. Friction is path dependent, so finer load steps are a refinement of their own. Friction's smoothing
  (``friction_slip_mm``) applies to each load step's slip, so a split also loosens it against the frame's motion;
- RTOL (default: the scene's): ``[physics] newton_force_rtol``, Newton's force test (convergence_tests.py
  ``_force_balanced``: also converged where |gradient| is at most RTOL times the normal load on the gel's support); 0
  turns it off, "-" keeps the scene's (to give SLIP alone);
- SLIP (default: ``--friction-slip-mm``'s, else the scene's): ``[physics] friction_slip_mm``, friction's smoothing
  (contact.py: a sticking point moves up to SLIP mm against the indenter before friction reaches mu times the
  pressure). Larger is smoother for Newton and further from Coulomb's law; a reference with a small SLIP measures
  what a larger one costs.

Everything else is as in the scene. The markers are the scene's own (each mesh embeds them anew), so every setting's
marker centres compare with the reference's (a finer setting) frame by frame. Per setting:
- tets and P2 unknowns;
- physics seconds per frame, the median and the mean over frames 1..N-1 (frame 0 also makes the solver's kept matrices
  and graphs; kernels are loaded by a 2-frame warm-up solve first; the plot takes the median);
- Newton iterations per frame (median) and the load steps each frame took (SPLIT, or more where a step was halved);
- against the reference: the marker error, the largest and the RMS over all frames and markers (mm, and % of the
  largest reference marker displacement from rest), and the largest per frame; the force error, the largest over frames
  and indenters of |F - F_ref| (each indenter's whole force vector, N) in % of the largest |F_ref|.
A setting that fails (``SimulationFailed``) gets a row that says at which frame and why; the others go on.

Writes BENCHMARKS.md section ``fem_slide_error_vs_runtime`` (``..._gpu`` where the physics runs on a GPU), the plot
docs/figures/<section>.png and the raw rows out/<section>.json. ``--friction MU`` (every indenter's friction
coefficient), ``--friction-slip-mm MM`` (``[physics] friction_slip_mm``) and ``--suffix S`` append ``_friction_MU``,
``_slip_MM`` and ``_S`` to these names, and ``--no-friction-memory`` (each step's slip measured afresh, the friction
model before contact.py carried its sticking stretch) ``_no_memory``. ``--mesh-only`` meshes every setting (into the
mesh cache, e.g. before carrying it to another machine) and stops; ``--replot`` makes the section and plot again from
out/<section>.json without solving (give it the run's own --device, --friction, --friction-slip-mm,
--no-friction-memory and --suffix: they name the file).
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import NamedTuple
from unittest import mock

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
import solver_variants  # noqa: E402
from benchmarks_md import machine_name, update_section  # noqa: E402
from fem_frame_timing import with_friction  # noqa: E402

from transtac_sim import meshing  # noqa: E402
from transtac_sim.dataset.sequence import StageClock  # noqa: E402
from transtac_sim.meshing import mesh_gel  # noqa: E402
from transtac_sim.scene_setup import load_setup  # noqa: E402
from transtac_sim.simulation import SimulationFailed, physics_device, simulate_frames  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class Setting(NamedTuple):
    """One way of solving the scene (``main``'s EDGE/LAGS[/SPLIT[/RTOL[/SLIP]]])."""

    edge_mm: float  # [mesh] contact_edge_mm
    lag_moves: int  # [physics] friction_lag_moves
    split: int = 1  # each frame solved as this many load steps (the trajectory's frames times SPLIT)
    force_rtol: float | None = None  # [physics] newton_force_rtol (0: off); None: the scene's
    slip_mm: float | None = None  # [physics] friction_slip_mm; None: --friction-slip-mm's, else the scene's

    def label(self) -> str:
        slip = f"/{self.slip_mm:g}" if self.slip_mm is not None else ""
        rtol = f"/{self.force_rtol:g}" if self.force_rtol is not None else ("/-" if slip else "")
        return f"{self.edge_mm:g}/{self.lag_moves}" + (f"/{self.split}" if self.split > 1 or rtol else "") + rtol + slip


def parse_setting(text: str) -> Setting:
    """"EDGE/LAGS[/SPLIT[/RTOL[/SLIP]]]" -> Setting (RTOL "-": the scene's)."""
    parts = text.strip().split("/")
    try:
        if len(parts) not in (2, 3, 4, 5):
            raise ValueError
        setting = Setting(float(parts[0]), int(parts[1]), int(parts[2]) if len(parts) >= 3 else 1,
                          float(parts[3]) if len(parts) >= 4 and parts[3] != "-" else None,
                          float(parts[4]) if len(parts) == 5 else None)
    except ValueError:
        raise typer.BadParameter(f"{text!r}: expected EDGE/LAGS, EDGE/LAGS/SPLIT, EDGE/LAGS/SPLIT/RTOL or "
                                 "EDGE/LAGS/SPLIT/RTOL/SLIP, e.g. 0.8/4, 0.8/4/2, 0.8/4/1/1e-3 or "
                                 "0.8/4/1/-/0.2") from None
    if setting.edge_mm <= 0 or setting.lag_moves < 1 or setting.split < 1:
        raise typer.BadParameter(f"{text!r}: EDGE must be > 0 mm, LAGS and SPLIT >= 1")
    if setting.force_rtol is not None and not 0.0 <= setting.force_rtol <= 0.1:
        raise typer.BadParameter(f"{text!r}: RTOL must be within [0, 0.1] (0: the force test off)")
    if setting.slip_mm is not None and not 0.0 < setting.slip_mm <= 1.0:
        raise typer.BadParameter(f"{text!r}: SLIP must be within (0, 1] mm ([physics] friction_slip_mm)")
    return setting


def with_split(setup, split: int):
    """The scene setup with every trajectory segment's frames times ``split``."""
    placed = []
    for p in setup.indenters:
        trajectory = [seg.model_copy(update={"frames": seg.frames * split}) for seg in p.config.trajectory]
        placed.append(dataclasses.replace(p, config=p.config.model_copy(update={"trajectory": trajectory})))
    return dataclasses.replace(setup, indenters=type(setup.indenters)(placed))


def with_setting(setup, setting: Setting, device: str, friction: float | None = None,
                 slip_mm: float | None = None):
    """The scene setup with the contact mesh size, lag moves and (where the setting names them) Newton's force test
    and friction's smoothing replaced, and if given the physics device, every indenter's friction coefficient and
    friction's smoothing (``slip_mm``, where the setting names none; not the split: ``solve`` splits the frames)."""
    if friction is not None:
        setup = with_friction(setup, friction)
    slip_mm = setting.slip_mm if setting.slip_mm is not None else slip_mm
    scene = setup.scene
    physics = scene.physics.model_copy(update={"friction_lag_moves": setting.lag_moves}
                                       | ({"device": device} if device else {})
                                       | ({"friction_slip_mm": slip_mm} if slip_mm is not None else {})
                                       | ({"newton_force_rtol": setting.force_rtol}
                                          if setting.force_rtol is not None else {}))
    mesh = scene.mesh.model_copy(update={"contact_edge_mm": setting.edge_mm})
    return dataclasses.replace(setup, scene=scene.model_copy(update={"physics": physics, "mesh": mesh}))


def p2_unknowns(tets: np.ndarray) -> int:
    """3 x (vertices + edges) of a P2 mesh."""
    edges = np.sort(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
    return 3 * (len(np.unique(tets)) + len(np.unique(edges, axis=0)))


def solve(setup, frames: int, split: int = 1) -> dict:
    """Solves ``frames`` frames of ``setup`` with each frame split into ``split`` load steps (``with_split``), on the
    unsplit scene's mesh: the mesh cache would mesh the split scene anew (its key holds the trajectory), and fTetWild
    makes another mesh. Within a segment of n frames, 0-based frame j is at (j + 1)/n of its motion, so frame f is the
    split scene's frame split (f + 1) - 1; its seconds, iterations and load steps are the sums over the split frames
    since the previously kept one. Returns per-frame markers (mm, gel frame), each indenter's force (N), seconds,
    iterations and load steps, and the mesh's size."""
    meshed = mesh_gel(setup)
    rows = {"markers": [], "forces": [], "seconds": [], "iterations": [], "substeps": []}
    seconds, iterations, steps = 0.0, 0, 0
    with mock.patch.object(meshing, "mesh_gel", lambda *args, **kwargs: meshed):  # simulation.py imports it per call
        solved = list(simulate_frames(with_split(setup, split), frames * split, StageClock()))
    for f in solved:
        seconds, iterations = seconds + float(f.solver["seconds"]), iterations + int(f.solver["iterations"])
        steps += int(f.solver["substeps"])
        if (f.frame + 1) % split:
            continue
        rows["markers"].append(np.asarray(f.markers_gel_mm).tolist())
        rows["forces"].append(np.asarray(f.forces_n).tolist())
        rows["seconds"].append(seconds)
        rows["iterations"].append(iterations)
        rows["substeps"].append(steps)
        seconds, iterations, steps = 0.0, 0, 0
    return rows | {"tets": int(len(meshed.mesh.tets)), "dofs": p2_unknowns(meshed.mesh.tets)}


def largest_displacement(ref: dict, rest_mm: np.ndarray) -> float:
    """The largest marker displacement from rest over the reference's frames (mm)."""
    return float(np.max(np.linalg.norm(np.array(ref["markers"]) - rest_mm, axis=2)))


def errors(row: dict, ref: dict, rest_mm: np.ndarray) -> dict:
    """Marker and force errors of ``row`` against ``ref`` over all frames (see the module docstring)."""
    m, m_ref = np.array(row["markers"]), np.array(ref["markers"])
    diff = np.linalg.norm(m - m_ref, axis=2)  # (frames, markers)
    scale = max(largest_displacement(ref, rest_mm), 1e-12)
    F, F_ref = np.array(row["forces"]), np.array(ref["forces"])  # (frames, indenters, 3)
    force = float(np.max(np.linalg.norm(F - F_ref, axis=-1)) / max(np.max(np.linalg.norm(F_ref, axis=-1)), 1e-12))
    rms = float(np.sqrt(np.mean(diff ** 2)))
    return {"marker_max_mm": float(diff.max()), "marker_rms_mm": rms, "marker_max_pct": 100 * float(diff.max()) / scale,
            "marker_max_per_frame_mm": diff.max(axis=1).tolist(),
            "marker_rms_pct": 100 * rms / scale, "force_max_pct": 100 * force, "largest_displacement_mm": scale}


def solved_with(setup) -> dict:
    """What a row records of the physics it solved with (``with_setting``'s setup): the force test's rtol (0: off) and
    friction's smoothing (mm)."""
    physics = setup.scene.physics
    return {"force_rtol": float(physics.newton_force_rtol or 0.0), "slip_mm": physics.friction_slip_mm}


def summary(row: dict) -> dict:
    """Median physics seconds per frame over frames 1..N-1 and median Newton iterations per frame."""
    return {"s_frame": statistics.median(row["seconds"][1:] or row["seconds"]),
            "iterations_median": statistics.median(row["iterations"])}


def plot(rows: list[dict], path: Path, title: str) -> None:
    """Marker error (RMS and largest) against physics seconds per frame, one line per (lag moves, split, force
    test, friction's smoothing: named in the legend where the rows differ in it), each point marked with its contact
    edge."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if "failed" not in r]
    slips_differ = len({line_of(r)[3] for r in rows}) > 1
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.2), dpi=90)
    for ax, key, label in ((axes[0], "marker_rms_mm", "marker error, RMS over frames and markers (mm)"),
                           (axes[1], "marker_max_mm", "marker error, largest (mm)")):
        for lags, split, rtol, slip in sorted({line_of(r) for r in rows}):
            pts = sorted((r["s_frame"], max(r[key], 1e-5), r["edge_mm"]) for r in rows
                         if line_of(r) == (lags, split, rtol, slip))
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", ms=5, lw=0.8,
                    label=f"{lags} lag move(s) a step" + (f", frames split in {split}" if split > 1 else "")
                    + (f", force test {rtol:g}" if rtol else "")
                    + (f", slip {slip:g} mm" if slip and slips_differ else ""))
            for t, e, h in pts:
                ax.annotate(f"edge {h:g} mm", (t, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # 1, 2 and 5 times powers of ten: a decade or less is on most axes here
            axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("physics seconds per frame (median)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
    handles, labels = axes[0].get_legend_handles_labels()  # one legend for both, below them: it hid points inside
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0.0, 0.04 * ((len(labels) + 2) // 3) + 0.02, 1.0, 1.0))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def measure(scene: Path, base, frames: int, chosen: list[Setting], ref_setting: Setting, device: str, gpu: bool,
            friction: float | None, slip_mm: float | None) -> dict:
    """Solves the reference and every chosen setting of ``base`` (the setup of ``scene``) after a 2-frame warm-up;
    the rows and what ``report`` needs."""
    def setup_of(setting: Setting):
        return with_setting(base, setting, device, friction, slip_mm)

    def described(setting: Setting, setup) -> dict:  # the setting, with the force test and smoothing it solved with
        return setting._asdict() | solved_with(setup)

    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    try:  # kernels loaded outside the timings; a setting that fails here gets its row below
        solve(setup_of(chosen[0]), 2, chosen[0].split)
    except SimulationFailed:
        pass
    rest = np.asarray(base.sensor.markers_rest_gel_mm)

    ref_setup = setup_of(ref_setting)
    try:
        ref = solve(ref_setup, frames, ref_setting.split)
    except SimulationFailed as e:
        raise SystemExit(f"the reference {ref_setting.label()} failed: {e}") from None
    ref |= described(ref_setting, ref_setup) | summary(ref)
    print(f"reference {ref_setting.label()}: {ref['tets']} tets, {ref['s_frame']:.2f} s/frame, {ref['iterations']}",
          flush=True)
    rows = []
    for setting in chosen:
        setup = setup_of(setting)
        try:
            r = solve(setup, frames, setting.split)
        except SimulationFailed as e:
            why = str(e) + (f" (counting the frames split in {setting.split})" if setting.split > 1 else "")
            rows.append(described(setting, setup) | {"failed": why})
            print(f"{setting.label()}: failed, {why}", flush=True)
            continue
        r |= described(setting, setup) | summary(r) | errors(r, ref, rest)
        rows.append(r)
        print(f"{setting.label()}: {r['tets']} tets, {r['s_frame']:.2f} s/frame, iterations {r['iterations']}, markers "
              f"max {r['marker_max_mm']:.4f} rms {r['marker_rms_mm']:.4f} mm, force {r['force_max_pct']:.2f} %",
              flush=True)
    scene_name = scene.resolve().relative_to(ROOT) if scene.resolve().is_relative_to(ROOT) else scene
    meta = {"machine": machine_name("cuda" if gpu else "cpu"), "gpu": gpu, "minutes": (time.perf_counter() - t0) / 60,
            "load": [load0, os.getloadavg()[0]], "cpus": os.cpu_count(), "scene": str(scene_name), "frames": frames,
            "markers": len(rest), "largest_displacement_mm": largest_displacement(ref, rest),
            "friction": friction, "slip_mm": slip_mm, "reference": ref_setting.label(),
            "friction_memory": solver_variants.friction_memory(),
            "command": ".venv/bin/python scripts/fem_slide_error_vs_runtime.py " + " ".join(sys.argv[1:])}
    return {"reference": ref, "rows": rows, "meta": meta}


def line_of(row: dict) -> tuple[int, int, float, float]:
    """A row's plotted line: (lag moves, split, the force test's rtol, friction's smoothing in mm). The rtol is 0 where
    the test was off; rtol and smoothing are 0 in rows of runs made before they were axes."""
    return row["lag_moves"], row["split"], row.get("force_rtol") or 0.0, row.get("slip_mm") or 0.0


def mean_seconds(row: dict) -> float:
    """Mean physics seconds per frame over frames 1..N-1 (the median, ``summary``, hides the slowest frames)."""
    return statistics.mean(row["seconds"][1:] or row["seconds"])


def rtol_cell(row: dict) -> str:
    return f"{row['force_rtol']:g}" if row.get("force_rtol") else "off"


def slip_cell(row: dict) -> str:
    return f"{row['slip_mm']:g}" if row.get("slip_mm") else "-"


def report(data: dict, name: str) -> str:
    """The BENCHMARKS.md section's markdown."""
    ref, rows, meta = data["reference"], data["rows"], data["meta"]
    header = ("| contact edge (mm) | lag moves a step | each frame split into | force test (rtol) | friction slip (mm) "
              "| tets | "
              "P2 unknowns | physics s / frame (median; mean) | Newton it. / frame (median; all frames) | "
              "load steps taken per frame | marker err max mm (%) | marker err RMS mm (%) | "
              "marker err max per frame (mm) | force err max (% of max force) |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in [*rows, ref]:
        if "failed" in r:
            lines.append(f"| {r['edge_mm']:g} | {r['lag_moves']} | {r['split']} | {rtol_cell(r)} | {slip_cell(r)} | "
                         f"failed: {r['failed']} |" + " |" * 8)
            continue
        cells = [f"{r['edge_mm']:g}" + (" (reference)" if r is ref else ""), str(r["lag_moves"]), str(r["split"]),
                 rtol_cell(r), slip_cell(r), str(r["tets"]), str(r["dofs"]),
                 f"{r['s_frame']:.2f}; {mean_seconds(r):.2f}",
                 f"{r['iterations_median']:g}; {', '.join(map(str, r['iterations']))}",
                 ", ".join(map(str, r["substeps"]))]
        cells += ["-"] * 4 if r is ref else [
            f"{r['marker_max_mm']:.4f} ({r['marker_max_pct']:.2f})",
            f"{r['marker_rms_mm']:.4f} ({r['marker_rms_pct']:.2f})",
            ", ".join(f"{e:.3f}" for e in r["marker_max_per_frame_mm"]), f"{r['force_max_pct']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    changed = (f"every indenter's friction set to {meta['friction']:g}, " if meta["friction"] is not None else "") + (
        f"friction_slip_mm {meta['slip_mm']:g} where a setting gives no SLIP, " if meta["slip_mm"] is not None
        else "") + (
        "" if meta.get("friction_memory", False) else "friction's sticking stretch not carried from step to step, ")
    return "\n".join([
        f"Machine: {meta['machine']}. Command: `{meta['command'].strip()}` ({meta['minutes']:.0f} min in all; load "
        f"average {meta['load'][0]:.1f} at the start, {meta['load'][1]:.1f} at the end, on {meta['cpus']} CPUs).",
        "",
        f"Scene: `{meta['scene']}`, {meta['frames']} frames, {changed}{meta['markers']} markers (largest reference "
        f"marker displacement {meta['largest_displacement_mm']:.3f} mm). Errors against the reference over all frames; "
        "see the script's docstring.",
        "",
        *lines,
        "",
        f"![FEM error against run time on the slide](docs/figures/{name}.png)",
    ])


def main(scene: Path = typer.Option(ROOT / "scenes" / "press_slide.toml"), frames: int = typer.Option(10, min=2),
         settings: str = typer.Option("1.2/4,1.0/4,0.8/4,0.8/1,0.65/4,0.5/4,0.4/4",
                                      help="EDGE/LAGS\\[/SPLIT\\[/RTOL\\[/SLIP]]], comma-separated: contact edge (mm) / "
                                      "lag moves / load steps a frame / Newton's force test (0: off; -, the "
                                      "default: the scene's) / friction's smoothing (mm; default: "
                                      "--friction-slip-mm's, else the scene's)"),
         reference: str = typer.Option("0.3/4", help="EDGE/LAGS\\[/SPLIT\\[/RTOL\\[/SLIP]]] of the reference solution"),
         device: str = typer.Option("", help="replace the scene's [physics] device (cpu, cuda)"),
         friction: float | None = typer.Option(None, min=0.0, help="replace every indenter's friction coefficient "
                                               "(0: frictionless); the names end in _friction_MU"),
         friction_slip_mm: float | None = typer.Option(None, min=1e-4, help="replace [physics] friction_slip_mm "
                                                       "(friction's smoothing); the names end in _slip_MM"),
         suffix: str = typer.Option("", help="appended to the section, plot and JSON names (e.g. load_steps)"),
         mesh_only: bool = typer.Option(False, help="mesh every setting (fills the mesh cache) and stop"),
         replot: bool = typer.Option(False, help="no solving: the section and plot again from out/<section>.json "
                                                 "(give the run's --device, --friction, --friction-slip-mm, "
                                                 "--no-friction-memory, --suffix)"),
         no_write: bool = typer.Option(False, help="print only: no BENCHMARKS.md, JSON or PNG"),
         friction_memory: bool = solver_variants.FRICTION_MEMORY_OPTION) -> None:
    solver_variants.solver_settings(friction_memory=friction_memory)
    chosen = [parse_setting(s) for s in settings.split(",") if s.strip()]
    if not chosen:
        raise typer.BadParameter("--settings names no setting")
    ref_setting = parse_setting(reference)
    base = load_setup(scene)
    if not base.has_contact:
        raise typer.BadParameter(f"{scene}: no indenter touches the gel, so there is no FEM to compare")
    if mesh_only:
        for edge in sorted({s.edge_mm for s in [ref_setting, *chosen]}):
            m = mesh_gel(with_setting(base, Setting(edge, 1), device)).mesh
            print(f"contact edge {edge:g} mm: {len(m.tets)} tets, {p2_unknowns(m.tets)} P2 unknowns", flush=True)
        return
    gpu = physics_device(device or base.scene.physics.device).startswith("cuda")
    name = "fem_slide_error_vs_runtime" + ("_gpu" if gpu else "") + (
        f"_friction_{friction:g}" if friction is not None else "") + (
        f"_slip_{friction_slip_mm:g}" if friction_slip_mm is not None else "") + (
        "" if friction_memory else "_no_memory") + (f"_{suffix}" if suffix else "")
    out = ROOT / "out" / f"{name}.json"
    if replot and not out.is_file():
        raise typer.BadParameter(f"--replot reads {out}, which does not exist (same --device, --friction, "
                                 "--friction-slip-mm, --no-friction-memory and --suffix as the run?)")
    data = json.loads(out.read_text()) if replot else measure(scene, base, frames, chosen, ref_setting, device, gpu,
                                                               friction, friction_slip_mm)
    body = report(data, name)
    print(body)
    if no_write:
        return
    if not replot:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(data))
    meta = data["meta"]
    plot(data["rows"], ROOT / "docs" / "figures" / f"{name}.png",
         f"{Path(meta['scene']).stem} FEM error vs run time, {meta['machine']}, reference {meta['reference']}"
         + (f", friction {meta['friction']:g}" if meta["friction"] is not None else "")
         + (f", slip {meta['slip_mm']:g} mm" if meta["slip_mm"] is not None else ""))
    update_section(ROOT / "BENCHMARKS.md", name, body)


if __name__ == "__main__":
    typer.run(main)
