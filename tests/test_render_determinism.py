"""The same scene and seed render to the same float32 bits in every run and process (CPU variant).

This is where run-to-run differences start: the film's float sums, whose order followed Dr.Jit's threads
(renderer.py's docstring). Compared on the linear renders, where such a difference shows in many values
(at 160x120 and 32 spp, hundreds per image), not on the 8-bit images, where it shows only when a sum
straddles a rounding boundary (one value in several frames of 640x480)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from transtac_sim.camera.model import CameraEffects
from transtac_sim.rendering import demo_scene
from transtac_sim.rendering.inputs import RenderRequest, RenderSettings
from transtac_sim.rendering.renderer import Renderer

SCRIPT = """
import sys, numpy as np
sys.path.insert(0, {tests!r})
from test_render_determinism import render
np.savez({out!r}, **render())
"""


def render(seed: int = 5) -> dict[str, np.ndarray]:
    """Both cameras under UV and white light, linear float32 (160x120, 32 spp)."""
    scene = demo_scene.sensor_scene(size=(160, 120))
    r = Renderer(scene, RenderRequest(illuminations=("uv", "white")), RenderSettings(spp=32, variant="llvm_ad_rgb"),
                 CameraEffects(noise=False, quantize=False))
    frame = demo_scene.indented_frame(scene, 0.8)
    return {f"{cam}_{ill}": img for (cam, ill), img in r.render(frame, seed=seed).linear.items()}


def test_renders_are_bitwise_reproducible_across_runs_and_processes(tmp_path: Path):
    runs = [render() for _ in range(3)]
    out = tmp_path / "other_process.npz"
    code = SCRIPT.format(tests=str(Path(__file__).parent), out=str(out))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    with np.load(out) as z:
        runs.append({k: z[k] for k in z.files})
    for k, ref in runs[0].items():
        assert ref.dtype == np.float32 and ref.max() > 0
        for i, other in enumerate(runs[1:], 1):
            differ = int((other[k] != ref).sum())
            assert differ == 0, f"{k}: run {i} differs from run 0 in {differ} values"
