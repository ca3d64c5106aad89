"""Labelled stereo frames per hour of `transtac-sim generate`, and how the time splits over the stages.

    .venv/bin/python scripts/bench_generate.py [--scene scenes/train_random.toml] [--sequences 2] [--frames 4]
        [--workers K] [--mps] [--executor local|ray] [--md-out FILE]

On a one-GPU machine ``--workers K`` runs K sequences at once on the GPU (local processes). After each
sequence it prints the frames processed so far and their rate, so that a run cut short still says something.
``--out DIR`` generates into DIR instead of a temporary folder: a run cut short (e.g. by a time limit) is
resumed by the same command, and the rate then counts only the frames computed in this run (the failure count
covers them all; the per-sequence progress lines count the frames found on disk too).

Runs the generator into a temporary folder, reads the per-stage seconds from its manifest, and writes a
table into BENCHMARKS.md (section ``generate``) with the machine it ran on and this command.

``--summarize DIR`` reads a dataset folder, finished or cut short, and prints what its frames' solver records say
(physics seconds and Newton iterations per frame, per sequence) and the failures kept for resuming, and how many more
Newton systems batches of sequences solved in lockstep would take (``lockstep_ratio``: the cost side of a batched
solver, issue 12), the (sub)steps that failed and were solved again in halves, by why
(``SolverRecord.failed_steps``), and what friction's lag leaves unbalanced over the contact force
(``SolverRecord.friction_lag_residual_n``; ``--worst N`` lists the N frames where that is largest).

``--mesh-only`` builds and caches the gel mesh of each of those sequences (their marker layouts differ) and
stops: for a benchmark machine without fTetWild, carry the cache folder (``TRANSTAC_SIM_CACHE``) there; its
mesh stage then reads the cache, and the table says so.
"""

from __future__ import annotations

import json
import platform
import re
import sys
import tempfile
import time
from pathlib import Path

import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402

from transtac_sim.dataset.generate import generate  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main(scene: Path = typer.Option(REPO / "scenes" / "train_random.toml"),
         sequences: int = typer.Option(2, min=1), frames: int = typer.Option(4, min=1),
         workers: int = typer.Option(1, min=1),
         mps: bool = typer.Option(False, help="the workers share each GPU through CUDA MPS (generate --mps)"),
         executor: str = typer.Option("local", help="local, or ray (on a machine with GPUs: workers / GPUs "
                                      "sequences per GPU)"),
         md_out: Path | None = typer.Option(None, help="also write the section's markdown to this file"),
         write: bool = typer.Option(True, help="update BENCHMARKS.md"),
         section: str = typer.Option("generate", help="BENCHMARKS.md section (one per machine kind)"),
         mesh_only: bool = typer.Option(False, help="only build and cache the sequences' gel meshes"),
         out: Path | None = typer.Option(None, help="dataset folder, kept (resumable); default: a temporary one"),
         summarize: Path | None = typer.Option(None, help="only print the solver records of this dataset folder"),
         worst: int = typer.Option(0, min=0, help="with --summarize: also list this many frames whose friction lag "
                                   "leaves the largest imbalance against their contact force")) -> None:
    if mesh_only:
        _mesh_sequences(scene, sequences)
        return
    if summarize:
        print(solver_summary(summarize, worst))
        return
    from transtac_sim.meshing.cache import cache_dir

    cached_before = set(cache_dir().glob("*.npz"))
    with tempfile.TemporaryDirectory() as tmp:
        root = out or Path(tmp) / "ds"
        t0 = time.perf_counter()
        def progress(done: int, total: int) -> None:  # after each sequence: a run cut short still tells its rate
            t = time.perf_counter() - t0
            print(f"[{t:.0f} s] {done}/{total} frames, {3600 * done / t:.0f} frames per hour so far", flush=True)

        report = generate(scene, root, frames=frames, sequences=sequences, workers=workers,
                          executor=executor, on_frames=progress, mps=mps)
        wall = time.perf_counter() - t0
        manifest = json.loads((root / "manifest.json").read_text())
    from transtac_sim.rendering.mitsuba_env import select_variant

    variant = select_variant().variant()  # the workers' automatic choice (the main process renders nothing)
    n = report.frames_done - report.frames_skipped  # computed in this run
    resumed = f" ({report.frames_skipped} more were already in {out}: resumed)" if report.frames_skipped else ""
    stage_total = sum(report.timings.values())
    rows = [f"| {k} | {v:.2f} | {v / max(n, 1):.3f} | {100 * v / stage_total:.0f} % |" for k, v in
            sorted(report.timings.items(), key=lambda kv: -kv[1])]
    md = "\n".join([
        f"`{' '.join(['python'] + sys.argv)}` on {machine_name('cuda' if variant.startswith('cuda') else 'cpu')} "
        f"(Python {platform.python_version()}, Mitsuba variant {variant}), {time.strftime('%Y-%m-%d')}:",
        "",
        f"{n} labelled stereo frames ({len(manifest['scene']['outputs']['cameras'])} cameras x "
        f"{', '.join(manifest['scene']['outputs']['illuminations'])}) in {wall:.1f} s wall{resumed}: "
        f"**{3600 * n / wall:.0f} frames per hour**; {len(report.frames_failed)} of "
        f"{len(manifest['samples'])} frames of {sequences} sequences failed."
        + (f" Executor {executor}, {workers} worker(s)" + (" under CUDA MPS" if mps else "")
           + (f" on the GPUs with Ray ids {', '.join(report.gpus_used)}" if report.gpus_used else "") + "."),
        "",
        "| stage | seconds | seconds per frame | share of the stages' seconds |",
        "| --- | --- | --- | --- |",
        *rows,
        "",
        f"The stages' seconds add up to {stage_total:.1f} s against {wall:.1f} s wall (with several workers the "
        "stages of different sequences overlap).",
        "",
        f"Gel meshes built in this run: {len(set(cache_dir().glob('*.npz')) - cached_before)} for {sequences} "
        "sequence(s) (a contact-free scene has none; any other was read from the mesh cache).",
    ])
    causes = [f for f in report.frames_failed if not f.get("reason", "").startswith("not simulated")]
    if causes:
        md += "\n\nFailed frames (each stops the rest of its sequence, which is recorded as not simulated):\n\n" + "\n".join(
            f"- {f['sequence']}/{f['frame']:06d}: {f.get('reason', '')}" for f in causes)
    publish(md, md_out, write, section)


