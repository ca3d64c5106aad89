"""Two runs of one scene, frame by frame: how far one's labels lie from the other's, and what each run's physics cost.

    .venv/bin/python scripts/compare_datasets.py RUN REFERENCE [--worst 3] [--md-out FILE]

RUN and REFERENCE are dataset folders of ``generate`` (``scripts/bench_generate.py --out DIR`` makes them) of the same
scene and seeds, solved on the same meshes (the mesh cache, ``TRANSTAC_SIM_CACHE``: fTetWild does not build the same
mesh twice) with different settings, e.g. a copy of the scene with another ``[physics] friction_slip_mm``. Error
against run time for a dataset: what a cheaper setting moves the labels by, and what it saves. Over every frame both
runs labelled (``sequences/*/*/labels.json``):

- the largest distance of a marker centre from the reference's (``xyz_mm``; mm) over the frame's markers;
- the largest image distance of a marker from the reference's (``uv``, in every camera the labels carry; px) over the
  markers visible in both runs, and how many (marker, camera) pairs are visible in one run only;
- the largest |force_n - reference force_n| over the indenters (N), and the same as a percentage of the largest
  reference |force_n| of the frame's sequence (a released frame's small force is not the scale);
- each run's Newton iterations and physics seconds per frame (``solver``).

It prints the median, 90th percentile and largest of each difference over the frames that have it (no marker visible
in both runs: no image distance; a sequence without reference force or a scene without indenters: no percentage),
both runs' Newton iterations (median, mean) and physics seconds (median: each sequence's first frame also builds
the solver), how many frames only one run labelled, and the ``--worst`` frames by marker distance.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer


def read_frames(root: Path) -> dict[tuple[str, str], dict]:
    """{(sequence folder, frame folder): labels.json} of a dataset folder."""
    if not (root / "sequences").is_dir():
        raise typer.BadParameter(f"{root}: no sequences/ folder (not a generate dataset)")
    return {(p.parent.parent.name, p.parent.name): json.loads(p.read_text())
            for p in sorted(root.glob("sequences/*/*/labels.json"))}


def _same(run: dict, ref: dict, what: str, key: str) -> None:
    """Refuses frames whose markers or indenters (``what``) differ by ``key`` between the runs."""
    if [m[key] for m in run[what]] != [m[key] for m in ref[what]]:
        raise ValueError(f"sequence {ref['sequence']} frame {ref['frame']}: the runs' {what} ({key}) differ (not the "
                         "same scene and seeds?)")


def frame_differences(run: dict, ref: dict, largest_force_n: float) -> dict:
    """One frame's differences (see the module docstring); ``largest_force_n``: the reference sequence's largest
    |force_n| (0: no percentage). NaN where the frame has no such difference."""
    _same(run, ref, "markers", "id")
    _same(run, ref, "indenters", "name")
    pairs = list(zip(run["markers"], ref["markers"], strict=True))
    xyz = [float(np.linalg.norm(np.subtract(a["xyz_mm"], b["xyz_mm"]))) for a, b in pairs]
    cameras = [cam for cam in ("left", "right") if all(cam in m for m in run["markers"] + ref["markers"])]
    px = [float(np.linalg.norm(np.subtract(a[cam]["uv"], b[cam]["uv"])))
          for a, b in pairs for cam in cameras if a[cam]["visible"] and b[cam]["visible"]]
    flipped = sum(a[cam]["visible"] != b[cam]["visible"] for a, b in pairs for cam in cameras)
    forces = [float(np.linalg.norm(np.subtract(a["force_n"], b["force_n"])))
              for a, b in zip(run["indenters"], ref["indenters"], strict=True)]
    force = max(forces, default=np.nan)
    return {"marker_mm": max(xyz, default=np.nan), "marker_px": max(px, default=np.nan), "visibility_flips": flipped,
            "force_n": force, "force_pct": 100.0 * force / largest_force_n if largest_force_n > 0.0 else np.nan,
            "iterations": int(run["solver"]["iterations"]), "iterations_ref": int(ref["solver"]["iterations"]),
            "seconds": float(run["solver"]["seconds"]), "seconds_ref": float(ref["solver"]["seconds"])}


def compare(run_dir: Path, ref_dir: Path) -> tuple[list[dict], int, int]:
    """Every common frame's differences, in order, each with its "sequence" and "frame"; and how many frames only the
    run and only the reference labelled."""
    run, ref = read_frames(run_dir), read_frames(ref_dir)
    largest: dict[str, float] = {}
    for (seq, _), labels in ref.items():
        for ind in labels["indenters"]:
            largest[seq] = max(largest.get(seq, 0.0), float(np.linalg.norm(ind["force_n"])))
    rows = [frame_differences(run[key], ref[key], largest.get(key[0], 0.0)) | {"sequence": key[0], "frame": key[1]}
            for key in sorted(run.keys() & ref.keys())]
    return rows, len(run.keys() - ref.keys()), len(ref.keys() - run.keys())


def spread(values: list[float]) -> str:
    """"median / 90th percentile / largest (frames)" over the values that are not NaN, or "none"."""
    kept = [v for v in values if not np.isnan(v)]
    if not kept:
        return "none"
    return " / ".join(f"{v:.3g}" for v in (np.median(kept), np.percentile(kept, 90), np.max(kept))) + f" ({len(kept)})"


def report(rows: list[dict], only_run: int, only_ref: int, run_dir: Path, ref_dir: Path, worst: int) -> str:
    """The comparison as markdown lines."""
    if not rows:
        raise typer.BadParameter(f"{run_dir} and {ref_dir} have no labelled frame in common")

    def column(key: str) -> list[float]:
        return [r[key] for r in rows]

    lines = [f"{len(rows)} frames in both `{run_dir}` (run) and `{ref_dir}` (reference); {only_run} only in the run, "
             f"{only_ref} only in the reference.", "",
             "| per frame | median / 90th percentile / largest (frames) |", "|---|---|",
             f"| largest marker distance (mm) | {spread(column('marker_mm'))} |",
             f"| largest marker image distance (px, every camera) | {spread(column('marker_px'))} |",
             f"| largest indenter force difference (N) | {spread(column('force_n'))} |",
             f"| the same, % of the sequence's largest reference force | {spread(column('force_pct'))} |", "",
             f"Markers visible in one run only: {sum(column('visibility_flips'))} (marker, camera) pairs in all.",
             f"Newton iterations per frame, median (mean): run {np.median(column('iterations')):g} "
             f"({np.mean(column('iterations')):.1f}), reference {np.median(column('iterations_ref')):g} "
             f"({np.mean(column('iterations_ref')):.1f}). Physics seconds per frame, median: run "
             f"{np.median(column('seconds')):.3f}, reference {np.median(column('seconds_ref')):.3f}."]
    if worst:
        lines += ["", "Frames with the largest marker distance:"]
    for r in sorted(rows, key=lambda r: -np.nan_to_num(r["marker_mm"], nan=-1.0))[:worst]:
        lines.append(f"- {r['sequence']} {r['frame']}: markers {r['marker_mm']:.4f} mm ({r['marker_px']:.2f} px), "
                     f"force {r['force_n']:.4f} N ({r['force_pct']:.1f} %), Newton iterations {r['iterations']} "
                     f"against {r['iterations_ref']}")
    return "\n".join(lines)


def main(run: Path, reference: Path, worst: int = typer.Option(3, min=0, help="list this many frames with the "
                                                                "largest marker distance"),
         md_out: Path | None = typer.Option(None, help="also write the report to this file")) -> None:
    rows, only_run, only_ref = compare(run, reference)
    text = report(rows, only_run, only_ref, run, reference, worst)
    print(text)
    if md_out is not None:
        md_out.write_text(text + "\n")


if __name__ == "__main__":
    typer.run(main)
