"""`transtac-sim generate` end to end on a tiny sensor: the dataset validates, the same seed gives the
same bytes in several runs, a killed run resumes to the same dataset, the Ray and worker layouts give the
same bytes as an inline run, and the COCO files load in pycocotools with one annotation per visible marker.
What it refuses to write into (another scene's dataset, one whose files changed, a folder of other files, a file)
is left as it was; damaged frames of a dataset are written again on resume."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO
from mps_stand_in import stand_in
from pycocotools.coco import COCO
from typer.testing import CliRunner

from transtac_sim.config import ConfigError, load_scene
from transtac_sim.dataset import contract
from transtac_sim.dataset.generate import _SequenceWorker, generate, ray_gpu_share
from transtac_sim.dataset.inputs import input_files
from transtac_sim.dataset.validate import validate_dataset

FIXTURES = Path(__file__).parent / "fixtures"
SCENE = FIXTURES / "tiny_rest.toml"


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file of a dataset, JSON files without their wall-clock fields."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            rel = str(p.relative_to(root))
            data = p.read_bytes()
            if p.suffix == ".json":
                data = json.dumps(contract.without_timings(json.loads(data)), sort_keys=True).encode()
            out[rel] = data
    return out


def _files(root: Path) -> dict[str, bytes]:
    """Every file under ``root``, byte for byte (to check that a refused run changed nothing)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ref") / "ds"
    report = generate(SCENE, root, frames=2)
    assert report.frames_done == 6 and not report.frames_failed
    return root


def test_dataset_is_valid_and_complete(reference: Path):
    assert validate_dataset(reference) == []
    manifest = json.loads((reference / "manifest.json").read_text())
    assert len(manifest["samples"]) == 6 and {s["status"] for s in manifest["samples"]} == {"done"}
    assert {"render", "camera", "labels", "write"} <= set(manifest["stages_run"])
    assert "physics" not in manifest["stages_run"]  # contact-free: the FEM never ran
    assert (reference / "contact_sheet.png").is_file()


def test_same_seed_same_bytes(reference: Path, tmp_path: Path):
    """Two more runs give the reference's bytes (renders in other processes: test_render_determinism.py;
    a killed and resumed run, the Ray and the worker layouts: below)."""
    for k in range(2):
        generate(SCENE, tmp_path / f"again{k}", frames=2)
        assert _snapshot(tmp_path / f"again{k}") == _snapshot(reference)


def test_other_seed_other_noise(reference: Path, tmp_path: Path):
    generate(SCENE, tmp_path / "seed9", frames=2, seed=9)
    a = (reference / "sequences/seq_00000/000000/left_uv.png").read_bytes()
    b = (tmp_path / "seed9/sequences/seq_00000/000000/left_uv.png").read_bytes()
    assert a != b


def test_coco_counts_match_the_labels(reference: Path):
    visible = 0
    for labels in reference.rglob("labels.json"):
        for m in json.loads(labels.read_text())["markers"]:
            visible += m["left"]["visible"] + m["right"]["visible"]
    anns = images = 0
    for split in ("train", "val", "test"):
        coco = COCO(str(reference / "coco" / f"{split}.json"))
        anns += len(coco.getAnnIds())
        images += len(coco.getImgIds())
    assert images == 12 and anns == visible > 0


