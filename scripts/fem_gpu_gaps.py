"""Where the GPU waits for the host during a FEM frame: its idle time between kernels and copies, charged to what the
host was doing meanwhile (the innermost solver method or Warp call then running).

    python scripts/fem_gpu_gaps.py scenes/press_slide.toml --frames 10 --passes 2 [--trace-out trace.json]

``fem_phase_profile.py --gpu-activity`` says how busy the GPU is over the frames, and ``fem_host_census.py`` how the
host's time splits between its reads and the rest; neither says which host work the GPU waits for. This script records
one timeline of both with PyTorch's profiler (Kineto over CUPTI: every kernel, copy and memset of the process, Warp's
included) while the solver's methods and its reads (``array.numpy`` of a device array) are marked as host ranges
(``record_function``; with ``--mark-warp-calls`` also Warp's one-by-one launches, copies and graph replays). The idle
stretches of the GPU inside the counted frames (``solve_frame``) are then split over the host ranges open at the time,
and each piece is charged to the innermost one and its callers.

CUPTI does not report to Kineto the kernels inside a CUDA graph's conditional nodes, which is where the device CG's
loop runs (definite_cg.py). A read, though, waits until the GPU has done all the work queued before it, so the GPU is
taken as busy for the whole of each read: what it does then is either recorded or the CG's loop. The marks cost host
time (tens of microseconds each with ``--mark-warp-calls``), so the frames run slower than unmarked; compare runs of
this script with each other.

Counted: the frames after the first of the last pass (``--passes N`` solves the frames N times in one process, each
pass with a new solver, as ``generate``'s sequences in one worker do; the first frame of a pass also loads kernels).
Needs CUDA and a PyTorch built with it (the GPU machine's torch; this project's CPU wheel cannot record GPU activity).
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import typer
import warp as wp
import warp._src.context as warp_context

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import QuasiStaticSolver
from transtac_sim.physics.linear import LinearSolver
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames

#: the solver's methods marked as host ranges (newton.py, trial_point.py, assembly.py, hessian_assembly.py,
#: contact_records.py, solver.py, load_stepping.py, friction_lag.py, warm_start.py, contact_prediction.py; linear.py,
#: device_linear.py)
MARKED = {
    QuasiStaticSolver: ("solve_frame", "_solve_step", "_newton", "_read_gradient", "_gradient", "_set_trial",
                        "_launch_energy", "_energy", "_try_step", "_energy_and_min_det", "_hessian", "_contact_subset",
                        "_min_det", "_launch_min_det", "_read_min_det", "_free_norm", "_read_free_norm",
                        "_max_penetration", "_raise_stiffness", "_move_lag", "_update_lag", "_launch_lag_change",
                        "_launch_friction_lag_residual", "_keep_stick", "_launch_wrench", "_read_wrench",
                        "_warm_start", "_predict_contact", "_indenter_struct", "_frame_records"),
    LinearSolver: ("solve", "solve_last", "_solve_cg", "_cg", "_known_solution", "known_summary"),
}
FRAME = "QuasiStaticSolver.solve_frame"  # the counted windows
GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")


@dataclasses.dataclass
class HostRange:
    """A marked host range (microseconds on the trace's clock)."""

    name: str
    start: float
    end: float


def host_segments(ranges: list[HostRange]) -> list[tuple[float, float, tuple[str, ...]]]:
    """The host timeline as (start, end, the names of the ranges open, outermost first) segments, from properly nested
    ranges of one thread; a stretch with no range open has the empty path. Ranges of no length are left out."""
    ranges = [r for r in ranges if r.end > r.start]
    events = sorted([(r.start, 1, -r.end, r.name) for r in ranges] + [(r.end, 0, -r.end, r.name) for r in ranges])
    segments, stack, last = [], [], None
    for t, opening, _, name in events:
        if last is not None and t > last:
            segments.append((last, t, tuple(stack)))
        last = t
        if opening:
            stack.append(name)
        elif name in stack:  # the innermost open range of that name
            del stack[len(stack) - 1 - stack[::-1].index(name)]
    return segments


def idle_stretches(busy: list[tuple[float, float]], windows: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The stretches of the ``windows`` in which no ``busy`` interval of the GPU runs (intervals may overlap)."""
    merged: list[list[float]] = []
    for start, end in sorted(busy):
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    idle = []
    for w0, w1 in windows:
        t = w0
        for start, end in merged:
            if end <= t or start >= w1:
                continue
            if start > t:
                idle.append((t, start))
            t = max(t, end)
        if t < w1:
            idle.append((t, w1))
    return idle


def idle_by_path(idle: list[tuple[float, float]], segments: list[tuple[float, float, tuple[str, ...]]]) -> dict:
    """Idle microseconds charged to each host path (the segments' paths), by overlap."""
    charged: dict[tuple[str, ...], float] = defaultdict(float)
    j = 0
    for a, b in sorted(idle):
        while j < len(segments) and segments[j][1] <= a:
            j += 1
        k = j
        covered = 0.0
        while k < len(segments) and segments[k][0] < b:
            overlap = min(b, segments[k][1]) - max(a, segments[k][0])
            if overlap > 0.0:
                charged[segments[k][2]] += overlap
                covered += overlap
            k += 1
        if b - a - covered > 0.0:
            charged[()] += b - a - covered
    return dict(charged)


def _mark(name: str, original, record_function):
    def marked(*args, **kwargs):
        with record_function(name):
            return original(*args, **kwargs)

    return marked


READ = "read (array.numpy)"


def install_marks(record_function, warp_calls: bool = False) -> Callable[[], None]:
    """Marks the solver's methods (``MARKED``), device reads and, with ``warp_calls``, Warp's launch, capture_launch and
    copy; returns a function that puts the originals back."""
    originals = []  # (owner, name, the original or None where the owner only inherited it)
    for cls, names in MARKED.items():
        for name in names:
            if hasattr(cls, name):
                originals.append((cls, name, cls.__dict__.get(name)))
                setattr(cls, name, _mark(f"{cls.__name__}.{name}", getattr(cls, name), record_function))
    for owner, name, label in ((warp_context, "launch", "wp.launch"), (wp, "launch", "wp.launch"),
                               (warp_context, "capture_launch", "wp.capture_launch"),
                               (wp, "capture_launch", "wp.capture_launch"), (warp_context, "copy", "wp.copy"),
                               (wp, "copy", "wp.copy")) if warp_calls else ():
        originals.append((owner, name, getattr(owner, name)))
        setattr(owner, name, _mark(label, getattr(owner, name), record_function))
    numpy = wp.array.numpy
    originals.append((wp.array, "numpy", numpy))

    def read(self, *args, **kwargs):
        if self.device.is_cpu:
            return numpy(self, *args, **kwargs)
        with record_function(READ):
            return numpy(self, *args, **kwargs)

    wp.array.numpy = read

    def uninstall() -> None:
        for owner, name, original in reversed(originals):
            if original is None:
                delattr(owner, name)
            else:
                setattr(owner, name, original)

    return uninstall


def read_trace(path: Path) -> tuple[list[tuple[float, float]], list[HostRange], float]:
    """(the GPU's busy intervals, the host ranges of the thread that ran the frames, the recorded kernels' GPU
    microseconds) from a Chrome trace that PyTorch's profiler wrote; the reads count as busy (see the module
    docstring)."""
    events = json.loads(path.read_text())["traceEvents"]
    busy = [(e["ts"], e["ts"] + e["dur"]) for e in events if e.get("cat") in GPU_CATEGORIES and "dur" in e]
    marks = [e for e in events if e.get("cat") == "user_annotation" and e.get("ph") == "X"]
    frame_threads = {e["tid"] for e in marks if e["name"] == FRAME}
    ranges = [HostRange(e["name"], e["ts"], e["ts"] + e["dur"]) for e in marks if e["tid"] in frame_threads]
    busy += [(r.start, r.end) for r in ranges if r.name == READ]
    kernels = sum(e["dur"] for e in events if e.get("cat") == "kernel" and "dur" in e)
    return busy, ranges, kernels


def main(scene: Path, frames: int = typer.Option(10, min=2), passes: int = typer.Option(2, min=1),
         top: int = typer.Option(25, min=1, help="host paths to list"),
         depth: int = typer.Option(3, min=1, help="the innermost ranges of a path that name it in the table"),
         trace_out: Path | None = typer.Option(None, help="also keep the Chrome trace (chrome://tracing, Perfetto)"),
         mark_warp_calls: bool = typer.Option(False, help="also mark Warp's one-by-one launches, copies and graph "
                                              "replays (slower frames)")) -> None:
    try:
        import torch
        from torch.autograd.profiler import record_function
        from torch.profiler import ProfilerActivity, profile
    except ImportError as error:
        raise typer.BadParameter(f"needs PyTorch ({error})") from error
    if not (torch.cuda.is_available() and wp.get_cuda_device_count()):
        raise typer.BadParameter("needs CUDA in both Warp and PyTorch: the GPU's idle time cannot be recorded here")
    torch.cuda.init()
    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": "cuda"})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    prof = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])
    uninstall = install_marks(record_function, mark_warp_calls)
    iterations, seconds = 0, 0.0
    try:
        for n in range(passes):
            for f in simulate_frames(setup, frames, StageClock()):
                counted = n == passes - 1 and f.frame > 0
                print(f"pass {n + 1}, frame {f.frame}: {f.solver['seconds']:.2f} s, {f.solver['iterations']} Newton "
                      f"iterations{'' if counted else ' (not counted)'}", flush=True)
                if counted:
                    iterations += f.solver["iterations"]
                    seconds += f.solver["seconds"]
                elif n == passes - 1:
                    wp.synchronize()
                    prof.start()
        wp.synchronize()
        prof.stop()
    finally:
        uninstall()
    with tempfile.TemporaryDirectory() as tmp:
        path = trace_out or Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(path))
        busy, ranges, kernel_us = read_trace(path)
    windows = [(r.start, r.end) for r in ranges if r.name == FRAME]
    if not busy or not windows:
        raise SystemExit(f"the trace holds {len(busy)} GPU activities and {len(windows)} counted frames: nothing to "
                         "compare (was the GPU's activity recorded?)")
    idle = idle_stretches(busy, windows)
    charged = idle_by_path(idle, host_segments(ranges))
    wall = sum(b - a for a, b in windows)
    idle_total = sum(b - a for a, b in idle)
    per = max(iterations, 1)
    print(f"\n{scene} on {wp.get_device('cuda')}: {len(windows)} frames, {wall / 1e6:.3f} s inside solve_frame "
          f"(marked; the solver's own timing {seconds:.3f} s), {iterations} Newton iterations; GPU idle "
          f"{idle_total / 1e6:.3f} s ({idle_total / wall:.1%}) in {len(idle)} stretches, "
          f"{idle_total / 1e3 / per:.2f} ms per Newton iteration; recorded kernels {kernel_us / 1e6:.3f} s")
    by_name: dict[str, float] = defaultdict(float)
    grouped: dict[str, float] = defaultdict(float)
    for path, us in charged.items():
        by_name[path[-1] if path else "(no range open)"] += us
        grouped[" > ".join(path[-depth:]) if path else "(no range open)"] += us
    print("\nGPU idle by the innermost host range open (ms over the frames, ms per Newton iteration, share of idle):")
    print("| host range | idle ms | per Newton iteration | share |")
    print("|---|---|---|---|")
    for name, us in sorted(by_name.items(), key=lambda kv: -kv[1])[:top]:
        print(f"| {name} | {us / 1e3:.1f} | {us / 1e3 / per:.3f} | {us / idle_total:.1%} |")
    print(f"\nGPU idle by the {depth} innermost host ranges open:")
    print("| host ranges | idle ms | per Newton iteration | share |")
    print("|---|---|---|---|")
    for name, us in sorted(grouped.items(), key=lambda kv: -kv[1])[:top]:
        print(f"| {name} | {us / 1e3:.1f} | {us / 1e3 / per:.3f} | {us / idle_total:.1%} |")


if __name__ == "__main__":
    typer.run(main)
