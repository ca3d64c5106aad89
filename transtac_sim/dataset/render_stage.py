"""The render, camera and label stages of one frame, as the dataset runner calls them."""

from __future__ import annotations

import numpy as np
import trimesh

from transtac_sim.camera.model import CameraEffects
from transtac_sim.indenters.texture import speckle_albedo
from transtac_sim.labels.markers import frame_labels
from transtac_sim.rendering.from_sensor import scene_from_sensor
from transtac_sim.rendering.inputs import FrameState, RenderRequest, RenderSettings
from transtac_sim.rendering.renderer import Renderer


def _posed(mesh: trimesh.Trimesh, pose: np.ndarray, to_left: np.ndarray) -> np.ndarray:
    return mesh.vertices @ pose[:3, :3].T + pose[:3, 3] + to_left


def _albedo(indenter, index: int) -> np.ndarray | None:
    """Per-vertex white-light albedo of a textured indenter (None: its plain colour)."""
    cfg = indenter.config
    if cfg.texture == "none":
        return None
    return speckle_albedo(indenter.mesh.mesh.vertices, cfg.color_rgb, cfg.texture_scale_mm, seed=index)


class FrameRenderer:
    """Renders the asked-for images and labels of a sequence's frames; built once per sequence."""

    def __init__(self, setup, variant, clock, gel_rest_vertices: np.ndarray | None = None,
                 gel_faces: np.ndarray | None = None):
        sc, s = setup.scene, setup.sensor
        self.setup, self.variant, self.clock, self.out = setup, variant, clock, sc.outputs
        self.o = s.gel_origin_in_left_mm
        if gel_faces is None:  # no FEM: the gel is its box
            w, h, t = s.gel_size_mm
            box = trimesh.creation.box((w, h, t))
            box.apply_translation((0, 0, t / 2))
            gel_rest_vertices, gel_faces = np.asarray(box.vertices), np.asarray(box.faces)
        r = sc.render
        self.exposure = {"uv": r.exposure_uv * variant.exposure_scale, "white": r.exposure_white * variant.exposure_scale}
        ind = [(_posed(i.mesh.mesh, i.start_pose, self.o), i.mesh.mesh.faces, i.config.color_rgb, _albedo(i, k))
               for k, i in enumerate(setup.indenters)]
        self.scene = scene_from_sensor(s, gel_rest_vertices, gel_faces, ind, ambient_white=r.ambient_white)
        self.scene.lights = [type(li)(li.kind, li.centre, li.normal, li.size, li.radiance * variant.light_scale, li.u_axis)
                             for li in self.scene.lights]
        # UV renders are also what uv_centroid labels are measured on
        ills = list(self.out.illuminations)
        if self.out.labels and "uv" not in ills:
            ills.insert(0, "uv")
        self.renderer = None
        if ills or self.out.aovs:
            effects = CameraEffects(distortion=r.distortion, vignetting=r.vignetting, noise=r.noise, quantize=r.quantize)
            self.renderer = Renderer(self.scene, RenderRequest(tuple(self.out.cameras), tuple(ills), tuple(self.out.aovs)),
                                     RenderSettings(spp=r.spp, max_depth=r.max_depth, variant=r.variant), effects)

    def render(self, phys, seed: int) -> tuple[dict, dict, dict]:
        """(8-bit images per (camera, illumination), depth per camera, label views per camera)."""
        frame = FrameState(
            gel_vertices=None if phys.surface_vertices_gel_mm is None else phys.surface_vertices_gel_mm + self.o,
            marker_centres=phys.markers_gel_mm + self.o,
            indenter_vertices=[_posed(i.mesh.mesh, p, self.o) for i, p in zip(self.setup.indenters, phys.indenter_poses, strict=True)] or None,
        )
        images, depth, linear = {}, {}, {}
        if self.renderer is not None:
            with self.clock("render"):
                out = self.renderer.render(frame, seed=seed)
            linear, depth = out.linear, out.depth
            with self.clock("camera"):
                asked = {k: v for k, v in linear.items() if k[1] in self.out.illuminations}
                images = self.renderer.to_8bit(type(out)(asked, {}), seed=seed, exposure=self.exposure)
        views = {}
        if self.out.labels:
            with self.clock("labels"):
                cams = {c: m.recorded for c, m in self.renderer.cameras.items()} if self.renderer else \
                    {c: self.scene.cameras[c] for c in self.out.cameras}
                uv = {c: linear[(c, "uv")] for c in self.out.cameras if (c, "uv") in linear}
                labels = frame_labels(self.scene, frame, cams, uv)
                views = {c: lab.as_views() for c, lab in labels.items()}
        return images, depth, views
