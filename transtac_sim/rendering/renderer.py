"""Rendering frames: the asked-for cameras under the asked-for illuminations (+ AOVs), as linear images
in each camera's recorded (distorted) geometry, then 8-bit through the camera model.

A ``Renderer`` builds one Mitsuba scene per illumination that is asked for (a UV-only request never
builds the white-light scene; a depth-only request builds a light-less geometry scene) and one sensor
per camera; ``render(frame)`` moves the gel, markers and indenters in place and renders. The same code
runs ``llvm_ad_rgb`` (CPU) and ``cuda_ad_rgb`` (GPU): ``RenderSettings.variant``, or automatic.

Reproducibility: the film adds each sample's filtered radiance to its pixels with float atomic adds, so a
pixel's sum depends on the order in which the samples arrive. Dr.Jit's LLVM backend spreads a render over
its thread pool, and that order changed from run to run (11-35 % of the float32 values of a 640x480
render differed in their last bits, now and then one 8-bit value by one grey level). On the CPU the render
calls therefore run on one Dr.Jit thread (``_one_thread``): the same scene, seed and variant give the same
bits in every run and process (about 2x the render time on 2 cores; ``generate --workers`` runs sequences
in parallel instead). The GPU variant keeps its parallel atomics and is not reproducible to the last bit.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from transtac_sim.camera.model import CameraEffects, CameraModel
from transtac_sim.rendering.depth import depth_z
from transtac_sim.rendering.inputs import FrameState, RenderRequest, RenderSettings, SensorScene
from transtac_sim.rendering.mitsuba_env import select_variant
from transtac_sim.rendering.scene import SceneAssembly
from transtac_sim.rendering.sensors import perspective_sensor


@dataclass
class RenderOutput:
    linear: dict[tuple[str, str], np.ndarray]  # (camera, illumination) -> (H, W, 3) float32, recorded geometry
    depth: dict[str, np.ndarray]  # camera -> (H, W) float32 z-depth mm (+inf: nothing hit)
    seconds: dict[str, float] = field(default_factory=dict)  # per stage


@contextmanager
def _one_thread(variant: str):
    """Run Dr.Jit's LLVM kernels on one thread inside the block (see the module docstring)."""
    if not variant.startswith("llvm"):
        yield
        return
    import drjit as dr

    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(threads)


class Renderer:
    def __init__(self, scene: SensorScene, request: RenderRequest = RenderRequest(),
                 settings: RenderSettings = RenderSettings(), effects: CameraEffects = CameraEffects()):
        self.mi = select_variant(settings.variant)
        self.variant = self.mi.variant()
        self.scene, self.request, self.settings = scene, request, settings
        self.cameras = {c: CameraModel(scene.cameras[c], effects) for c in request.cameras}
        kinds = list(request.illuminations) or (["geometry"] if request.aovs else [])
        self.assemblies = {k: SceneAssembly(self.mi, scene, k, settings.max_depth, settings.rr_depth) for k in kinds}
        self.sensors = {c: perspective_sensor(self.mi, m.render_K, m.render_size, scene.cameras[c].R, scene.cameras[c].T,
                                              settings.spp, settings.sampler) for c, m in self.cameras.items()}
        self.spp = next(iter(self.sensors.values())).sampler().sample_count() if self.sensors else settings.spp

    def render(self, frame: FrameState | None = None, seed: int = 0) -> RenderOutput:
        """Render one frame; ``seed`` seeds Mitsuba's sampler (a different stream per camera and image)."""
        mi, out = self.mi, RenderOutput({}, {})
        t = time.perf_counter()
        for a in self.assemblies.values():
            if frame is not None:
                a.update(frame)
        out.seconds["update"] = time.perf_counter() - t
        t = time.perf_counter()
        with _one_thread(self.variant):
            for i, ill in enumerate(self.request.illuminations):
                scene = self.assemblies[ill].mi_scene
                for j, (cam, model) in enumerate(self.cameras.items()):
                    img = mi.render(scene, sensor=self.sensors[cam], spp=self.spp, seed=4 * seed + 2 * i + j)
                    out.linear[(cam, ill)] = model.to_recorded(np.array(img))
        out.seconds["render"] = time.perf_counter() - t
        if "depth" in self.request.aovs:
            t = time.perf_counter()
            scene = next(iter(self.assemblies.values())).mi_scene
            for cam, model in self.cameras.items():
                spec = self.scene.cameras[cam]
                z = depth_z(mi, scene, spec.centre, model.pixel_rays() @ np.asarray(spec.R, float), spec.R, spec.T)
                out.depth[cam] = z.reshape(spec.size[1], spec.size[0]).astype(np.float32)
            out.seconds["depth"] = time.perf_counter() - t
        return out

    def to_8bit(self, out: RenderOutput, seed: int = 0, exposure: dict[str, float] | None = None) -> dict[tuple[str, str], np.ndarray]:
        """The camera model applied to every linear image: noise seeded per (seed, camera, illumination),
        exposure times ``exposure[illumination]`` (default 1)."""
        exposure = exposure or {}
        return {(cam, ill): self.cameras[cam].expose(
            img, np.random.default_rng([seed, list(self.cameras).index(cam), ("uv", "white").index(ill)]),
            exposure.get(ill, 1.0)) for (cam, ill), img in out.linear.items()}