def test_resume_after_kill_gives_the_same_dataset(reference: Path, tmp_path: Path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "transtac_sim.cli", "generate", str(SCENE), "--out", str(out), "--frames", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and not any(out.rglob("labels.json")):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # mid-run: some frames written, others not
    proc.wait()
    written = len(list(out.rglob("labels.json")))
    samples = json.loads((out / "manifest.json").read_text())["samples"]  # written before the first frame
    assert 0 < written < 6 and samples == [] or written == 6
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert not list(out.rglob("*.tmp"))
    assert _snapshot(out) == _snapshot(reference)


def test_ray_backend_equals_local(reference: Path, tmp_path: Path):
    pytest.importorskip("ray")
    generate(SCENE, tmp_path / "ray", frames=2, executor="ray", workers=2)
    assert _snapshot(tmp_path / "ray") == _snapshot(reference)


def test_ray_gpu_workers_equal_local(reference: Path, tmp_path: Path, monkeypatch):
    """On a cluster with GPUs (here 2 logical ones on a CPU machine) sequences run on GPU-holding actors (2 per
    GPU with 4 workers, ``ray_gpu_share``): both GPUs solve sequences, and the dataset is the same. ``mps`` with no
    Ray address (a stand-in MPS control program here) starts the daemon around the run and stops it."""
    ray = pytest.importorskip("ray")
    log = tmp_path / "mps.log"
    stand_in(tmp_path / "bin", log)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    ray.shutdown()
    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False)
    try:
        report = generate(SCENE, tmp_path / "ray_gpus", frames=2, executor="ray", workers=4, mps=True)
    finally:
        ray.shutdown()
    assert report.gpus_used == ["0", "1"]
    assert _snapshot(tmp_path / "ray_gpus") == _snapshot(reference)
    assert log.read_text().splitlines() == ["start", "command quit"]


def test_local_workers_equal_inline(reference: Path, tmp_path: Path):
    generate(SCENE, tmp_path / "workers", frames=2, workers=2)
    assert _snapshot(tmp_path / "workers") == _snapshot(reference)


def test_refuses_to_mix_datasets(reference: Path):
    before = _snapshot(reference)
    with pytest.raises(ConfigError, match=r"another scene, seed or frame count \(seed: 3 -> 12345\)"):
        generate(SCENE, reference, frames=2, seed=12345)
    assert _snapshot(reference) == before


class _Stop(Exception):
    """Stands for a run interrupted between two sequences."""


def _stop(done: int, total: int) -> None:
    raise _Stop


def test_an_interrupted_first_run_keeps_its_identity(tmp_path: Path):
    """The manifest (the run's identity) is there before the first frame: a first run stopped after one sequence
    is not resumed with another seed; frames with no manifest at all are refused. Nothing is changed by either."""
    out = tmp_path / "ds"
    out.mkdir()  # an existing empty folder is written into
    with pytest.raises(_Stop):
        generate(SCENE, out, frames=1, on_frames=_stop)
    assert len(list(out.rglob("labels.json"))) == 1
    assert json.loads((out / "manifest.json").read_text())["samples"] == []
    before = _files(out)
    with pytest.raises(ConfigError, match=r"another scene, seed or frame count \(seed: 3 -> 9\)"):
        generate(SCENE, out, frames=1, seed=9)
    assert _files(out) == before
    (out / "manifest.json").unlink()
    before = _files(out)
    with pytest.raises(ConfigError, match=r"holds dataset frames \(sequences/\) but no manifest.json.*delete"):
        generate(SCENE, out, frames=1, seed=9)
    assert _files(out) == before


def test_input_files_name_every_file_a_scene_uses():
    """The hardware model, its materials and the indenter meshes, resolved as the scene's setup resolves them."""
    path = FIXTURES / "tiny_press.toml"
    files = input_files(load_scene(path), path)
    assert set(files) == {"sensor.hardware", "gel.material", "backing.material", "housing.material",
                          "markers.pigment", "indenters[0].mesh"}
    assert files["sensor.hardware"] == FIXTURES / "tiny_sensor.toml" and files["gel.material"].name == "solaris.toml"
    assert files["indenters[0].mesh"].resolve() == REPO / "scenes/indenters/sphere_r4.stl"
    assert all(p.is_file() for p in files.values())


