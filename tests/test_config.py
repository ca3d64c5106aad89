"""Every kind of bad configuration is refused with a message naming the file, the key and the range."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import REPO, edit

from transtac_sim.config import ConfigError, load_hardware, load_material, load_scene
from transtac_sim.scene_setup import load_setup
from transtac_sim.sensor.assembly import build_sensor


def _error(fn, *args) -> str:
    with pytest.raises(ConfigError) as e:
        fn(*args)
    return str(e.value)


def test_shipped_files_are_valid():
    for p in sorted((REPO / "materials").glob("*.toml")):
        load_material(str(p))
    for p in sorted((REPO / "hardware_models").glob("*.toml")):
        load_hardware(p)
    for p in sorted((REPO / "scenes").glob("*.toml")):
        load_setup(p)


def test_negative_youngs_modulus(repo_copy: Path):
    p = edit(repo_copy / "materials/solaris.toml", "youngs_modulus_mpa = 0.37", "youngs_modulus_mpa = -0.37")
    msg = _error(load_material, str(p))
    assert str(p) in msg and "youngs_modulus_mpa" in msg and "-0.37 is out of range: allowed > 0.0" in msg


def test_poisson_ratio_of_one_half(repo_copy: Path):
    p = edit(repo_copy / "materials/solaris.toml", "poisson_ratio = 0.49", "poisson_ratio = 0.5")
    msg = _error(load_material, str(p))
    assert "poisson_ratio" in msg and "0.5 is out of range: allowed < 0.5" in msg


def test_unknown_key_and_wrong_type(repo_copy: Path):
    p = edit(repo_copy / "hardware_models/transtac.toml", "thickness_mm = 5.0", "thicknes_mm = 5.0")
    msg = _error(load_hardware, p)
    assert "gel.thicknes_mm: unknown key" in msg and "gel.thickness_mm: required key is missing" in msg
    p = edit(repo_copy / "hardware_models/transtac.toml", "baseline_mm = 12.0", 'baseline_mm = "wide"')
    assert "cameras.baseline_mm" in _error(load_hardware, p)


def test_malformed_toml_names_the_file(repo_copy: Path):
    p = repo_copy / "scenes/press_slide.toml"
    p.write_text(p.read_text() + "\n[mesh\n")
    msg = _error(load_scene, p)
    assert str(p) in msg and "not valid TOML" in msg


def test_marker_layout_outside_the_gel(repo_copy: Path):
    # depth + radius beyond the 5 mm gel
    p = edit(repo_copy / "hardware_models/transtac.toml", "depth_mm = 0.6", "depth_mm = 4.9")
    msg = _error(load_hardware, p)
    assert "do not fit inside the 5.0 mm gel" in msg
    # a measured layout file with one marker beyond the footprint
    csv = repo_copy / "layout.csv"
    csv.write_text("x_mm,y_mm,depth_mm\n0,0,0.5\n17.0,0,0.5\n")
    scene = edit(repo_copy / "scenes/press_slide.toml", 'hardware = "transtac"',
                 f'hardware = "transtac"\nmarkers = {{ layout = "file", path = "{csv}", radius_mm = 0.25 }}')
    msg = _error(load_setup, scene)
    assert str(scene) in msg and "markers[1]" in msg and "outside the gel" in msg and "|x| <= 15.750" in msg


def test_poisson_disk_that_cannot_fit(repo_copy: Path):
    p = edit(repo_copy / "hardware_models/transtac.toml", "count = 110", "count = 5000")
    msg = _error(build_sensor, p)
    assert "asked for 5000" in msg and "min_spacing_mm = 1.8" in msg


def test_indenter_that_starts_inside_the_gel(repo_copy: Path):
    scene = edit(repo_copy / "scenes/press_slide.toml", "start_gap_mm = 0.3", "start_gap_mm = -1.0")
    msg = _error(load_setup, scene)
    assert "indenters[0].start_gap_mm" in msg and "1 mm inside the gel" in msg


def test_trajectory_segment_errors(repo_copy: Path):
    scene = edit(repo_copy / "scenes/press_slide.toml", '{ kind = "press", depth_mm = 1.0, frames = 4 }',
                 '{ kind = "press", depth_mm = 1.0, force_n = 2.0, frames = 0 }')
    msg = _error(load_scene, scene)
    assert "indenters[0].trajectory[0].frames: 0 is out of range: allowed >= 1" in msg


def test_missing_hardware_model_and_wrong_material_kind(repo_copy: Path):
    scene = edit(repo_copy / "scenes/press_slide.toml", 'hardware = "transtac"', 'hardware = "no_such_sensor"')
    assert "no_such_sensor" in _error(load_setup, scene)
    hw = edit(repo_copy / "hardware_models/transtac.toml", 'material = "solaris"', 'material = "acrylic"')
    msg = _error(build_sensor, hw)
    assert "gel.material" in msg and "'acrylic' is a dielectric material" in msg


def test_nan_and_inf_in_tuples_and_lists(repo_copy: Path):
    scene = edit(repo_copy / "scenes/press_slide.toml", "start_xy_mm = [0.0, 0.0]",
                 "start_xy_mm = [nan, 0.0]\nrotation_deg = [0.0, inf, 0.0]")
    msg = _error(load_scene, scene)
    assert "indenters[0].start_xy_mm[0]: Input should be a finite number (got nan)" in msg
    assert "indenters[0].rotation_deg[1]: Input should be a finite number (got inf)" in msg
    hw = edit(repo_copy / "hardware_models/transtac.toml", "distortion = [-0.12,", "distortion = [nan,")
    assert "cameras.left.distortion[0]: Input should be a finite number" in _error(load_hardware, hw)
    mat = edit(repo_copy / "materials/pla_matte_black.toml", "[0.04, 0.04, 0.04]", "[0.04, nan, 0.04]")
    assert "reflectance_rgb[1]: Input should be a finite number" in _error(load_material, str(mat))


def test_light_normal_of_zero_length(repo_copy: Path):
    hw = edit(repo_copy / "hardware_models/transtac.toml", "normal = [0.0, 0.45, 0.89]", "normal = [0.0, 0.0, 0.0]")
    assert "lights[0].normal: must be a non-zero vector" in _error(load_hardware, hw)


def test_press_through_the_gel(repo_copy: Path):
    scene = load_scene(edit(repo_copy / "scenes/press_slide.toml", "depth_mm = 1.0", "depth_mm = 5.0"))
    assert scene.depth_problems(5.0) == [
        ("indenters[0].trajectory[0].depth_mm", "5.0 mm reaches through the 5.0 mm gel (allowed: < 5.0)")]
    assert scene.depth_problems(5.5) == []
    train = load_scene(edit(repo_copy / "scenes/train_random.toml", "[0.4, 1.5]", "[0.4, 6.0]"))
    assert train.depth_problems(5.0) == [
        ("randomize.press_depth_mm", "high 6.0 mm reaches through the 5.0 mm gel (allowed: < 5.0)")]
    deep = edit(repo_copy / "scenes/press_slide.toml", "depth_mm = 5.0", "depth_mm = 40.0")
    msg = _error(load_setup, deep)
    assert str(deep) in msg and "indenters[0].trajectory[0].depth_mm: 40.0 mm reaches through the 5.0 mm gel" in msg


def test_lens_distortion_that_folds_over(repo_copy: Path):
    hw = edit(repo_copy / "hardware_models/transtac.toml", "distortion = [-0.12, 0.02,", "distortion = [-0.9, 0.0,")
    msg = _error(build_sensor, hw)
    assert str(hw) in msg and "cameras.left.distortion: the lens distortion is not invertible over the image" in msg


@pytest.mark.parametrize("name", ["/tmp/elsewhere", "../../x", ".hidden", "two words"])
def test_scene_name_that_is_not_a_folder_name(repo_copy: Path, name: str):
    """A scene's name names its default output folders (out/<name>/...): a path or an odd name is refused."""
    p = edit(repo_copy / "scenes/quickstart.toml", 'name = "quickstart"', f'name = "{name}"')
    assert "name: the scene's name names its default output folders" in _error(load_scene, p)


def test_missing_hardware_model_is_the_scenes_key(repo_copy: Path):
    p = edit(repo_copy / "scenes/quickstart.toml", 'hardware = "transtac"', 'hardware = "nohw"')
    msg = _error(load_setup, p)
    assert f"{p}: sensor.hardware: no file for 'nohw'" in msg
