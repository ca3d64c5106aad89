"""Design-space sweeps over marker layouts (and optionally gel thickness, stiffness and camera baseline):
``transtac-sim sweep SWEEP.toml --out DIR`` (``run.run_sweep``).

For each point of the sweep a small benchmark set (press, slide, roll; several indenters, a sharp one
among them) is simulated and rendered (UV images, both cameras), the perception pipeline (detect, track,
match, triangulate) runs on it, and its output is scored against the exact labels (``scoring``).

What is reused (``mechanics``, ``run``): the markers do not change the mechanics, so the FEM of each
benchmark sequence is solved once per mechanical configuration and its displacement field cached; a point
that differs only in its marker layout embeds its markers into the cached field. Points that differ only
in pipeline settings share the rendered images.
"""