def test_refuses_to_resume_after_a_used_file_changed(tmp_path: Path):
    """An edit to a material or to the hardware model (not to the scene file) between two runs is refused, naming the
    changed files, and nothing is written (calibration.json included)."""
    scene, hw, gel = tmp_path / "tiny_rest.toml", tmp_path / "tiny_sensor.toml", tmp_path / "my_gel.toml"
    shutil.copy(SCENE, scene)
    shutil.copy(REPO / "materials" / "solaris.toml", gel)
    hw.write_text((FIXTURES / "tiny_sensor.toml").read_text().replace('"solaris"', '"my_gel.toml"', 1))
    out = tmp_path / "ds"
    generate(scene, out, frames=1, sequences=1)
    assert json.loads((out / "manifest.json").read_text())["inputs"]["gel.material"]["file"] == gel.name
    before = _files(out)
    gel.write_text(gel.read_text() + "\n# edited\n")
    with pytest.raises(ConfigError, match=re.escape(f"have changed since: gel.material ({gel.name})")):
        generate(scene, out, frames=1, sequences=1)
    hw.write_text(hw.read_text().replace("radiant_power_mw = 60.0", "radiant_power_mw = 90.0"))
    with pytest.raises(ConfigError, match=re.escape(f"sensor.hardware ({hw.name}); gel.material ({gel.name})")):
        generate(scene, out, frames=1, sequences=1)
    assert _files(out) == before


def test_refuses_a_folder_of_other_files_or_a_file(tmp_path: Path):
    """``--out`` naming a folder of the user's files, or a file, is refused with what and where; nothing changes."""
    from transtac_sim.cli import app

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "calibration.json").write_text('{"mine": true}')
    (mine / "notes.txt").write_text("keep")
    before = _files(mine)
    with pytest.raises(ConfigError, match=re.escape(f"{mine}: is not empty and holds no dataset")):
        generate(SCENE, mine, frames=1)
    assert _files(mine) == before
    a_file = tmp_path / "file.txt"
    a_file.write_text("keep")
    with pytest.raises(ConfigError, match="cannot create the dataset folder"):
        generate(SCENE, a_file / "ds", frames=1)
    r = CliRunner().invoke(app, ["generate", str(SCENE), "--out", str(a_file), "--frames", "1"])
    assert r.exit_code == 2 and "exists and is not a folder" in r.output, r.output
    assert a_file.read_text() == "keep"


def test_resume_rewrites_damaged_frames(reference: Path, tmp_path: Path):
    """A frame counts as done only when its labels.json parses and its images are whole: a deleted PNG, a labels.json
    and a PNG cut short are written again (and reported), and the dataset is the uninterrupted run's again."""
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    (contract.frame_dir(out, "seq_00000", 1) / "left_uv.png").unlink()
    labels = contract.frame_dir(out, "seq_00001", 0) / "labels.json"
    labels.write_text(labels.read_text()[:50])
    png = contract.frame_dir(out, "seq_00002", 1) / "right_white.png"
    png.write_bytes(png.read_bytes()[:-20])
    report = generate(SCENE, out, frames=2)
    assert report.frames_redone == ["seq_00000/000001: left_uv.png missing or damaged",
                                    "seq_00001/000000: labels.json unreadable",
                                    "seq_00002/000001: right_white.png missing or damaged"]
    assert report.frames_skipped == 3 and report.frames_done == 6
    assert _snapshot(out) == _snapshot(reference)
    assert validate_dataset(out) == []


def test_contact_sheet_marks_an_unreadable_image(reference: Path, tmp_path: Path, monkeypatch):
    """An image damaged after generate checked it gets a captioned empty tile, not a crash at the end of the run."""
    from transtac_sim.dataset import sheet

    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    (contract.frame_dir(out, "seq_00000", 0) / "left_uv.png").write_bytes(b"not a png")
    tiles = []
    real = sheet.save_contact_sheet
    monkeypatch.setattr(sheet, "save_contact_sheet", lambda t, *a, **k: tiles.extend(t) or real(t, *a, **k))
    assert sheet.dataset_contact_sheet(out, [("seq_00000", 0)], load_scene(SCENE).outputs, seed=0).is_file()
    unreadable = [(c, t.shape) for c, t in tiles if c.endswith("unreadable")]
    assert unreadable == [("seq_00000/000000 left uv unreadable", (1, 1, 3))] and len(tiles) > 1


