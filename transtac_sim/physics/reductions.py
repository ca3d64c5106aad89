"""Reductions of the Newton loop's vectors on the solver's device, so that the host reads a few scalars instead of
whole vectors (newton.py).

Each reduction is two launches: ``reduction_blocks(device)`` thread blocks of ``REDUCTION_THREADS`` threads stride over
the array and write one partial result per block (a tile reduction), then one thread block combines the partials
(``_combine``): no atomics, so every run gives the same bits, and the sums are summed in a fixed order. On a GPU, one
thread block alone took 60-95 us over press_slide's 31k nodes (an H100 runs a block on one of its 132 SMs), on the
critical path of the Newton loop, whose host waits for each result; the two passes take 20-22 us (BENCHMARKS.md
``fem_host_census_gpu``, ``fem_multi_block_reductions_gpu``). The CPU keeps one block (Warp runs a thread block as one
thread there).

What they replace: the gradient, the Newton step, the step estimate, the iterate's largest entry and the 4 det F per tet
read to numpy once or twice per Newton pass (about 0.75 MB each on press_slide's 31k nodes; 2,553 device-to-host
copies over frames 1-9 on an H100, 0.33 s of copying against 3.9 s of frames, BENCHMARKS.md
``fem_device_reductions_gpu``).

Vectors are arrays of vec3d (one per node, mm or N); ``fixed`` is 1.0 on the fixed components, 0.0 elsewhere.
"""

from __future__ import annotations

import warp as wp

REDUCTION_THREADS = 256
CUDA_BLOCKS = 128  # thread blocks of a reduction's first pass on a GPU
SUM, MAX, MIN = (wp.constant(k) for k in range(3))  # how ``_combine`` combines a result's partials


@wp.func
def free_part(v: wp.vec3d, fixed: wp.vec3d):
    """v with its fixed components (``fixed`` > 0.5) set to 0, whatever they hold (a NaN or an infinity there is dropped,
    not multiplied by 0)."""
    zero = wp.float64(0.0)
    half = wp.float64(0.5)
    return wp.vec3d(wp.where(fixed[0] > half, zero, v[0]), wp.where(fixed[1] > half, zero, v[1]),
                    wp.where(fixed[2] > half, zero, v[2]))


@wp.func
def _largest_component(d: wp.vec3d):
    """max |d_k| over the components of d."""
    return wp.max(wp.abs(d[0]), wp.max(wp.abs(d[1]), wp.abs(d[2])))


@wp.kernel(enable_backward=False)
def _max_abs_difference(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64),
                        blocks: int):
    """[max over entries and components of |a - b| (b empty: of |a|), count of entries with a NaN], per block."""
    block, lane = wp.tid()
    largest = wp.float64(0.0)
    nans = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, a.shape[0], blocks * wp.block_dim()):
        d = a[i]
        if b.shape[0] > 0:
            d = d - b[i]
        if wp.isnan(d):
            nans += wp.float64(1.0)
        else:
            largest = wp.max(largest, _largest_component(d))
    total = wp.tile_max(wp.tile(largest))
    count = wp.tile_sum(wp.tile(nans))
    if lane == 0:
        out[2 + 2 * block] = total[0]
        out[3 + 2 * block] = count[0]


@wp.kernel(enable_backward=False)
def _extremes(a: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64), blocks: int):
    """[min, max, NaN count] of a, per block."""
    block, lane = wp.tid()
    low = wp.float64(1.0e300)
    high = wp.float64(-1.0e300)
    nans = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, a.shape[0], blocks * wp.block_dim()):
        v = a[i]
        if wp.isnan(v):
            nans += wp.float64(1.0)
        else:
            low = wp.min(low, v)
            high = wp.max(high, v)
    lows = wp.tile_min(wp.tile(low))
    highs = wp.tile_max(wp.tile(high))
    count = wp.tile_sum(wp.tile(nans))
    if lane == 0:
        out[3 + 3 * block] = lows[0]
        out[4 + 3 * block] = highs[0]
        out[5 + 3 * block] = count[0]


