"""What the host does between a FEM frame's device synchronisations: its reads (``array.numpy`` of a device array, which
waits for the GPU), kernel launches and copies made one by one, and CUDA graph replays, by the solver's call site.

    .venv/bin/python scripts/fem_host_census.py scenes/press_slide.toml --device cuda --frames 10 --skip-first

On a GPU a read blocks the host until the work queued before it is done, and the GPU then idles until the host has
queued the next work: between two reads it can only be busy for what the host launched in between. So the wall time
of the frames splits into the host's waits in reads (the GPU busy, or copying back) and the host's own time (Python,
launches; the GPU idle for at least the first launch after each read). The script wraps Warp's ``launch`` (tiled
launches included), ``capture_launch``, ``copy`` and ``array.numpy`` and records each call made outside a graph
capture with the solver's innermost call site (the first frame in ``transtac_sim``) and the host seconds it took. The
span between two reads is charged to the site of the read that ends it (what its work was for). Waits that do not go
through ``array.numpy`` (a ``copy`` into a host array, ``BsrMatrix.nnz_sync``, the condition reads of a CG loop
without conditional graphs) are not counted as reads: they fall into the host's own time.

It prints, for the frames counted: the reads, launches, copies and replays per Newton iteration; the host's seconds
inside reads against the rest; and the read sites that take the most host time outside their waits, with the launches
made for each. The wrappers themselves cost host time (the call-site lookup), so the frames run a little slower than
untraced; compare runs of this script with each other.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import typer
import warp as wp
import warp._src.context as warp_context

import transtac_sim
from transtac_sim.dataset.sequence import StageClock
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames

_PACKAGE = str(Path(transtac_sim.__file__).resolve().parent) + os.sep


def _site() -> str:
    """``module.py:function`` of the innermost caller in the transtac_sim package, or ``other``."""
    frame = sys._getframe(2)
    while frame is not None:
        if frame.f_code.co_filename.startswith(_PACKAGE):
            return f"{Path(frame.f_code.co_filename).name}:{frame.f_code.co_name}"
        frame = frame.f_back
    return "other"


class Census:
    """Host calls by kind and site (outside captures); spans between reads charged to the read that ends them."""

    def __init__(self):
        self.counting = False
        self.depth = 0  # wrapped calls in progress (a read copies through ``copy``: counted once, as the read)
        self.calls: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0, 0.0])  # (kind, site) -> [n, s]
        self.spans: dict[str, list[float]] = defaultdict(lambda: [0, 0.0, 0.0, 0])  # site -> [reads, span s, wait s,
        # launches+copies+replays in the spans]
        self._span_start = time.perf_counter()
        self._span_ops = 0

    def reset(self) -> None:
        self.calls.clear()
        self.spans.clear()
        self._span_start = time.perf_counter()
        self._span_ops = 0

    def record(self, kind: str, start: float, end: float) -> None:
        site = _site()
        entry = self.calls[(kind, site)]
        entry[0] += 1
        entry[1] += end - start
        if kind == "read":
            span = self.spans[site]
            span[0] += 1
            span[1] += start - self._span_start
            span[2] += end - start
            span[3] += self._span_ops
            self._span_start, self._span_ops = end, 0
        else:
            self._span_ops += 1

    def wrap(self, original, kind: str, capturing):
        """``original`` recorded as ``kind`` where it is called outside a capture (``capturing``: a function of the
        call's arguments)."""
        census = self

        def traced(*args, **kwargs):
            if not census.counting or census.depth or capturing(args, kwargs):
                return original(*args, **kwargs)
            census.depth += 1
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                census.depth -= 1
                census.record(kind, start, time.perf_counter())

        return traced


def _capturing_device(device) -> bool:
    try:
        d = wp.get_device(device)
    except Exception:
        return False
    return bool(d.is_cuda and d.is_capturing)


def install(census: Census):
    """Wraps Warp's launch, capture_launch, copy and array.numpy (every module reaches them through these names);
    returns a function that puts the originals back."""
    originals = [(warp_context, "launch", warp_context.launch), (wp, "launch", wp.launch),
                 (warp_context, "capture_launch", warp_context.capture_launch),
                 (wp, "capture_launch", wp.capture_launch), (warp_context, "copy", warp_context.copy),
                 (wp, "copy", wp.copy), (wp.array, "numpy", wp.array.numpy)]
    launch = census.wrap(warp_context.launch, "launch",
                         lambda a, k: _capturing_device(k.get("device") or (a[6] if len(a) > 6 else None)))
    warp_context.launch = launch  # launch_tiled calls it by this name
    wp.launch = launch
    replay = census.wrap(warp_context.capture_launch, "replay", lambda a, k: False)
    warp_context.capture_launch = replay
    wp.capture_launch = replay
    copy = census.wrap(warp_context.copy, "copy", lambda a, k: _capturing_device(a[0].device if a else None))
    warp_context.copy = copy
    wp.copy = copy
    wp.array.numpy = census.wrap(wp.array.numpy, "read", lambda a, k: a[0].device.is_cpu)

    def uninstall() -> None:
        for owner, name, original in originals:
            setattr(owner, name, original)

    return uninstall


def main(scene: Path, device: str = typer.Option("cuda", help="cuda (or cpu, where nothing is read back)"),
         frames: int = typer.Option(10, min=1), skip_first: bool = typer.Option(True),
         top: int = typer.Option(15, min=1, help="read sites to list")) -> None:
    if skip_first and frames < 2:
        raise typer.BadParameter("--skip-first leaves no frame to count: give --frames 2 or more, or --no-skip-first")
    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": device})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    census = Census()
    uninstall = install(census)
    census.counting = not skip_first
    wall, iterations, started = 0.0, 0, time.perf_counter()
    try:
        for f in simulate_frames(setup, frames, StageClock()):
            now = time.perf_counter()
            print(f"frame {f.frame}: {f.solver['seconds']:.2f} s, {f.solver['iterations']} Newton iterations",
                  flush=True)
            if census.counting:
                wall += now - started
                iterations += f.solver["iterations"]
            else:
                census.counting = True
                census.reset()
            started = time.perf_counter()
    finally:
        uninstall()
    by_kind: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
    for (kind, _), (n, s) in census.calls.items():
        by_kind[kind][0] += n
        by_kind[kind][1] += s
    waits = by_kind["read"][1]
    per = max(iterations, 1)
    print(f"\n{scene} on {device}: {wall:.2f} s of frames (including the simulate loop's own host work), "
          f"{iterations} Newton iterations")
    print(f"host inside reads (waiting for the GPU, then copying): {waits:.3f} s ({waits / wall:.1%}); host "
          f"elsewhere (Python, launches): {wall - waits:.3f} s ({(wall - waits) / wall:.1%}), "
          f"{1000 * (wall - waits) / per:.2f} ms per Newton iteration")
    print("| call | count | per Newton iteration | host s in the call |")
    print("|---|---|---|---|")
    for kind in ("read", "launch", "copy", "replay"):
        n, s = by_kind[kind]
        print(f"| {kind} | {n} | {n / per:.1f} | {s:.3f} |")
    print("\nRead sites by the host time of the spans they end (host s outside the read, launches, copies and replays "
          "made in those spans):")
    print("| read site | reads | per Newton iteration | span s (outside reads) | ms per span | ops per span | "
          "wait s |")
    print("|---|---|---|---|---|---|---|")
    for site, (n, span, wait, ops) in sorted(census.spans.items(), key=lambda kv: -kv[1][1])[:top]:
        print(f"| {site} | {n} | {n / per:.2f} | {span:.3f} | {1000 * span / n:.2f} | {ops / n:.1f} | {wait:.3f} |")
    print("\nLaunch sites (one-by-one kernel launches, copies and graph replays outside captures):")
    print("| kind | site | count | per Newton iteration | host s |")
    print("|---|---|---|---|---|")
    ops = [(k, site, n, s) for (k, site), (n, s) in census.calls.items() if k != "read"]
    for kind, site, n, s in sorted(ops, key=lambda r: -r[2])[:2 * top]:
        print(f"| {kind} | {site} | {n} | {n / per:.1f} | {s:.3f} |")


if __name__ == "__main__":
    typer.run(main)
