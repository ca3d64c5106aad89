"""Training the learned detector: a tiny model's loss falls in a few CPU steps on a synthetic dataset, the
saved model loads, and its ONNX export gives the same outputs as PyTorch; the shipped model meets its
precision and recall on a small generated set."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_markers import write_tiny_dataset

from transtac_sim.perception.detection.model_file import DEFAULT_MODEL, load_model
from transtac_sim.perception.detection.network import normalise
from transtac_sim.perception.images import read_color_image
from transtac_sim.perception.training.train import TrainConfig, load_samples, train_detector


def test_tiny_model_loss_falls_and_the_model_round_trips(tmp_path: Path):
    ds = write_tiny_dataset(tmp_path / "ds", sequences=3, frames=2)
    losses = []
    cfg = TrainConfig(steps=80, batch=8, crop_px=64, width=8, learning_rate=5e-3, device="cpu", eval_every=80)
    rep = train_detector([ds], tmp_path / "m.pt", cfg, lambda step, loss, val: losses.append(loss))
    assert np.mean(losses[-2:]) < 0.5 * np.mean(losses[:2]), losses
    net, meta = load_model(tmp_path / "m.pt")
    assert meta["image_sizes"] == [(128, 96)] and meta["provenance"]["train_images"] == rep.train_images
    import onnxruntime as ort

    x = normalise(read_color_image(ds / "sequences/seq_00000/000000/left_uv.png"))[None]
    onnx_out = ort.InferenceSession(str(tmp_path / "m.onnx")).run(None, {"image": x})
    with torch.no_grad():
        torch_out = [t.numpy() for t in net(torch.from_numpy(x))[:3]]
    for a, b in zip(onnx_out, torch_out, strict=True):
        assert np.allclose(a, b, atol=1e-4)
    # the two runtimes (numpy + onnxruntime, and all-tensor torch) decode and refine the same markers
    from transtac_sim.perception.detection.runtime import LearnedDetector

    image = read_color_image(ds / "sequences/seq_00000/000000/left_uv.png")
    a = LearnedDetector(tmp_path / "m.pt", backend="onnx", device="cpu", score_threshold=0.05).detect([image])[0]
    b = LearnedDetector(tmp_path / "m.pt", backend="torch", device="cpu", score_threshold=0.05).detect([image])[0]
    assert len(a) == len(b) > 0
    assert np.abs(a.uv - b.uv).max() < 1e-3 and np.abs(a.score - b.score).max() < 1e-4


def test_every_eighth_sequence_is_validation(tmp_path: Path):
    ds = write_tiny_dataset(tmp_path / "ds", sequences=9, frames=1)
    train, val = load_samples([ds])
    assert {Path(s.name).parts[-3] for s in val} == {"seq_00007"}
    assert len(train) == 16 and len(val) == 2


def test_the_context_level_needs_sizes_in_multiples_of_16(tmp_path: Path):
    """MarkerNet's context level has stride 16: a crop or image size that is a multiple of 8 only is refused
    before training, by the command and by the library, with what to change."""
    from typer.testing import CliRunner

    from transtac_sim.cli import app
    from transtac_sim.perception.errors import PerceptionInputError

    ds = write_tiny_dataset(tmp_path / "ds", sequences=2, frames=1, shape_hw=(88, 128))
    res = CliRunner().invoke(app, ["train-detector", str(ds), "--out", str(tmp_path / "m.pt"), "--crop", "72",
                                   "--context"])
    assert res.exit_code == 2 and "multiple of 16 with the context level (--context)" in " ".join(res.output.split())
    with pytest.raises(ValueError, match="crop 72 px: must be a multiple of 16"):
        train_detector([ds], tmp_path / "m.pt", TrainConfig(steps=1, crop_px=72, context=True, device="cpu"))
    with pytest.raises(PerceptionInputError, match="images of 128x88 px"):
        train_detector([ds], tmp_path / "m.pt", TrainConfig(steps=1, crop_px=64, context=True, device="cpu"))
    assert not (tmp_path / "m.pt").exists()


def test_correlation_term_is_zero_for_alike_neighbours_and_one_for_orthogonal_ones():
    """L_corr = mean over neighbour pairs of (1 - cos): features equal at every marker give 0, features
    alternating between two orthogonal vectors along a row of markers give 1 (every neighbour differs)."""
    from transtac_sim.perception.training.loss import correlation_term

    centres = [np.array([[2 + 4 * k, 5] for k in range(6)])]  # cells (x, y), 4 cells apart
    feats = torch.zeros(1, 2, 10, 30)
    feats[0, 0] = 1.0
    assert float(correlation_term(feats, centres, k=1)) == pytest.approx(0.0, abs=1e-6)
    for k, (x, y) in enumerate(centres[0]):
        feats[0, :, y, x] = torch.tensor([1.0, 0.0]) if k % 2 == 0 else torch.tensor([0.0, 1.0])
    assert float(correlation_term(feats, centres, k=1)) == pytest.approx(1.0, abs=1e-6)
    far = [np.array([[2, 5], [28, 5]])]  # 26 cells apart: beyond the cluster radius, no pair
    assert float(correlation_term(feats, far)) == 0.0


@pytest.mark.slow
def test_shipped_model_on_a_generated_rest_frame(tmp_path: Path):
    """The shipped model on a freshly rendered frame of the default sensor (a marker layout it never saw):
    precision and recall at 2 px and the median error against uv_centroid."""
    from transtac_sim.dataset.generate import generate
    from transtac_sim.perception.dataset_files import labelled_images
    from transtac_sim.perception.detection.runtime import LearnedDetector
    from transtac_sim.perception.evaluation.detection import DetectionTally

    REPO = Path(__file__).resolve().parents[1]
    scene = tmp_path / "rest.toml"
    scene.write_text((REPO / "scenes" / "rest_uv_only.toml").read_text().replace('seed = 0', 'seed = 0\n')
                     .replace('[sensor]\nhardware = "transtac"', f'[sensor]\nhardware = "{REPO}/hardware_models/transtac.toml"\n'
                              '[sensor.markers]\nlayout = "poisson_disk"\ncount = 110\nmin_spacing_mm = 1.8\n'
                              'radius_mm = 0.25\ndepth_mm = 0.6\ndepth_jitter_mm = 0.1\nseed = 4242'))
    generate(scene, tmp_path / "ds", frames=1)
    det = LearnedDetector(DEFAULT_MODEL, device="cpu")
    tally = DetectionTally()
    for li in labelled_images(tmp_path / "ds"):
        tally.add(det.detect([read_color_image(li.uv_path)])[0].uv, li.truth.uv)
    s = tally.summary()
    (tmp_path / "summary.json").write_text(json.dumps(s))
    assert tally.truths > 80
    assert s["precision@2px"] >= 0.97 and s["recall@2px"] >= 0.97, s
    assert s["error_median_px"] <= 0.15, s