@wp.kernel(enable_backward=False)
def _negated_free(g: wp.array(dtype=wp.vec3d), fixed: wp.array(dtype=wp.vec3d), rhs: wp.array(dtype=wp.vec3d),
                  out: wp.array(dtype=wp.float64), blocks: int):
    """rhs = -g on the free components (0 on the fixed ones, whatever g holds there); per block |rhs|^2 and the sum of
    g's fixed z components (the normal load the gel passes to its support)."""
    block, lane = wp.tid()
    squares = wp.float64(0.0)
    load = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, g.shape[0], blocks * wp.block_dim()):
        v = -free_part(g[i], fixed[i])
        rhs[i] = v
        squares += wp.dot(v, v)
        if fixed[i][2] > wp.float64(0.5):
            load += g[i][2]
    totals = wp.tile_sum(wp.tile(squares))
    loads = wp.tile_sum(wp.tile(load))
    if lane == 0:
        out[2 + 2 * block] = totals[0]
        out[3 + 2 * block] = loads[0]


@wp.kernel(enable_backward=False)
def _step_summary(du: wp.array(dtype=wp.vec3d), rhs: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64),
                  blocks: int):
    """[du . rhs, max |du| over entries and components, count of entries with a NaN or an infinity], per block."""
    block, lane = wp.tid()
    dot = wp.float64(0.0)
    largest = wp.float64(0.0)
    bad = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, du.shape[0], blocks * wp.block_dim()):
        d = du[i]
        if wp.isfinite(d):
            dot += wp.dot(d, rhs[i])
            largest = wp.max(largest, _largest_component(d))
        else:
            bad += wp.float64(1.0)
    dots = wp.tile_sum(wp.tile(dot))
    largests = wp.tile_max(wp.tile(largest))
    bads = wp.tile_sum(wp.tile(bad))
    if lane == 0:
        out[3 + 3 * block] = dots[0]
        out[4 + 3 * block] = largests[0]
        out[5 + 3 * block] = bads[0]


@wp.kernel(enable_backward=False)
def _combine(out: wp.array(dtype=wp.float64), ops: wp.vec3i, count: int, blocks: int):
    """out[j] = the partials out[count + count b + j] of blocks b combined by ops[j] (SUM, MAX or MIN), j < count."""
    _, lane = wp.tid()
    for j in range(count):
        op = ops[j]
        value = wp.float64(0.0)
        if op == MAX:
            value = wp.float64(-1.0e300)
        elif op == MIN:
            value = wp.float64(1.0e300)
        for b in range(lane, blocks, wp.block_dim()):
            v = out[count + count * b + j]
            if op == MAX:
                value = wp.max(value, v)
            elif op == MIN:
                value = wp.min(value, v)
            else:
                value += v
        if op == MAX:  # the same op in every thread: the whole block takes the same branch
            highs = wp.tile_max(wp.tile(value))
            if lane == 0:
                out[j] = highs[0]
        elif op == MIN:
            lows = wp.tile_min(wp.tile(value))
            if lane == 0:
                out[j] = lows[0]
        else:
            sums = wp.tile_sum(wp.tile(value))
            if lane == 0:
                out[j] = sums[0]


def reduction_blocks(device) -> int:
    """Thread blocks of a reduction's first pass on ``device``."""
    return CUDA_BLOCKS if wp.get_device(device).is_cuda else 1


def reduction_buffer(count: int, device) -> wp.array:
    """A reduction's output: its ``count`` results, then ``count`` partials per block of the first pass."""
    return wp.empty(count * (1 + reduction_blocks(device)), dtype=wp.float64, device=device)


def _launch(kernel, inputs: list, out: wp.array, ops: tuple[int, ...]) -> None:
    """The two passes of a reduction into ``out`` (``reduction_buffer(len(ops))``): ``kernel`` over blocks, then
    ``_combine`` of their partials by ``ops``."""
    blocks = reduction_blocks(out.device)
    if out.shape[0] < len(ops) * (1 + blocks):
        raise ValueError(f"a reduction of {len(ops)} results over {blocks} blocks needs a buffer of "
                         f"{len(ops) * (1 + blocks)} (reduction_buffer), got {out.shape[0]}")
    wp.launch_tiled(kernel, dim=[blocks], block_dim=REDUCTION_THREADS, device=out.device,
                    inputs=[*inputs, out, blocks])
    wp.launch_tiled(_combine, dim=[1], block_dim=REDUCTION_THREADS, device=out.device,
                    inputs=[out, wp.vec3i(*ops, *([SUM] * (3 - len(ops)))), len(ops), blocks])


def _reduce(kernel, inputs: list, ops: tuple[int, ...], device) -> list[float]:
    out = reduction_buffer(len(ops), device)
    _launch(kernel, inputs, out, ops)
    return [float(v) for v in out[:len(ops)].numpy()]


def max_abs(a: wp.array, b: wp.array | None = None) -> float:
    """max |a - b| (max |a| without b) over the entries and components of vec3d arrays; NaN where any entry is NaN,
    as numpy's."""
    out = reduction_buffer(2, a.device)
    launch_max_abs(a, out, b)
    largest, nans = (float(v) for v in out[:2].numpy())
    return float("nan") if nans else largest


