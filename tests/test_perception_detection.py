"""The marker detectors' geometry against exactly known centres: intensity centroids, the blob baseline,
the learned detector's targets and decoding, and the detection metrics."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_markers import draw_markers, grid_markers

from transtac_sim.perception.detection.blob import detect_blobs
from transtac_sim.perception.detection.network import STRIDE, decode, normalise
from transtac_sim.perception.detection.refine import intensity_centroids
from transtac_sim.perception.evaluation.detection import DetectionTally, match_points
from transtac_sim.perception.training.targets import make_targets


def test_intensity_centroid_recovers_subpixel_centres_over_a_leak_background():
    uv = grid_markers()
    img = draw_markers(uv, background=12.0)  # a grey white-light leak under the markers
    start = uv + np.random.default_rng(1).uniform(-0.8, 0.8, uv.shape)
    got = intensity_centroids(img[:, :, 1].astype(np.float32), start, half_px=5)
    assert np.abs(got - uv).max() < 0.05


def test_blob_baseline_finds_every_marker_to_a_twentieth_of_a_pixel():
    uv = grid_markers()
    det = detect_blobs(draw_markers(uv, level=30.0))
    i, j, d = match_points(det.uv, uv, 1.0)
    assert len(det) == len(uv) == len(d)
    assert d.max() < 0.05


def test_blob_baseline_ignores_a_grey_leak_and_scales_with_exposure():
    uv = grid_markers()
    for level, leak in ((12.0, 0.0), (200.0, 0.0), (30.0, 25.0)):
        det = detect_blobs(draw_markers(uv, level=level, background=leak))
        assert len(match_points(det.uv, uv, 0.2)[2]) == len(uv) == len(det), (level, leak)


def test_targets_decode_back_to_the_exact_centres():
    """make_targets and decode use the same pixel convention: a perfect network output gives back the
    centres to float precision."""
    uv = grid_markers((96, 128))
    t = make_targets(uv, np.full((len(uv), 2), 7.0), (96, 128))
    assert t["heat"].shape == (1, 96 // STRIDE, 128 // STRIDE) and t["mask"].sum() == len(uv)
    logits = np.where(t["heat"] >= 1.0, 8.0, -8.0 + 4.0 * t["heat"])
    got, score, size = decode(logits, t["offset"], t["size"], 0.5)
    i, j, d = match_points(got, uv, 0.01)
    assert len(d) == len(uv) == len(got) and d.max() < 1e-4
    assert np.allclose(size, 7.0)


def test_normalise_is_independent_of_exposure():
    uv = grid_markers()
    a, b = normalise(draw_markers(uv, level=20.0)), normalise(draw_markers(uv, level=80.0))
    assert a.shape == (3, 96, 128) and a.max() == pytest.approx(1.0, abs=0.06)
    assert np.abs(a - b).max() < 0.06


def test_detection_tally_counts_matches_within_each_radius():
    truth = np.array([[10.0, 10.0], [30.0, 10.0], [50.0, 10.0]])
    pred = np.array([[10.5, 10.0], [31.5, 10.0], [80.0, 10.0], [10.0, 11.2]])
    t = DetectionTally(radii_px=(1.0, 2.0))
    t.add(pred, truth)
    s = t.summary()
    assert s["precision@1px"] == pytest.approx(1 / 4) and s["recall@1px"] == pytest.approx(1 / 3)
    assert s["precision@2px"] == pytest.approx(2 / 4) and s["recall@2px"] == pytest.approx(2 / 3)
    assert s["error_median_px"] == pytest.approx(1.0)  # matches at 2 px: 0.5 and 1.5