def test_unreadable_manifest_is_a_clear_error(reference: Path, tmp_path: Path):
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    manifest = out / "manifest.json"
    manifest.write_text(manifest.read_text()[:100])
    before = _files(out)
    with pytest.raises(ConfigError,
                       match=re.escape(f"{manifest}: unreadable (") + ".*restore the file, or choose another --out"):
        generate(SCENE, out, frames=2)
    assert _files(out) == before


def test_scene_differences_name_the_keys_that_differ():
    """The refusal to mix datasets names what differs, nested keys dotted (a default changed between package versions
    shows up as an ordinary difference)."""
    from transtac_sim.dataset.generate import scene_differences

    old = {"seed": 3, "physics": {"newton_force_rtol": None, "degree": 2}, "name": "a"}
    new = {"seed": 3, "physics": {"newton_force_rtol": 0.003, "degree": 2}, "name": "a", "sequences": 2}
    assert scene_differences(old, new) == 'physics.newton_force_rtol: null -> 0.003; sequences: "unset" -> 2'
    many = {f"k{i}": i for i in range(6)}
    assert scene_differences({}, many, shown=2) == 'k0: "unset" -> 0; k1: "unset" -> 1; and 4 more'
    assert scene_differences(old, old) == ""


@pytest.mark.parametrize("gpus, workers, share", [(1, 1, 1.0), (2, 1, 1.0), (2, 2, 1.0), (2, 4, 0.5), (1, 2, 0.5),
                                                  (2, 3, 0.5), (4, 12, 1 / 3)])
def test_ray_gpu_share(gpus: int, workers: int, share: float):
    """Each GPU holds at most ceil(workers / gpus) sequence tasks, and all GPUs are used."""
    assert ray_gpu_share(gpus, workers) == pytest.approx(share)


def _thread_counts(_task=None) -> tuple[int, list[int]]:
    import cv2
    from threadpoolctl import threadpool_info

    return cv2.getNumThreads(), [pool["num_threads"] for pool in threadpool_info()]


def test_local_workers_share_the_cores():
    """A local worker's thread pools (BLAS, OpenMP, OpenCV) get its share of the cores (K workers on C cores:
    C // K threads each, at least 1), as ``local_tasks`` starts them for ``generate`` and ``sweep``."""
    from transtac_sim.executors import local_tasks

    workers = 2 * (os.cpu_count() or 1)  # more workers than cores: one thread each
    for opencv, pools in local_tasks(_thread_counts, [None] * workers, workers, spawn=True):
        assert opencv == 1
        assert pools and all(n == 1 for n in pools)


class _ThreadProbe(_SequenceWorker):
    """``generate``'s GPU actor, asked for its thread pools."""

    def counts(self) -> tuple[int, list[int]]:
        return _thread_counts()


def test_ray_workers_share_the_cores():
    """Ray tasks (``ray_tasks``: ``generate``'s Ray path without GPUs) and GPU actors get their share of their node's
    cores, as local workers do: cores / the node's Ray CPUs each for a task (here twice as many Ray CPUs as cores: 1
    thread), cores x GPU share / the node's GPUs for an actor (half of the one GPU: half the cores, at least 1)."""
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    from transtac_sim.executors import ray_tasks

    cores = os.cpu_count() or 1
    this_module = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this_module)  # Ray's workers do not have the tests on their path
    ray.shutdown()
    ray.init(num_cpus=2 * cores, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        task_counts = list(ray_tasks(_thread_counts, [None] * 2, None, 2 * cores))
        actor = ray.remote(num_gpus=0.5, num_cpus=0)(_ThreadProbe).remote(0.5)
        opencv, pools = ray.get(actor.counts.remote())
    finally:
        ray.shutdown()
        cloudpickle.unregister_pickle_by_value(this_module)
    assert all(o == 1 and p and all(n == 1 for n in p) for o, p in task_counts)
    share = max(1, cores // 2)
    assert opencv == share and pools and all(n == share for n in pools)