#: batch sizes of the lockstep estimate in ``solver_summary``
LOCKSTEP_BATCHES = (2, 4, 8)


def solver_summary(root: Path, worst: int = 0) -> str:
    """The physics of a dataset folder (finished or cut short), from its frames' ``labels.json`` solver records and
    the failures kept in ``.resume/``: frames, failures, seconds and Newton iterations per frame, per sequence; the
    residuals (the largest one's frame); friction's lag residual over the contact force, and the ``worst`` frames by
    it."""
    import statistics

    frames: dict[str, list[dict]] = {}
    lagged = []  # (lag residual / largest |force|, sequence, frame, |force|, record) of frames with both
    residuals = []  # (the solver record's residual, N; sequence, frame)
    for path in sorted(root.glob("sequences/*/*/labels.json")):
        labels = json.loads(path.read_text())
        frames.setdefault(labels["sequence"], []).append(labels["solver"])
        if "residual" in labels["solver"]:
            residuals.append((labels["solver"]["residual"], labels["sequence"], labels.get("frame")))
        force = max((sum(f * f for f in i["force_n"]) ** 0.5 for i in labels.get("indenters", [])), default=0.0)
        if "friction_lag_residual_n" in labels["solver"] and force > 0.0:
            lagged.append((labels["solver"]["friction_lag_residual_n"] / force, labels["sequence"], labels.get("frame"),
                           force, labels["solver"]))
    lag_share = [x[0] for x in lagged]
    failures = [json.loads(p.read_text()) for p in sorted(root.glob(".resume/*.json"))]
    records = [r for rs in frames.values() for r in rs]
    lines = [f"{root}: {len(records)} frames with labels in {len(frames)} sequences; "
             f"{len(failures)} failed frame(s) kept for resuming"]
    lines += [f"- failed: {f['records'][0]['sequence']} frame {f['frame']}: {f['records'][0].get('reason', '')}"
              for f in failures]
    if records:
        seconds = [r["seconds"] for r in records]
        its_by_sequence = [[r["iterations"] for r in rs] for rs in frames.values()]
        its = [n for seq_its in its_by_sequence for n in seq_its]
        lines.append(f"physics seconds per frame: median {statistics.median(seconds):.2f}, mean "
                     f"{statistics.mean(seconds):.2f}, max {max(seconds):.1f}; Newton iterations per frame: median "
                     f"{statistics.median(its):g}, max {max(its)}, {sum(its)} in all; frames with sub-steps: "
                     f"{sum(r.get('substeps', 1) > 1 for r in records)}; not converged: "
                     f"{sum(not r['converged'] for r in records)}")
        failed = [f for r in records for f in r.get("failed_steps", [])]
        if failed:  # (sub)steps that failed and were halved, by why (SolverRecord.failed_steps)
            kinds: dict[str, list[int]] = {}
            for f in failed:
                kinds.setdefault(why_kind(f["why"]), []).append(f["iterations"])
            in_frames = sum(bool(r.get("failed_steps")) for r in records)
            lines.append(f"failed (sub)steps, each solved again in halves: {len(failed)} in {in_frames} frames, "
                         f"{sum(f['iterations'] for f in failed)} Newton iterations; " + ", ".join(
                             f"{kind}: {len(n)} ({sum(n)} iterations)"
                             for kind, n in sorted(kinds.items(), key=lambda x: -sum(x[1]))))
        if residuals:  # a frame reported as converged with a large one was seen (``fem_float64_fallback_gpu``)
            top, seq, frame = max(residuals, key=lambda x: x[0])
            median = statistics.median(x[0] for x in residuals)
            lines.append(f"residual (labels.json solver residual, N): median {median:.1e}, max {top:.2e} ({seq} frame "
                         f"{frame})")
        if lag_share:
            high = statistics.quantiles(lag_share, n=10, method="inclusive")[-1] if len(lag_share) > 1 else lag_share[0]
            lines.append(f"friction's lag left unbalanced (labels.json solver friction_lag_residual_n over the largest "
                         f"indenter force) in {len(lag_share)} frames with contact: median "
                         f"{statistics.median(lag_share):.1e}, 90th percentile {high:.1e}, max {max(lag_share):.1e}")
        lines += [f"- {seq} frame {frame}: friction's lag leaves {r['friction_lag_residual_n']:.3g} N against "
                  f"|force| {force:.3g} N ({share:.2f}); {r['iterations']} Newton iterations"
                  for share, seq, frame, force, r in sorted(lagged, key=lambda x: -x[0])[:worst]]
        lines.append("solved in lockstep (batches of K sequences in one solve, each frame taking its batch's largest "
                     "Newton iteration count): " + ", ".join(
                         f"K = {k}: {lockstep_ratio(its_by_sequence, k):.2f}x the Newton systems" for k in LOCKSTEP_BATCHES
                         if k <= len(its_by_sequence)))
        lines += [f"- {seq}: {len(rs)} frames, {sum(r['seconds'] for r in rs):.1f} s of physics, Newton iterations "
                  f"{seq_its}" for (seq, rs), seq_its in zip(frames.items(), its_by_sequence, strict=True)]
    return "\n".join(lines)