def launch_max_abs(a: wp.array, out: wp.array, b: wp.array | None = None) -> None:
    """``max_abs`` without the read: [max |a - b| over the entries without a NaN, count of entries with a NaN] into out
    (``reduction_buffer(2)``)."""
    empty = wp.empty(0, dtype=wp.vec3d, device=a.device)
    _launch(_max_abs_difference, [a, b if b is not None else empty], out, (MAX, SUM))


def extremes(a: wp.array) -> tuple[float, float]:
    """(min, max) of a float64 array; (NaN, NaN) where it holds a NaN, as numpy's min and max (and, as they do, an
    error for an empty array)."""
    out = reduction_buffer(3, a.device)
    launch_extremes(a, out)
    return read_extremes(out)


def launch_extremes(a: wp.array, out: wp.array) -> None:
    """``extremes`` without the read: [min, max, NaN count] of a into out (``reduction_buffer(3)``), for
    ``read_extremes``."""
    if a.shape[0] == 0:
        raise ValueError("extremes of an empty array")
    _launch(_extremes, [a], out, (MIN, MAX, SUM))


def read_extremes(out: wp.array, also: int = 0):
    """(min, max) from ``launch_extremes``'s [min, max, NaN count]; with ``also`` = k > 0, ((min, max), the k values
    the caller copied after them, out[3:3 + k], after the reduction: over partials it has used), in the same read."""
    values = [float(v) for v in out[:3 + also].numpy()]
    low, high, nans = values[:3]
    result = (float("nan"), float("nan")) if nans else (low, high)
    return (result, values[3:]) if also else result


def negated_free(g: wp.array, fixed: wp.array) -> tuple[wp.array, float]:
    """(-g with its fixed components set to 0, the norm of that): Newton's right-hand side and |g| on the free dofs."""
    return negated_free_and_load(g, fixed)[:2]


def negated_free_and_load(g: wp.array, fixed: wp.array, also: tuple[tuple[wp.array, int], ...] = ()):
    """``negated_free`` and |sum of g's fixed z components| (N): the normal load the gel passes to its support, which at
    equilibrium balances the indenters' normal force (one read for all three). ``also``: (float64 array on g's device,
    k) pairs whose first k values are read with them and returned after them, in order (the caller's scalars, without
    reads of their own)."""
    rhs = wp.empty_like(g)
    out = negated_free_buffer(sum(count for _, count in also), g.device)
    return read_negated_free(rhs, out, launch_negated_free_and_load(g, fixed, rhs, out, also))


def negated_free_buffer(also: int, device) -> wp.array:
    """The output of ``launch_negated_free_and_load`` with ``also`` of the caller's values in all."""
    return wp.empty(max(2 * (1 + reduction_blocks(device)), 2 + also), dtype=wp.float64, device=device)


def launch_negated_free_and_load(g: wp.array, fixed: wp.array, rhs: wp.array, out: wp.array,
                                 also: tuple[tuple[wp.array, int], ...] = ()) -> int:
    """``negated_free_and_load`` without its allocations and read (launches only, so that a caller may replay them as
    a graph, replay.py): -g on the free components into ``rhs``, [|rhs|^2, the sum of g's fixed z components, then
    the ``also`` values] into ``out`` (``negated_free_buffer``); returns how many values ``read_negated_free``
    reads."""
    _launch(_negated_free, [g, fixed, rhs], out, (SUM, SUM))
    at = 2
    for array, count in also:  # over partials that the combine has used
        wp.copy(out, array, dest_offset=at, count=count)
        at += count
    return at


def read_negated_free(rhs: wp.array, out: wp.array, count: int) -> tuple:
    """(rhs, |rhs|, |the load|, the ``also`` values) from ``launch_negated_free_and_load``'s ``out``, in one read."""
    values = [float(v) for v in out[:count].numpy()]
    return (rhs, values[0] ** 0.5, abs(values[1]), *values[2:])


def step_summary(du: wp.array, rhs: wp.array) -> tuple[float, float, bool]:
    """(du . rhs, max |du|, whether every entry of du is finite): a Newton step's slope (with rhs = -g, -(du . g)),
    length and sanity in one read. The sum and the maximum are over the finite entries."""
    dot, largest, bad = _reduce(_step_summary, [du, rhs], (SUM, MAX, SUM), du.device)
    return dot, largest, bad == 0.0
