"""Stability sweep of the quasi-static FEM: materials, depths, sharp indenters, friction, bad starts.

Each case presses (and possibly slides) a rigid indenter into a gel block (graded P2 mesh, the bottom
face bonded) and reports: outcome (converged / the solver's error), NaN check, min det F over all
frames, the largest penetration and sub-step count of any frame, Newton iterations and seconds.
The full run writes a markdown table into BENCHMARKS.md (section ``fem_stability``; ``fem_stability_gpu`` with a GPU).

    .venv/bin/python scripts/fem_stability.py [--quick] [--device cpu|cuda] [--only NAME ...] [--max-newton-iterations N]
        [--newton-force-rtol R] [--no-progress-steps N] [--linear-solver auto|direct|cg]

``--quick`` uses a coarser mesh and prints the table without writing BENCHMARKS.md.
The case definitions and ``run_case`` are shared with tests/test_physics_stability.py (which runs them
on a smaller, coarser block).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.indenters import library  # noqa: E402
from transtac_sim.physics import (  # noqa: E402
    ElasticMaterial,
    IndenterStartsInsideGel,
    QuasiStaticSolver,
    RigidIndenter,
    SolverDidNotConverge,
    SolverSettings,
)
from transtac_sim.physics.box_mesh import gel_block  # noqa: E402


@dataclass(frozen=True)
class Block:
    """Gel block [-w/2, w/2]^2 x [0, t] (mm), mesh spacing h on the top centre (|x|, |y| < fine_half_width)."""

    width: float = 10.0
    thickness: float = 5.0
    h_fine: float = 0.6
    h_fine_z: float | None = None
    fine_half_width: float = 3.0
    growth: float = 1.6
    degree: int = 2

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        return gel_block(self.width, self.width, self.thickness, h_fine=self.h_fine,
                         fine_half_width=self.fine_half_width, growth=self.growth, h_fine_z=self.h_fine_z)


FULL = Block(h_fine=0.85, h_fine_z=1.0)  # 0.75 mm cells on the central 6 mm (8 across), ~12k dofs
QUICK = Block(h_fine=1.0, h_fine_z=1.0)


@dataclass(frozen=True)
class Case:
    """One stability case; lengths of the indenter and the press are relative to the block thickness t."""

    name: str
    young_mpa: float = 0.5
    poisson: float = 0.45
    backing: bool = False  # bottom 20 % of the block is a layer 1000x stiffer (nu 0.3)
    shape: str = "sphere"  # sphere (radius 0.6 t), cube_edge (edge 0.8 t, an edge down), cone (tip down),
    # rounded_cone (the same, tip radius 0.1 t), flat_punch (radius 0.4 t)
    friction: float = 0.0
    depth: float = 0.3  # press depth below first contact, fraction of t
    step: float = 0.1  # press increment per frame, fraction of t
    slide_frames: int = 0  # after the press, slide along +x by slide_step * t per frame
    slide_step: float = 0.1
    start_gap: float = 2e-4  # start height of the lowest indenter point above the gel, fraction of t
    expect_error: str | None = None  # the honest outcome is this error class (e.g. starts inside the gel)

    def key(self) -> tuple:
        """Cases with equal keys are the same computation (run once, listed under each name)."""
        return tuple(v for k, v in self.__dict__.items() if k not in ("name", "expect_error"))


def make_indenter(shape: str, thickness: float, friction: float) -> RigidIndenter:
    s = thickness / 5.0  # sizes below are for a 5 mm gel
    if shape == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=3.0 * s)
    elif shape == "cube_edge":  # a cube turned 45 deg about x: an edge along x points down
        mesh = trimesh.creation.box(extents=(4.0 * s, 4.0 * s, 4.0 * s))
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [1, 0, 0]))
    elif shape == "cone":  # half-angle 37 deg, tip down at local (0, 0, -4 s)
        mesh = trimesh.creation.cone(radius=3.0 * s, height=4.0 * s, sections=32)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    elif shape == "rounded_cone":  # the library's cone: the same, its tip rounded to 0.5 mm (scaled with s)
        mesh = library.cone(radius_mm=3.0 * s, height_mm=4.0 * s, tip_radius_mm=0.5 * s)
    elif shape == "flat_punch":  # the library's flat punch, radius 2 mm: its sharp rim on the fine mesh
        mesh = library.flat_punch(radius_mm=2.0 * s, height_mm=4.0 * s)
    else:
        raise ValueError(f"unknown indenter shape {shape!r}")
    return RigidIndenter.from_trimesh(shape, mesh, friction)


def trajectory(case: Case, ind: RigidIndenter, thickness: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """Start pose and the per-frame poses: press in equal increments, then slide along +x."""
    start = np.eye(4)
    start[2, 3] = thickness - ind.lowest_z(np.eye(4)) + case.start_gap * thickness
    depth = (case.depth + case.start_gap) * thickness  # below the first contact
    n_press = max(1, math.ceil(case.depth / case.step - 1e-9))
    poses = []
    for k in range(1, n_press + 1):
        P = start.copy()
        P[2, 3] -= depth * k / n_press
        poses.append(P)
    for _ in range(case.slide_frames):
        P = poses[-1].copy()
        P[0, 3] += case.slide_step * thickness
        poses.append(P)
    return start, poses


@dataclass
class CaseResult:
    case: Case
    frames: list[dict] = field(default_factory=list)  # per solved frame, see run_case
    error: Exception | None = None
    seconds: float = 0.0
    dofs: int = 0

    @property
    def converged(self) -> bool:
        return self.error is None and all(f["converged"] for f in self.frames)


def build_solver(case: Case, block: Block, device: str = "cpu", max_newton_iterations: int | None = None,
                 newton_force_rtol: float | None = None, no_progress_steps: int | None = None,
                 linear_solver: str | None = None):
    V, T = block.mesh()
    materials = [ElasticMaterial(case.young_mpa, case.poisson)]
    material_index = None
    backing_vertices = np.zeros(len(V), dtype=bool)
    if case.backing:
        z_interface = 0.2 * block.thickness
        materials.append(ElasticMaterial(1000.0 * case.young_mpa, 0.3))
        material_index = (V[T].mean(axis=1)[:, 2] < z_interface).astype(int)
        in_gel = np.zeros(len(V), dtype=bool)
        in_gel[T[material_index == 0].ravel()] = True
        backing_vertices = ~in_gel  # vertices of backing tets only (the interface belongs to the gel)
    ind = make_indenter(case.shape, block.thickness, case.friction)
    replaced = {name: value for name, value in (("newton_no_progress_steps", no_progress_steps),
                                                ("linear_solver", linear_solver)) if value is not None}
    settings = SolverSettings(degree=block.degree, max_newton_iterations=max_newton_iterations,
                              newton_force_rtol=newton_force_rtol, **replaced)
    solver = QuasiStaticSolver(V, T, materials, [ind], settings, device=device, material_index=material_index)
    return solver, V, ind, backing_vertices


def run_case(case: Case, block: Block, device: str = "cpu", verbose: bool = False,
             max_newton_iterations: int | None = None, newton_force_rtol: float | None = None,
             no_progress_steps: int | None = None, linear_solver: str | None = None) -> CaseResult:
    """Run one case (``max_newton_iterations``: replaces the solver's default cap per (sub)step;
    ``newton_force_rtol``: Newton's force test, as scenes take it, config/scene.py; ``no_progress_steps``: replaces
    SolverSettings.newton_no_progress_steps; ``linear_solver``: replaces SolverSettings.linear_solver); a
    SolverDidNotConverge / IndenterStartsInsideGel ends it and is kept in ``error``.

    Per frame: converged, iterations, substeps, min_det_f, max_penetration_mm, seconds, finite (no NaN
    in the displacement), fz, fx (N, on the gel), max_u_mm (all vertices), max_u_backing_mm."""
    solver, V, ind, backing = build_solver(case, block, device, max_newton_iterations, newton_force_rtol,
                                           no_progress_steps, linear_solver)
    out = CaseResult(case, dofs=3 * len(solver.nodal_displacement()))
    start, poses = trajectory(case, ind, block.thickness)
    t0 = time.perf_counter()
    try:
        solver.start([start])
        for k, P in enumerate(poses):
            r = solver.solve_frame([P])
            u = r.displacement_mm
            norm = np.linalg.norm(u, axis=1)
            rec = r.record
            out.frames.append({
                "converged": rec.converged, "iterations": rec.iterations, "substeps": rec.substeps,
                "min_det_f": rec.min_det_f, "max_penetration_mm": rec.max_penetration_mm,
                "seconds": rec.seconds, "finite": bool(np.all(np.isfinite(u)) and np.all(np.isfinite(r.forces_n))),
                "fz": float(r.forces_n[0, 2]), "fx": float(r.forces_n[0, 0]),
                "max_u_mm": float(np.max(norm)),
                "max_u_backing_mm": float(np.max(norm[backing])) if backing.any() else 0.0,
            })
            if verbose:
                f = out.frames[-1]
                print(f"    frame {k}: it {rec.iterations} sub {rec.substeps} detF {rec.min_det_f:.3f} "
                      f"pen {rec.max_penetration_mm:.2g} fz {f['fz']:.4g} fx {f['fx']:.4g} {rec.seconds:.1f} s",
                      flush=True)
    except (SolverDidNotConverge, IndenterStartsInsideGel) as e:
        out.error = e
        if verbose:
            print(f"    {type(e).__name__}: {e}", flush=True)
    out.seconds = time.perf_counter() - t0
    return out


def cases() -> list[Case]:
    """Every case of the issue. The base case is E 0.5 MPa, nu 0.45, a sphere pressed to 30 %."""
    out = [Case(f"nu = {nu}", poisson=nu) for nu in (0.3, 0.45, 0.49, 0.499)]
    out += [Case(f"E = {E} MPa", young_mpa=E) for E in (0.05, 0.5, 5.0)]
    out += [Case("gel on a 1000x stiffer backing", backing=True)]
    out += [Case(f"depth {round(d * 100)} % of thickness", depth=d) for d in (0.1, 0.3, 0.5)]
    out += [Case("cube edge, 30 %", shape="cube_edge"), Case("cone tip, 30 %", shape="cone")]
    out += [Case("cone tip rounded to 0.5 mm, 30 %", shape="rounded_cone"),
            Case("flat punch (its rim), 30 %", shape="flat_punch")]
    out += [Case(f"{what}, 30 % + slide mu = 1.0 (4 x 0.5 mm)", shape=shape, friction=1.0, slide_frames=4)
            for what, shape in (("cube edge", "cube_edge"), ("cone tip rounded to 0.5 mm", "rounded_cone"),
                                ("flat punch", "flat_punch"))]
    out += [Case(f"slide mu = {mu} (20 % deep, 4 x 0.5 mm)", friction=mu, depth=0.2, slide_frames=4)
            for mu in (0.2, 1.0)]
    out += [Case("starts 1 mm inside the gel", start_gap=-0.2, expect_error="IndenterStartsInsideGel")]
    return out


def outcome(r: CaseResult) -> str:
    if r.error is None:
        return "converged" if r.converged else "NOT converged"
    msg = str(r.error).replace("|", "/")
    return f"{type(r.error).__name__}: {msg}"


def table_row(name: str, r: CaseResult, thickness: float, same_as: str | None) -> str:
    c = r.case
    fr = r.frames
    n_press = max(1, math.ceil(c.depth / c.step - 1e-9))
    inc = f"{n_press} x {(c.depth + c.start_gap) * thickness / n_press:.2g}" if c.start_gap >= 0 else "-"
    if c.slide_frames:
        inc += f" + {c.slide_frames} x {c.slide_step * thickness:.2g} slide"
    cells = [
        name, outcome(r) if same_as is None else f"{outcome(r).split(':')[0]} (same run as {same_as})",
        inc, f"{len(fr)}",
        "yes" if any(not f["finite"] for f in fr) else "no",
        f"{min(f['min_det_f'] for f in fr):.3f}" if fr else "-",
        f"{max(f['max_penetration_mm'] for f in fr):.4f}" if fr else "-",
        f"{max(f['substeps'] for f in fr)}" if fr else "-",
        f"{sum(f['iterations'] for f in fr)}" if fr else "-",
        f"{fr[-1]['fz']:.4g}" if fr else "-",
        f"{fr[-1]['fx']:.3g}" if fr else "-",
        f"{r.seconds:.1f}",
    ]
    return "| " + " | ".join(cells) + " |"


HEADER = [
    "| case | outcome | press (+ slide) frames x mm | frames solved | NaN | min det F | max penetration (mm) "
    "| max substeps | Newton iters | Fz last (N) | Fx last (N) | s |",
    "|---|---|---|---|---|---|---|---|---|---|---|---|",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="coarse mesh; print only, BENCHMARKS.md untouched")
    parser.add_argument("--only", nargs="*", help="run only the cases whose name contains one of these")
    parser.add_argument("-v", "--verbose", action="store_true", help="print every frame")
    parser.add_argument("--max-newton-iterations", type=int, default=None,
                        help="Newton's cap per (sub)step instead of the solver's default; prints only, BENCHMARKS.md untouched")
    parser.add_argument("--newton-force-rtol", type=float, default=None,
                        help="Newton's force test (SolverSettings.newton_force_rtol; scenes take 3e-3) instead of the "
                        "step-length test alone; prints only, BENCHMARKS.md untouched")
    parser.add_argument("--no-progress-steps", type=int, default=None,
                        help="SolverSettings.newton_no_progress_steps instead of its default of 30 (0: off); prints "
                        "only, BENCHMARKS.md untouched")
    parser.add_argument("--linear-solver", choices=("auto", "direct", "cg"), default=None,
                        help="SolverSettings.linear_solver instead of its default (cg on the CPU: the device path's "
                        "solver, deterministic there); prints only, BENCHMARKS.md untouched")
    args = parser.parse_args()
    if args.no_progress_steps is not None and args.no_progress_steps < 0:
        parser.error(f"--no-progress-steps {args.no_progress_steps}: expected 0 (off) or more")
    if args.newton_force_rtol is not None and not 0.0 <= args.newton_force_rtol <= 0.1:
        parser.error(f"--newton-force-rtol {args.newton_force_rtol:g}: expected a value within [0, 0.1]")

    block = QUICK if args.quick else FULL
    todo = [c for c in cases() if not args.only or any(s in c.name for s in args.only)]
    V, _ = block.mesh()
    print(f"block {block}: {len(V)} vertices", flush=True)
    lines = list(HEADER)
    done: dict[tuple, tuple[str, CaseResult]] = {}
    results: list[CaseResult] = []
    t_all = time.perf_counter()
    for case in todo:
        same_as = None
        if case.key() in done:
            same_as, r = done[case.key()]
        else:
            print(f"{case.name} ...", flush=True)
            r = run_case(case, block, args.device, verbose=args.verbose,
                         max_newton_iterations=args.max_newton_iterations, newton_force_rtol=args.newton_force_rtol,
                         no_progress_steps=args.no_progress_steps, linear_solver=args.linear_solver)
            done[case.key()] = (case.name, r)
        results.append(r)
        line = table_row(case.name, r, block.thickness, same_as)
        print(line, flush=True)
        lines.append(line)
    total = time.perf_counter() - t_all
    print(f"total {total:.0f} s", flush=True)
    if (args.quick or args.only or args.max_newton_iterations is not None or args.newton_force_rtol is not None
            or args.no_progress_steps is not None or args.linear_solver is not None):
        return
    head = (
        f"Machine: {machine_name(args.device)}. Command: `.venv/bin/python scripts/fem_stability.py"
        f"{' --device ' + args.device if args.device != 'cpu' else ''}` "
        f"({f'{total / 60:.0f} min' if total >= 120 else f'{total:.0f} s'} in all). "
        f"Gel block {block.width:g} x {block.width:g} x {block.thickness:g} mm, P{block.degree} tets "
        f"(h = {block.h_fine} mm on the central {2 * block.fine_half_width:g} mm, growing by {block.growth} "
        f"outwards; {len(V)} vertices, {r.dofs} dofs), bottom face bonded, default SolverSettings. Base case: "
        f"E 0.5 MPa, nu 0.45, sphere of radius 3 mm pressed to 30 % of the thickness (1.5 mm); every other case "
        f"changes one thing. Depths are below the first contact; forces are on the gel (pressing: Fz < 0)."
    )
    section = "fem_stability" if args.device == "cpu" else "fem_stability_gpu"
    update_section(Path(__file__).resolve().parents[1] / "BENCHMARKS.md", section,
                   head + "\n\n" + "\n".join(lines) + "\n\n" + summary(results))


def summary(results: list[CaseResult]) -> str:
    """Counts over the cases: outcomes, and the checks every reported frame must pass."""
    frames = [f for r in results for f in r.frames]
    failed = [r for r in results if r.error is not None]
    kinds = sorted({type(r.error).__name__ for r in failed})
    bad = sum(1 for f in frames if not f["finite"] or f["min_det_f"] <= 0.0 or f["max_penetration_mm"] > 0.02 + 1e-9)
    return (f"Summary: {len(results) - len(failed)} of {len(results)} cases converged; {len(failed)} stopped with "
            f"{', '.join(kinds) or 'no error'}. Over the {len(frames)} reported frames, {bad} had a NaN, det F <= 0 or "
            f"a penetration above 0.02 mm.")


if __name__ == "__main__":
    main()