def why_kind(why: str) -> str:
    """A failed step's reason without its figures: the text before its first colon, parenthesis or number ("Newton
    stalled", "Newton iteration limit reached", "penetration", ...)."""
    return re.split(r"[:(]| [0-9]", why, maxsplit=1)[0].strip()


def lockstep_ratio(its_by_sequence: list[list[int]], batch: int) -> float:
    """Newton systems solved if the sequences (each a list of Newton iterations per frame, frames in order) were solved
    in batches of ``batch`` consecutive ones in lockstep, per Newton system solved alone (>= 1). In lockstep a batch's
    frame takes as many batched iterations as its slowest sequence, and each serves as many systems as the batch has
    sequences (a sequence without that frame, e.g. one that failed earlier, still occupies its slot; the last batch may
    be smaller). A lower bound for a batched solver: one that shares the line search or sub-steps across the batch
    couples its sequences further."""
    alone = sum(sum(its) for its in its_by_sequence)
    together = 0
    for start in range(0, len(its_by_sequence), batch):
        group = its_by_sequence[start:start + batch]
        frames = max(len(its) for its in group)
        together += len(group) * sum(max(its[f] if f < len(its) else 0 for its in group) for f in range(frames))
    return together / alone if alone else 1.0


def _mesh_sequences(scene_path: Path, sequences: int) -> None:
    from transtac_sim.config import load_scene
    from transtac_sim.dataset.randomize import sequence_variant
    from transtac_sim.meshing import mesh_gel
    from transtac_sim.meshing.cache import cache_dir
    from transtac_sim.scene_setup import build_setup

    scene = load_scene(scene_path).model_copy(update={"sequences": sequences})
    for i in range(sequences):
        variant = sequence_variant(scene, i)
        meshed = mesh_gel(build_setup(variant.scene, scene_path.resolve(), marker_seed=variant.marker_seed))
        print(f"sequence {i}: {meshed.quality.tets} tets, cache {'hit' if meshed.cache_hit else 'stored'} "
              f"({meshed.cache_key}) in {cache_dir()}")


if __name__ == "__main__":
    typer.run(main)
