"""Launch sequences replayed as CUDA graphs: the host work of a warp.fem integration (finding its kernel, packing
its arguments: about half a millisecond each on an H100's host) paid once per graph instead of once per call.

The energy at a trial displacement (the line search's test), the smallest det F, and Newton's gradient and Hessian are
evaluated many times per load step with the same arrays: ``GraphCache.run`` launches the sequence the first time (which
also loads its kernels and makes any buffer or matrix it keeps), captures it the second time it sees the same key and
replays the graph from then on. A key names what a graph bakes in and can change: the displacement field's address and
the values passed by value (the indenters' struct, their contact stiffness, raised inside Newton, and for the Hessian
its (geometric, clamp) pair, the barrier flag and the contact side subset, whose matrix is made anew with it); the
objects in ``keep`` are held from a key's first launch on, so that an address in a key
is not reused by another object while the key is known: held only once captured, a contact side subset replaced after
one launch was freed, the next one was made at its address and captured on its first use, and its new matrix was made
inside the capture, which Warp refuses (press_slide with ``contact_edge_mm = 0.5`` on an H100). Every other array a
graph reads (u_prev, the contact state, the material parameters, the sums and matrices it writes, the indenters' pose
arrays) must be made once for the solver and only changed in place, as solver.py, assembly.py and hessian_assembly.py
do: a replay reads their current values. The indenter struct is one per solver (solver.py ``_indenter_struct`` writes
each load step's poses into it), so a graph serves every load step; before, each step made a new struct and dropped
every graph, and each step's first evaluations were launched and captured anew. ``clear`` drops graphs that can no
longer be replayed: the Hessian's when its contact side subset is made anew, every graph when the contact stiffness is
raised. On the CPU (no graphs) the sequence is launched every time. press_slide on an H100: the energy
1.11-1.14 -> 0.69 ms per evaluation, det F 0.30-0.31 -> 0.14 ms, the frames 0.95x (BENCHMARKS.md
``fem_graph_replay_gpu``); then on an H200 the gradient 1.6 -> 0.9 ms, the Hessian 2.0 -> 1.4-1.5 ms, the frames
0.90-0.93x (``fem_gradient_hessian_replay_gpu``); kept across load steps, on an H100, the energy 0.34 -> 0.24 ms, the
gradient 0.57 -> 0.46 ms, the frames within the runs' noise (``fem_kept_graphs_across_steps_gpu``).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable

import warp as wp


class GraphCache:
    """CUDA graphs of launch-only sequences, by key (see the module docstring)."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._graphs: dict[Hashable, tuple[tuple, object]] = {}
        self._seen: dict[Hashable, tuple] = {}  # keys launched once, not captured yet, with their ``keep``
        self.captures = 0  # graphs captured (diagnostics)

    def run(self, key: Hashable, keep: tuple, launches: Callable[[], None]) -> None:
        """``launches()`` (device work only: no host read, no allocation that outlives it), or its graph."""
        if not self.device.is_cuda:
            launches()
            return
        entry = self._graphs.get(key)
        if entry is not None:
            wp.capture_launch(entry[1])
            return
        if key not in self._seen:  # first time: launched as it is (loads the modules, makes kept buffers)
            self._seen[key] = keep  # held too: an address in a seen key must not name another object later
            launches()
            return
        with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
            launches()
        self._graphs[key] = (keep, capture.graph)
        del self._seen[key]  # held by the graph's entry from now on
        self.captures += 1
        wp.capture_launch(capture.graph)

    def clear(self, name: str | None = None) -> None:
        """Drops every graph, or those whose key starts with ``name``."""
        for table in (self._graphs, self._seen):
            for key in [k for k in table if name is None or k[0] == name]:
                del table[key]
