"""Scene assembly and the two illuminations on small renders: only what is asked for is built, UV
light makes the markers glow (in proportion to their quantum yield) over a dark background, white light
shows the indenter through the gel in its colour, depth finds a known plane through the refracting
layers, and the LED irradiance follows the inverse-square and Beer-Lambert laws."""

from __future__ import annotations

import numpy as np
import pytest

from transtac_sim.camera.model import CameraEffects
from transtac_sim.rendering import demo_scene, mitsuba_env
from transtac_sim.rendering.depth import read_depth_exr, write_depth_exr
from transtac_sim.rendering.illumination import led_irradiance
from transtac_sim.rendering.inputs import IndenterSpec, LightSpec, Pigment, RenderRequest, RenderSettings
from transtac_sim.rendering.renderer import Renderer

IDEAL = CameraEffects(noise=False, quantize=False)


def _plate(z=22.0, rgb=(0.9, 0.2, 0.1)):
    from transtac_sim.rendering.geometry import box_mesh

    v, f = box_mesh([-10.0, -8.0, z], [10.0, 8.0, z + 1.0])
    return IndenterSpec(v, f, rgb)


def test_only_what_is_asked_for_is_built():
    scene = demo_scene.sensor_scene(size=(64, 48))
    r = Renderer(scene, RenderRequest(cameras=("right",), illuminations=("uv",)), RenderSettings(spp=1), IDEAL)
    assert set(r.assemblies) == {"uv"} and set(r.cameras) == {"right"}
    out = r.render()
    assert set(out.linear) == {("right", "uv")} and out.depth == {}
    r = Renderer(scene, RenderRequest(illuminations=(), aovs=("depth",)), RenderSettings(spp=1), IDEAL)
    assert set(r.assemblies) == {"geometry"}
    assert set(r.render().depth) == {"left", "right"}
    with pytest.raises(ValueError):
        RenderRequest(illuminations=("infrared",))


@pytest.mark.slow
def test_uv_markers_glow_in_proportion_to_quantum_yield():
    markers = np.array([[0.0, 0.0, 21.5], [5.0, 3.0, 21.5]])
    sums = []
    for qy in (0.8, 0.4):
        scene = demo_scene.sensor_scene(size=(96, 72), markers=markers, radius=0.4, pigment=Pigment(quantum_yield=qy))
        img = Renderer(scene, RenderRequest(cameras=("left",), illuminations=("uv",)), RenderSettings(spp=64),
                       IDEAL).render().linear[("left", "uv")]
        lum = img @ [0.2126, 0.7152, 0.0722]
        assert np.median(lum) < 1e-3 * lum.max()  # everything but the markers nearly dark
        blobs = lum > 0.2 * lum.max()
        assert img[blobs, 1].sum() > 2 * img[blobs, 0].sum()  # the emission colour (green) of the default pigment
        sums.append(lum[blobs].sum())
    assert sums[0] / sums[1] == pytest.approx(2.0, rel=0.05)


@pytest.mark.slow
def test_white_light_shows_the_indenter_through_the_gel():
    scene = demo_scene.sensor_scene(size=(96, 72), indenters=[_plate()])
    request, settings = RenderRequest(illuminations=("white",)), RenderSettings(spp=16)
    img = Renderer(scene, request, settings, IDEAL).render().linear[("left", "white")]
    scene.indenters = []
    bare = Renderer(scene, request, settings, IDEAL).render().linear[("left", "white")]
    centre, centre_bare = (x[30:42, 42:54].reshape(-1, 3).mean(axis=0) for x in (img, bare))
    assert centre[0] > 3 * centre[1] and centre[0] > 3 * centre[2]  # the plate's red
    assert centre[0] > 3 * centre_bare[0]  # far brighter than the room seen through the bare gel
    assert not np.isnan(img).any()


@pytest.mark.parametrize("gap_mm", [0.0, 2e-5])
def test_depth_finds_a_plane_through_the_gel(tmp_path, gap_mm):
    """The plate touches the gel's surface (z = 22 mm), as an indenter in contact does: at gap 0 or 2e-5 mm
    (inside Mitsuba's spawn offset, ~1e-4 mm here) the depth is still its near face, not its far one."""
    scene = demo_scene.sensor_scene(size=(64, 48), markers=np.array([[14.0, 10.0, 21.5]]),
                                    indenters=[_plate(22.0 + gap_mm)])
    r = Renderer(scene, RenderRequest(illuminations=(), aovs=("depth",)), RenderSettings(spp=1), IDEAL)
    out = r.render()
    for cam, (u, v) in {"left": (32, 24), "right": (12, 24)}.items():
        assert out.depth[cam][v, u] == pytest.approx(22.0, abs=1e-3)
    # moved in place: the plate pushed 1.5 mm into the gel's place (the gel moved with it)
    frame = demo_scene.indented_frame(scene, 0.0)
    frame.indenter_vertices = [scene.indenters[0].vertices - [0.0, 0.0, 1.5 + gap_mm]]
    frame.gel_vertices = demo_scene.dimple(scene.gel.vertices, 1.5, sigma_mm=100.0)
    d = r.render(frame).depth["left"]
    assert d[24, 32] == pytest.approx(20.5, abs=1e-3)
    write_depth_exr(tmp_path / "d.exr", d)
    back = read_depth_exr(tmp_path / "d.exr")
    assert back.dtype == np.float32 and np.array_equal(back, d)


