"""FEM error against run time: element order x mesh size x Newton tolerance on the standard press scene.

    .venv/bin/python scripts/fem_error_vs_runtime.py [--device cpu|cuda] [--quick] [--no-write]
                                                    [--reference-json out/fem_error_vs_runtime_cpu.json]
                                                    [--out-md BENCHMARKS.md] [--out-png docs/figures/...png]

Standard press scene (the block of ``scripts/bench_fem.py``): a 20 x 20 x 5 mm Solaris gel (E 0.37 MPa,
nu 0.49, bonded bottom) and a rigid frictionless sphere (R 3 mm, icosphere with 6 subdivisions: facets
0.06 mm, sag 1e-4 mm) pressed 0.6 mm into the centre in two frames (0.3 mm, 0.6 mm; contact radius about
1.3 mm at the end). The press is symmetric, so the quarter x, y >= 0 is solved with u_x = 0 on x = 0 and
u_y = 0 on y = 0 (exact for a frictionless vertical press, and 4x fewer unknowns than the whole block:
s/frame is that of the quarter model, about a quarter of the whole block's at the same resolution).
Mesh: ``box_mesh`` structured graded tets, size h under the sphere (over 2 mm laterally and in the top
2 mm), growing by 1.5 per cell outside. Markers: a 8 x 8 grid at 0.25 ... 3.75 mm (x, y), 0.6 mm below
the surface (the hardware model's marker depth), read with ``displacement_at``.

Per setting (order P1/P2, h, newton_tol): tets, dofs, seconds per frame (mean of the two frames; kernels
are loaded by a warm-up solve first), and at 0.6 mm the marker displacement error against the reference
(finest P2: h 0.25 mm, 0.5 mm with --quick; newton_tol 1e-6: max and RMS over markers of |u - u_ref|, mm and % of the largest reference
marker displacement), the total force error against the reference and against the bonded-layer formula
(Dimitriadis et al. 2002, linear elastic, small strain: at d/R = 0.2 and chi = sqrt(R d)/h = 0.27 it is
itself an approximation, a few %, so the reference column is the one that measures discretisation error).
The table, the Pareto front (s/frame against marker RMS error) and the chosen default go to BENCHMARKS.md
(section ``fem_error_vs_runtime``, or ``fem_error_vs_runtime_gpu`` for --device cuda, so the CPU results
stay) and the plot to docs/figures/fem_error_vs_runtime[_gpu].png. Raw rows: out/fem_error_vs_runtime_<device>[_quick].json
(``--replot`` makes the table and plot again from it without solving).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.meshing.embedding import embed_points  # noqa: E402
from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, SolverSettings  # noqa: E402
from transtac_sim.physics.analytic import bonded_layer_force, hertz_force  # noqa: E402
from transtac_sim.physics.box_mesh import box_tet_mesh, graded_coordinates  # noqa: E402
from transtac_sim.physics.solver import SolverDidNotConverge  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HALF_WIDTH, THICKNESS, FINE, GROWTH = 10.0, 5.0, 2.0, 1.5
RADIUS, DEPTHS = 3.0, (0.3, 0.6)
MATERIAL = ElasticMaterial(0.37, 0.49)
MARKER_DEPTH = 0.6
# The default: the fastest setting whose markers are within MAX_MARKER_ERR_PCT (max over markers, % of the largest
# marker displacement: 3 % is ~0.014 mm here) and whose force is within MAX_FORCE_ERR_PCT of the reference, among
# newton_tol <= MAX_DEFAULT_TOL: a looser tolerance can stop Newton early where the line search damps the steps
# (a stiff contact: the Hertz test of tests/test_physics_contact_accuracy.py came out 13 % off at 1e-4 and 40 %
# at 1e-3 with a 5000 N/mm^3 penalty), so it is not taken as a default even where it is accurate here.
MAX_MARKER_ERR_PCT, MAX_FORCE_ERR_PCT, MAX_DEFAULT_TOL = 3.0, 2.0, 1e-4


def quarter_block(h: float):
    xs = graded_coordinates(0.0, HALF_WIDTH, h, 0.0, FINE, GROWTH)
    zs = graded_coordinates(0.0, THICKNESS, h, THICKNESS - FINE, THICKNESS, GROWTH)
    V, T = box_tet_mesh(xs, xs, zs)
    fixed = np.stack([V[:, 0] < 1e-9, V[:, 1] < 1e-9, np.zeros(len(V), dtype=bool)], axis=1)
    fixed |= (V[:, 2] < 1e-9)[:, None]  # bonded bottom
    return V, T, fixed


def markers() -> np.ndarray:
    g = np.arange(0.25, 4.0, 0.5)
    X, Y = np.meshgrid(g, g, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, THICKNESS - MARKER_DEPTH)])


def run(degree: int, h: float, tol: float, device: str, sphere: RigidIndenter, halvings: int = 5,
        linear_solver: str = "auto") -> dict:
    V, T, fixed = quarter_block(h)
    emb = embed_points(V, T, markers())
    # the step-length test alone: this table's axis is newton_tol_mm (the force test's error against run time is
    # scripts/fem_slide_error_vs_runtime.py's EDGE/LAGS/SPLIT/RTOL)
    solver = QuasiStaticSolver(V, T, MATERIAL, [sphere], SolverSettings(degree=degree, newton_tol_mm=tol,
                                                                    max_substep_halvings=halvings,
                                                                    linear_solver=linear_solver,
                                                                    newton_force_rtol=None),
                               device=device, fixed=fixed)
    pose = np.eye(4)
    pose[2, 3] = THICKNESS + RADIUS + 1e-3
    solver.start([pose])
    seconds, iterations = [], []
    row = {"degree": degree, "h": h, "tol": tol, "tets": len(T), "dofs": 3 * solver._space.node_count()}
    for d in DEPTHS:
        pose = pose.copy()
        pose[2, 3] = THICKNESS + RADIUS - d
        try:
            res = solver.solve_frame([pose])
        except SolverDidNotConverge as e:
            print(f"P{degree} h {h} tol {tol:g}: {e}", flush=True)
            return row | {"failed": str(e).split(";")[0]}
        seconds.append(res.record.seconds)
        iterations.append(res.record.iterations)
    return row | {
            "s_frame": float(np.mean(seconds)), "iterations": float(np.mean(iterations)),
            "force": float(-4.0 * res.forces_n[0, 2]), "markers": solver.displacement_at(emb.tet_index,
                                                                                          emb.barycentric).tolist()}


def settings(quick: bool):
    """(degree, h, tol) of the sweep and of the reference."""
    if quick:
        sweep = [(1, 0.7, 1e-4), (1, 0.5, 1e-4), (2, 1.0, 1e-4), (2, 0.7, 1e-4), (2, 1.0, 1e-3), (2, 1.0, 1e-5)]
        return sweep, (2, 0.5, 1e-6)
    sweep = [(1, h, 1e-4) for h in (0.7, 0.5, 0.35, 0.25)] + [(1, 0.35, 1e-3), (1, 0.35, 1e-5)]
    sweep += [(2, h, 1e-4) for h in (1.0, 0.7, 0.5, 0.35)] + [(2, 0.5, 1e-3), (2, 0.5, 1e-5), (2, 0.7, 1e-3),
                                                              (2, 0.7, 1e-5)]
    return sweep, (2, 0.25, 1e-6)


def errors(row: dict, ref: dict) -> dict:
    u, u_ref = np.array(row["markers"]), np.array(ref["markers"])
    diff = np.linalg.norm(u - u_ref, axis=1)
    scale = float(np.max(np.linalg.norm(u_ref, axis=1)))
    formula = float(bonded_layer_force(MATERIAL.young_mpa, MATERIAL.poisson, RADIUS, DEPTHS[-1], THICKNESS))
    return {"marker_max_mm": float(diff.max()), "marker_rms_mm": float(np.sqrt(np.mean(diff**2))),
            "marker_max_pct": 100 * float(diff.max()) / scale, "marker_rms_pct": 100 * float(np.sqrt(np.mean(diff**2))) / scale,
            "force_ref_pct": 100 * (row["force"] / ref["force"] - 1.0), "force_formula_pct": 100 * (row["force"] / formula - 1.0)}


def pareto(points):
    return [i for i, (t, e) in enumerate(points)
            if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in points)]


def plot(rows, ref, front, choice, path: Path, title: str) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), dpi=90)
    for ax, key, label in ((axes[0], "marker_rms_pct", "marker displacement error, RMS (% of max |u|)"),
                           (axes[1], "force_ref_pct", "|force error| vs reference (%)")):
        for degree, colour in ((1, "tab:blue"), (2, "tab:red")):
            for tol, marker in ((1e-3, "v"), (1e-4, "o"), (1e-5, "^")):
                pts = sorted((r["s_frame"], max(abs(r[key]), 1e-4), r["h"]) for r in rows
                             if r["degree"] == degree and r["tol"] == tol)
                if not pts:
                    continue
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker + ("-" if tol == 1e-4 else ""),
                        color=colour, ms=5, lw=0.8, label=f"P{degree}, tol {tol:g} mm")
                if tol == 1e-4:
                    for t, e, h in pts:
                        ax.annotate(f"h {h:g}", (t, e), fontsize=6, xytext=(3, 3), textcoords="offset points")
        f = sorted((rows[i]["s_frame"], max(abs(rows[i][key]), 1e-4)) for i in front)
        ax.plot([p[0] for p in f], [p[1] for p in f], "k--", lw=1.0,
                label=f"Pareto front (marker RMS, tol <= {MAX_DEFAULT_TOL:g})")
        if choice is not None:
            ax.plot(choice["s_frame"], max(abs(choice[key]), 1e-4), "*", color="gold", mec="k", ms=14,
                    label="default", zorder=5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("seconds per frame")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.legend(*axes[0].get_legend_handles_labels(), loc="lower center", ncol=4, fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--quick", action="store_true", help="coarser sweep and reference (a few minutes on 2 CPU cores)")
    ap.add_argument("--no-write", action="store_true", help="print only; no BENCHMARKS.md, no PNG")
    ap.add_argument("--out-md", type=Path, default=ROOT / "BENCHMARKS.md")
    ap.add_argument("--out-png", type=Path, default=None,
                    help="default docs/figures/fem_error_vs_runtime.png (cpu) or ..._gpu.png (cuda)")
    ap.add_argument("--note", default="", help="a sentence added to the BENCHMARKS.md section (e.g. machine shared)")
    ap.add_argument("--linear-solver", choices=("auto", "direct", "cg"), default="auto",
                    help="auto: cg on a GPU, direct on the CPU")
    ap.add_argument("--reference-json", type=Path, default=None,
                    help="take the reference from this earlier run's JSON (e.g. the CPU run's) instead of solving it")
    ap.add_argument("--replot", action="store_true",
                    help="no solving: table and plot again from out/fem_error_vs_runtime_<device>[_quick].json")
    a = ap.parse_args()
    png = a.out_png or ROOT / "docs" / "figures" / f"fem_error_vs_runtime{'_gpu' if a.device == 'cuda' else ''}.png"
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=6, radius=RADIUS))
    sweep, ref_setting = settings(a.quick)

    out_json = ROOT / "out" / f"fem_error_vs_runtime_{a.device}{'_quick' if a.quick else ''}.json"
    if a.replot:
        data = json.loads(out_json.read_text())
    else:
        data = measure(a, sweep, ref_setting, sphere)
        out_json.parent.mkdir(parents=True, exist_ok=True)
        out_json.write_text(json.dumps(data, indent=1))
    ref, rows, failed, meta = data["reference"], data["rows"], data["failed"], data["meta"]
    report(a, ref, rows, failed, meta, png)


def measure(a, sweep, ref_setting, sphere) -> dict:
    t_start, load_start = time.perf_counter(), os.getloadavg()[0]
    for degree in (1, 2):  # warm-up: kernel compilation / loading is not part of the timings
        run(degree, 0.7, 1e-4, a.device, sphere, linear_solver=a.linear_solver)
    if a.reference_json:  # the reference solution does not depend on the device: solve it once, on the CPU
        ref = {k: v for k, v in json.loads(a.reference_json.read_text())["reference"].items()
               if k in ("degree", "h", "tol", "tets", "dofs", "s_frame", "iterations", "force", "markers")}
    else:
        ref = run(*ref_setting, a.device, sphere, halvings=1, linear_solver=a.linear_solver)
    if "failed" in ref:  # Newton could not reach 1e-6 mm: a looser reference rather than none
        ref = run(*ref_setting[:2], 1e-5, a.device, sphere, linear_solver=a.linear_solver)
    if "failed" in ref:
        raise SystemExit(f"the reference did not converge: {ref['failed']}")
    print(f"reference P{ref['degree']} h {ref['h']}: {ref['dofs']} dofs, {ref['s_frame']:.1f} s/frame, "
          f"force {ref['force']:.4f} N", flush=True)
    rows, failed = [], []
    for s in sweep:
        r = run(*s, a.device, sphere, linear_solver=a.linear_solver)
        if "failed" in r:
            failed.append(r)
            continue
        r |= errors(r, ref)
        rows.append(r)
        print(f"P{r['degree']} h {r['h']} tol {r['tol']:g}: {r['dofs']} dofs, {r['s_frame']:.2f} s/frame, "
              f"markers max {r['marker_max_pct']:.2f} % rms {r['marker_rms_pct']:.2f} %, force vs ref "
              f"{r['force_ref_pct']:+.2f} %, vs formula {r['force_formula_pct']:+.2f} %", flush=True)
    ref |= errors(ref, ref)
    argv = [x for x in sys.argv[1:] if x != "--note"]
    if "--note" in sys.argv:
        argv = [x for x in argv if x != sys.argv[sys.argv.index("--note") + 1]]
    meta = {"minutes": (time.perf_counter() - t_start) / 60, "load_start": load_start, "load_end": os.getloadavg()[0],
            "cpus": os.cpu_count(), "command": ".venv/bin/python scripts/fem_error_vs_runtime.py " + " ".join(argv)}
    return {"reference": ref, "rows": rows, "failed": failed, "meta": meta}


def report(a, ref, rows, failed, meta, png: Path) -> None:
    gpu = a.device == "cuda"
    # The front is taken over the settings that may be the default (newton_tol <= MAX_DEFAULT_TOL); errors that
    # agree to 2 significant digits count as equal (the tolerance variants differ only by round-off).
    admissible = [i for i, r in enumerate(rows) if r["tol"] <= MAX_DEFAULT_TOL]
    front = {admissible[i] for i in pareto([(rows[j]["s_frame"], float(f"{rows[j]['marker_rms_pct']:.2g}"))
                                            for j in admissible])}
    ok = [r for r in rows if r["marker_max_pct"] <= MAX_MARKER_ERR_PCT and abs(r["force_ref_pct"]) <= MAX_FORCE_ERR_PCT
          and r["tol"] <= MAX_DEFAULT_TOL]
    choice = min(ok, key=lambda r: r["s_frame"]) if ok else None

    header = ("| order | h (mm) | newton tol (mm) | tets | dofs | s / frame | Newton it. / frame | marker err max mm (%) "
              "| marker err RMS mm (%) | force err vs ref % | force err vs formula % | Pareto |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]

    def line(r, mark):
        return (f"| P{r['degree']} | {r['h']:g} | {r['tol']:g} | {r['tets']} | {r['dofs']} | {r['s_frame']:.2f} | "
                f"{r['iterations']:.1f} | {r['marker_max_mm']:.4f} ({r['marker_max_pct']:.2f}) | "
                f"{r['marker_rms_mm']:.4f} ({r['marker_rms_pct']:.2f}) | {r['force_ref_pct']:+.2f} | "
                f"{r['force_formula_pct']:+.2f} | {mark} |")

    for i, r in enumerate(rows):
        lines.append(line(r, ("*" if i in front else "") + (" default" if r is choice else "")))
    lines.append(line(ref, "reference"))
    for r in failed:
        lines.append(f"| P{r['degree']} | {r['h']:g} | {r['tol']:g} | {r['tets']} | {r['dofs']} | failed: "
                     f"{r['failed']} | | | | | | |")
    formula = float(bonded_layer_force(MATERIAL.young_mpa, MATERIAL.poisson, RADIUS, DEPTHS[-1], THICKNESS))
    hertz = float(hertz_force(MATERIAL.young_mpa, MATERIAL.poisson, RADIUS, DEPTHS[-1]))
    chosen = (f"Default (the fastest setting with marker error max <= {MAX_MARKER_ERR_PCT:g} % of the largest marker "
              f"displacement, force within {MAX_FORCE_ERR_PCT:g} % of the reference and newton_tol <= "
              f"{MAX_DEFAULT_TOL:g} mm, see the script): **P{choice['degree']}, "
              f"h {choice['h']:g} mm, newton_tol {choice['tol']:g} mm** ({choice['s_frame']:.2f} s/frame)."
              if choice else "No setting met the default's criteria.")
    rel = png.resolve().relative_to(a.out_md.resolve().parent) if png.resolve().is_relative_to(
        a.out_md.resolve().parent) else png
    body = "\n".join([
        f"Machine: {machine_name(a.device)}. Command: `{meta['command'].strip()}` ({meta['minutes']:.0f} min in all; "
        f"load average {meta['load_start']:.1f} at the start, {meta['load_end']:.1f} at the end, on {meta['cpus']} "
        f"CPUs). {a.note}".strip(),
        "",
        f"Scene: quarter model of a 20 x 20 x 5 mm bonded Solaris gel (E {MATERIAL.young_mpa} MPa, nu "
        f"{MATERIAL.poisson}), frictionless sphere R {RADIUS} mm pressed {DEPTHS[0]} then {DEPTHS[1]} mm (2 frames); "
        f"errors at {DEPTHS[1]} mm; 64 markers {MARKER_DEPTH} mm deep (largest reference marker displacement "
        f"{np.max(np.linalg.norm(ref['markers'], axis=1)):.3f} mm). h: element size under the sphere. Reference: "
        f"P{ref['degree']}, h {ref['h']:g} mm, newton_tol {ref['tol']:g} mm, force {ref['force']:.4f} N (bonded-layer "
        f"formula {formula:.4f} N, Hertz half-space {hertz:.4f} N). Seconds per frame of the quarter model (the "
        "whole block has about 4x the unknowns). Pareto: on the front of s/frame against marker RMS error among the "
        f"settings with newton_tol <= {MAX_DEFAULT_TOL:g} mm (looser ones are not default candidates, see the "
        "script). See the script's docstring for details.",
        "",
        *lines,
        "",
        chosen,
        "",
        f"![FEM error against run time]({rel})",
    ])
    print(body)
    if not a.no_write:
        plot(rows, ref, front, choice, png, f"FEM error vs run time, {machine_name(a.device)} ({a.device}), quarter press "
             f"scene, reference P{ref['degree']} h {ref['h']:g}")
        update_section(a.out_md, "fem_error_vs_runtime_gpu" if gpu else "fem_error_vs_runtime", body)


if __name__ == "__main__":
    main()