def test_led_irradiance_inverse_square_and_beer_lambert():
    light = LightSpec("uv", np.zeros(3), np.array([0.0, 0.0, 1.0]), (0.01, 0.01), radiance=5.0)
    p = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 20.0], [10.0, 0.0, 10.0]])
    far = (np.array([100.0] * 3), np.array([101.0] * 3))
    E = led_irradiance(p, [light], "uv", far, 0.0, far, 0.0)
    A = 1e-4
    assert E == pytest.approx([5 * A / 100, 5 * A / 400, 5 * A * np.cos(np.pi / 4) / 200], rel=1e-3)
    gel = (np.array([-50.0, -50.0, 5.0]), np.array([50.0, 50.0, 30.0]))  # 5 mm (15 mm) of the path inside
    E_abs = led_irradiance(p[:2], [light], "uv", gel, 0.1, far, 0.0)
    assert E_abs == pytest.approx(E[:2] * np.exp(-0.1 * np.array([5.0, 15.0])), rel=1e-3)
    assert led_irradiance(p, [light], "white", far, 0.0, far, 0.0).sum() == 0


def test_libllvm_is_found_or_explained(monkeypatch):
    lib = mitsuba_env.find_libllvm()
    assert lib is None or "LLVM" in lib
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(mitsuba_env, "find_libllvm", lambda *a, **k: None)
    with pytest.raises(mitsuba_env.RendererUnavailable, match="apt-get install libllvm19"):
        mitsuba_env._ensure_libllvm()


def test_cpu_variant_finds_its_libllvm_by_itself():
    """In a fresh process without DRJIT_LIBLLVM_PATH the package points Dr.Jit at the libLLVM it found and
    renders with it (where Dr.Jit's own search would pick Debian's LLVM 15, that render would crash)."""
    import os
    import subprocess
    import sys

    if mitsuba_env.find_libllvm() is None:
        pytest.skip("no libLLVM 17-20 on this machine")
    code = ("from transtac_sim.rendering.mitsuba_env import select_variant; mi = select_variant('llvm_ad_rgb'); "
            "import os; s = mi.load_dict({'type': 'scene', 'i': {'type': 'direct'}, 'e': {'type': 'constant'}}); "
            "img = mi.render(s, sensor=mi.load_dict({'type': 'perspective', 'film': {'type': 'hdrfilm', 'width': 4, "
            "'height': 4}}), spp=1); print(os.environ['DRJIT_LIBLLVM_PATH'], float(mi.TensorXf(img).array[0]))")
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    lib, value = res.stdout.split()
    assert lib == mitsuba_env.find_libllvm() and float(value) == pytest.approx(1.0)


def test_scene_from_the_project_sensor_renders_its_markers():
    """The adapter from ``sensor.assembly.Sensor``: markers glow green where the labels put them."""
    from transtac_sim.labels.markers import frame_labels
    from transtac_sim.rendering.from_sensor import scene_from_sensor, spectrum_to_rgb
    from transtac_sim.sensor.assembly import build_sensor

    rgb = spectrum_to_rgb([[500.0, 0.0], [520.0, 1.0], [540.0, 0.0]])
    assert rgb[1] > 2 * rgb[0] and rgb[1] > 2 * rgb[2]  # 520 nm is green
    sensor = build_sensor()
    w, h, t = sensor.gel_size_mm
    v, f = demo_scene.gel_mesh(2.0)
    v = (v - demo_scene.GEL_LO) / (demo_scene.GEL_HI - demo_scene.GEL_LO) * [w, h, t] - [w / 2, h / 2, 0.0]
    scene = scene_from_sensor(sensor, v, f)
    for c in scene.cameras.values():
        c.size, c.K = (160, 120), c.K * [[0.25], [0.25], [1.0]]
        c.K[:2, 2] = (c.K[:2, 2] * 4 + 0.5) / 4 - 0.5
    r = Renderer(scene, RenderRequest(illuminations=("uv",)), RenderSettings(spp=32), IDEAL)
    out = r.render()
    labels = frame_labels(scene, None, {c: m.recorded for c, m in r.cameras.items()},
                          {c: out.linear[(c, "uv")] for c in r.cameras})
    for cam, lab in labels.items():
        assert lab.visible.sum() > 0.6 * len(lab.visible)
        ok = lab.visible & np.isfinite(lab.uv_centroid).all(axis=1)
        assert ok.sum() > 0.3 * len(lab.visible)
        assert np.median(np.linalg.norm(lab.uv - lab.uv_centroid, axis=1)[ok]) < 0.3, cam
