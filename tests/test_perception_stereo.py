"""Stereo matching and triangulation (transtac_sim.perception.stereo): calibration files and their bad
inputs, rectification, the three point matchers on synthetic point sets with known answers (and the two
image-based baselines on synthetic dot images), and the linear and
refraction-aware triangulations against exact refracted paths (the simulator's label geometry) and
against a generated dataset's ``xyz_mm`` (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.stereo import (
    MATCHERS,
    MatchParams,
    load_calibration,
    match_hungarian,
    triangulate_linear,
    triangulate_refracted,
)
from transtac_sim.perception.stereo.calibration import (
    StereoCalibration,
    calibration_from_dict,
    check_image_size,
)
from transtac_sim.perception.stereo.delaunay import similar
from transtac_sim.perception.stereo.image_matchers import image_matcher
from transtac_sim.perception.stereo.matching import candidates
from transtac_sim.perception.stereo.triangulation import FlatStack, flat_stack_from_dict, load_flat_stack

FIXTURES = Path(__file__).parent / "fixtures"
K_L = [[268.5, 0.0, 319.5], [0.0, 268.5, 239.5], [0.0, 0.0, 1.0]]
K_R = [[268.5, 0.0, 321.0], [0.0, 268.5, 238.5], [0.0, 0.0, 1.0]]
# The default TransTac's calibration.json (datasets' values): 640x480, 12 mm baseline, barrel distortion.
DATASET_CALIB = {"image_size": [640, 480], "model": "pinhole", "K_left": K_L, "dist_left": [-0.12, 0.02, 0, 0, 0],
                 "K_right": K_R, "dist_right": [-0.115, 0.019, 0.0005, -0.0003, 0], "R": np.eye(3).tolist(),
                 "T": [-12.0, 0.0, 0.0], "units": "mm"}
# Its flat stack (hardware_models/transtac.toml: backing 15-17 mm from the cameras, acrylic and Solaris).
STACK = {"point_mm": [0, 0, 15.0], "normal": [0, 0, 1], "backing_thickness_mm": 2.0, "n_backing": 1.49, "n_gel": 1.41}


def _calib(**changes) -> StereoCalibration:
    return calibration_from_dict({**DATASET_CALIB, **changes})


# ---------------------------------------------------------------- calibration


@pytest.mark.parametrize("changes, message", [
    ({"K_left": None}, "missing key(s) K_left"),
    ({"R": [[1, 0], [0, 1]]}, "R has shape (2, 2)"),
    ({"dist_right": [0.1, 0.2, 0.3]}, "dist_right has 3 coefficients"),
    ({"image_size": [640]}, "image_size [640] is not [width, height]"),
    ({"model": "omni"}, "model 'omni' is not one of"),
    ({"T": [1, "x", 0]}, "T is not numeric"),
    ({"units": "m"}, "units 'm'"),
])
def test_bad_calibration_files_say_what_is_wrong(tmp_path: Path, changes: dict, message: str):
    data = {k: v for k, v in {**DATASET_CALIB, **changes}.items() if v is not None}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(data))
    with pytest.raises(PerceptionInputError) as e:
        load_calibration(tmp_path)
    assert str(e.value).startswith(f"{path}: ") and message in str(e.value)


def test_a_translation_saved_as_opencv_returns_it_is_read():
    """cv2.stereoCalibrate returns T as a 3 x 1 array; saved as it is, it is read as the vector it is."""
    calib = _calib(T=[[-12.0], [0.0], [0.0]])
    assert calib.T.shape == (3,) and calib.T.tolist() == [-12.0, 0.0, 0.0]


def test_unreadable_calibration_file(tmp_path: Path):
    (tmp_path / "calibration.json").write_text("{not json")
    with pytest.raises(PerceptionInputError, match="not readable JSON"):
        load_calibration(tmp_path / "calibration.json")
    with pytest.raises(PerceptionInputError, match="no such file"):
        load_calibration(tmp_path / "missing.json")


def _project(calib: StereoCalibration, X: np.ndarray, camera: str) -> np.ndarray:
    R, T = (np.eye(3), np.zeros(3)) if camera == "left" else (calib.R, calib.T)
    project = cv2.fisheye.projectPoints if calib.model == "fisheye" else cv2.projectPoints
    uv, _ = project(X.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], T, calib.K(camera), calib.dist(camera))
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("model, dist", [("pinhole", None), ("fisheye", [0.05, -0.01, 0.002, 0.0])])
def test_rectified_pairs_share_rows_and_linear_triangulation_is_exact(model: str, dist: list | None):
    """Without refraction (points projected by OpenCV's own model, a slightly rotated right camera)."""
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0]
    changes = {"model": model, "dist_left": dist, "dist_right": dist} if dist else {}
    calib = _calib(R=R.tolist(), T=[-12.0, 0.3, -0.2], **changes)
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-10, 10, 50), rng.uniform(-8, 8, 50), rng.uniform(17, 25, 50)])
    ul, ur = _project(calib, X, "left"), _project(calib, X, "right")
    rl, rr = calib.rectified(ul, "left"), calib.rectified(ur, "right")
    assert np.abs(rl[:, 1] - rr[:, 1]).max() < 1e-6
    assert calib.rectification.baseline_mm == pytest.approx(np.linalg.norm(calib.T))
    assert np.all(rl[:, 0] - rr[:, 0] > 0)
    assert np.abs(triangulate_linear(calib, ul, ur) - X).max() < 1e-6
    maps = calib.rectification_maps  # remap(recorded, *maps): rectified pixel -> recorded position
    for cam, u, rect in (("left", ul, rl), ("right", ur, rr)):
        ix, iy = np.round(rect).astype(int).T
        inside = (ix >= 0) & (ix < 640) & (iy >= 0) & (iy < 480)
        back = np.column_stack([maps[cam][0][iy[inside], ix[inside]], maps[cam][1][iy[inside], ix[inside]]])
        assert inside.sum() > 20 and np.abs(back - u[inside]).max() < 2.0  # within the rounding to a pixel


def test_image_size_check():
    check_image_size(_calib(), (640, 480), "left.png")
    with pytest.raises(PerceptionInputError, match="left.png: image is 320x240 px, the calibration is for 640x480"):
        check_image_size(_calib(), (320, 240), "left.png")


# ---------------------------------------------------------------- matchers on synthetic point sets

IDEAL = {"image_size": [640, 480], "K_left": K_L, "dist_left": [0] * 5, "K_right": K_L, "dist_right": [0] * 5,
         "R": np.eye(3).tolist(), "T": [-12.0, 0.0, 0.0]}


def synthetic(seed: int, *, dy_amp: float = 4.5, drop_right: float = 0.1, drop_left: float = 0.05,
              outliers: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """~110 markers >= 24 px apart, a right view made by a smooth disparity field (150-165 px) and a smooth
    y offset field of up to ``dy_amp`` px (as refraction gives) plus 0.2 px noise; some points dropped
    from each view and spurious points added. Returns left, right (px) and their ids (-1... spurious)."""
    rng = np.random.default_rng(seed)
    pts: list[np.ndarray] = []
    while len(pts) < 110:
        p = rng.uniform([170, 30], [610, 450])
        if all(np.hypot(*(p - q)) >= 24 for q in pts):
            pts.append(p)
    L = np.array(pts)
    u, v = (L[:, 0] - 320) / 320, (L[:, 1] - 240) / 240
    d = 156 + 6 * np.sin(np.pi * u) + 3 * v
    dy = dy_amp * np.clip(2 * u * v + 0.3 * v, -1, 1)
    R = np.column_stack([L[:, 0] - d, L[:, 1] + dy]) + rng.normal(0, 0.2, L.shape)
    il = np.flatnonzero(rng.random(110) >= drop_left)
    ir = rng.permutation(np.flatnonzero(rng.random(110) >= drop_right))
    left = np.vstack([L[il], rng.uniform([170, 30], [610, 450], (outliers, 2))])
    right = np.vstack([R[ir], rng.uniform([10, 30], [450, 450], (outliers, 2))])
    return left, right, np.r_[il, -1 - np.arange(outliers)], np.r_[ir, -1000 - np.arange(outliers)]


def scores(name: str, params: MatchParams, seeds=range(4), **kw) -> tuple[float, float]:
    """Precision and recall of matcher ``name`` over synthetic sets (recall of the markers in both views)."""
    calib = calibration_from_dict(IDEAL)
    ok = found = truth = 0
    for seed in seeds:
        left, right, lid, rid = synthetic(seed, **kw)
        pairs = MATCHERS[name](left, right, calib, params)
        assert pairs.shape[1] == 2 and len(np.unique(pairs[:, 0])) == len(pairs)
        ok += int(np.sum(lid[pairs[:, 0]] == rid[pairs[:, 1]]))
        found += len(pairs)
        truth += len(np.intersect1d(lid[lid >= 0], rid[rid >= 0]))
    return ok / max(found, 1), ok / truth


@pytest.mark.parametrize("name", sorted(MATCHERS))
def test_every_matcher_is_exact_on_an_easy_set(name: str):
    precision, recall = scores(name, MatchParams(), dy_amp=1.0, drop_right=0, drop_left=0, outliers=0)
    assert precision == 1.0 and recall == 1.0


def test_delaunay_recovers_the_refraction_offset_pairs_that_a_tight_gate_loses():
    """tau_epi = 3 px, true pairs offset by up to 4.5 px: NN and Hungarian miss them, Delaunay's
    propagation predicts the offset from matched neighbours."""
    p = MatchParams(tau_epi_px=3.0)
    precision, recall = scores("delaunay", p)
    assert precision >= 0.99 and recall >= 0.95
    for baseline in ("epipolar_nn", "hungarian"):
        assert scores(baseline, p)[1] < 0.85


def test_delaunay_keeps_precision_where_a_wide_gate_nn_takes_wrong_partners():
    """tau_epi = 6 px and 20 % of the right points missing: NN takes a wrong neighbour for many of
    them, the Delaunay matcher's geometric checks reject those."""
    p, hard = MatchParams(tau_epi_px=6.0), dict(drop_right=0.2, outliers=10)
    precision, recall = scores("delaunay", p, **hard)
    assert precision >= 0.99 and recall >= 0.95
    assert scores("epipolar_nn", p, **hard)[0] < 0.975


def test_hungarian_is_one_to_one_and_nn_is_not():
    calib = calibration_from_dict(IDEAL)
    left = np.array([[300.0, 200.0], [304.0, 201.0]])
    right = np.array([[145.0, 200.5]])
    nn = MATCHERS["epipolar_nn"](left, right, calib, MatchParams(disparity_px=156.0))
    hu = match_hungarian(left, right, calib, MatchParams(disparity_px=156.0))
    assert nn.tolist() == [[0, 0], [1, 0]] and hu.tolist() == [[0, 0]]


def test_delaunay_without_a_triangulation_matches_one_to_one():
    """Three left points on a line have no triangulation; the epipolar NN gives two of them one right point,
    the Delaunay matcher's fallback (the gated one-to-one assignment) does not."""
    calib = calibration_from_dict(IDEAL)
    left = np.array([[300.0, 200.0], [304.0, 200.0], [308.0, 200.0]])
    right = np.array([[144.0, 200.5], [152.5, 200.2]])
    params = MatchParams(disparity_px=156.0)
    nn = MATCHERS["epipolar_nn"](left, right, calib, params)
    assert len(np.unique(nn[:, 1])) < len(nn)
    pairs = MATCHERS["delaunay"](left, right, calib, params)
    assert len(pairs) == 2 and len(np.unique(pairs[:, 1])) == 2


@pytest.mark.parametrize("name", sorted(MATCHERS))
@pytest.mark.parametrize("n_left, n_right", [(0, 0), (0, 3), (1, 1), (2, 2), (3, 0)])
def test_matchers_take_empty_and_tiny_inputs(name: str, n_left: int, n_right: int):
    calib = calibration_from_dict(IDEAL)
    left = np.array([[300.0, 100.0], [400.0, 200.0], [350.0, 300.0]])[:n_left]
    right = left[:n_right] - [156.0, 0.0] if n_right <= n_left else np.array([[144, 100.0], [244, 200], [194, 300]])
    pairs = MATCHERS[name](left, right, calib, MatchParams())
    assert pairs.shape == (min(n_left, n_right), 2)
    assert np.all(pairs[:, 0] == pairs[:, 1])


def test_disparity_prior_is_estimated_from_the_points():
    calib = calibration_from_dict(IDEAL)
    left, right, lid, rid = synthetic(5)
    c = candidates(left, right, calib, MatchParams())
    i, j = np.nonzero(lid[:, None] == rid[None, :])
    assert abs(c.d_ref - np.median(c.disparity[i, j])) < 3.0


def test_triangle_similarity_ignores_position_and_scale_not_shape_or_mirroring():
    t = np.array([[0.0, 0.0], [30.0, 2.0], [12.0, 25.0]])
    assert similar(t, 1.3 * t + [150.0, -4.0], 0.05)
    assert not similar(t, t * [1.0, 1.6], 0.05)  # stretched
    assert not similar(t, t * [-1.0, 1.0], 0.05)  # mirrored: the same edge lengths, the other turn


def test_delaunay_shortcuts_give_scipys_triangulation():
    """The Delaunay matcher's shortcuts (delaunay.py): a right triangle is one of the view's Delaunay
    triangulation when its circumcircle is empty (the same answer as scipy's, and no answer on a square grid,
    whose points share circles), and the propagation's edges come from the triangles in the order of
    ``vertex_neighbor_vertices``, nearest first."""
    from scipy.spatial import Delaunay

    from transtac_sim.perception.stereo.delaunay import _delaunay_triangles, _edges, _triangles

    rng = np.random.default_rng(3)
    p = rng.uniform(0.0, 600.0, (110, 2))
    t = Delaunay(p)
    others = rng.integers(0, len(p), (400, 3))
    others = others[(others[:, 0] != others[:, 1]) & (others[:, 1] != others[:, 2]) & (others[:, 0] != others[:, 2])]
    asked = np.vstack([t.simplices, others])
    truth = {tuple(sorted(x)) for x in t.simplices.tolist()}
    answer = _delaunay_triangles(p, asked)
    assert answer is not None and answer.tolist() == [tuple(sorted(x)) in truth for x in asked.tolist()]
    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(5.0)), axis=-1).reshape(-1, 2) * 22.0
    assert _delaunay_triangles(grid, Delaunay(grid).simplices) is None

    v, w = _edges(_triangles(p), np.arange(len(p)), p)
    indptr, indices = t.vertex_neighbor_vertices
    edges = np.column_stack([np.repeat(np.arange(len(p)), np.diff(indptr)), indices])
    edges = edges[np.lexsort((np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1), edges[:, 0]))]
    assert np.array_equal(np.column_stack([v, w]), edges)


def _dots(points: np.ndarray) -> np.ndarray:
    """A dark 640x480 grey image with a bright anti-aliased dot of radius 3 px at each point (px)."""
    im = np.zeros((480, 640), np.float32)
    for u, v in np.round(points * 16).astype(int):
        cv2.circle(im, (int(u), int(v)), 48, 1.0, -1, cv2.LINE_AA, shift=4)
    return (cv2.GaussianBlur(im, (0, 0), 1.0) * 200).astype(np.uint8)


@pytest.mark.parametrize("name", ["farneback", "sgbm"])
def test_image_matchers_follow_the_images(name: str):
    calib = calibration_from_dict(IDEAL)
    left, right, lid, rid = synthetic(0, drop_right=0, drop_left=0, outliers=0)
    pairs = image_matcher(name, _dots(left), _dots(right))(left, right, calib, MatchParams())
    assert np.mean(lid[pairs[:, 0]] == rid[pairs[:, 1]]) >= 0.98 and len(pairs) >= 100
    blank = image_matcher(name, _dots(left), np.zeros((480, 640), np.uint8))(left, right, calib, MatchParams())
    assert np.sum(lid[blank[:, 0]] == rid[blank[:, 1]]) < 50  # without the right image's dots: guesses
    with pytest.raises(PerceptionInputError, match="image is 320x240 px"):
        image_matcher(name, np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint8))(left, right, calib)


def test_sgbm_matcher_matches_markers_by_the_left_edge():
    """SGBM leaves the leftmost minDisparity + numDisparities columns without a disparity (184 px for these
    disparities of about 156 px); the images are padded so that markers there are matched too."""
    calib = calibration_from_dict(IDEAL)
    left, right, lid, rid = synthetic(0, drop_right=0, drop_left=0, outliers=0)
    edge = lid[(left[:, 0] < 184.0)]
    assert len(edge) >= 3
    pairs = image_matcher("sgbm", _dots(left), _dots(right))(left, right, calib, MatchParams())
    matched = {int(lid[i]) for i, j in pairs if lid[i] == rid[j]}
    assert set(edge.tolist()) <= matched


# ---------------------------------------------------------------- triangulation


@pytest.mark.parametrize("changes, message", [
    ({"n_gel": None}, "missing key(s) n_gel"),
    ({"normal": [0, 0, 0]}, "normal non-zero"),
    ({"n_backing": 0.9}, "refractive indices >= 1"),
    ({"normal": [0, 0, -1]}, "in front of the left camera"),
])
def test_bad_flat_stack_files_say_what_is_wrong(tmp_path: Path, changes: dict, message: str):
    path = tmp_path / "stack.json"
    path.write_text(json.dumps({k: v for k, v in {**STACK, **changes}.items() if v is not None}))
    with pytest.raises(PerceptionInputError) as e:
        load_flat_stack(path)
    assert message in str(e.value)


def _exact_pixels(calib: StereoCalibration, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Recorded pixels of points in the gel along their exact refracted paths (the simulator's labels)."""
    from transtac_sim.labels.refraction import PlanarStack, refracted_paths

    planes = PlanarStack(z_back=15.0, z_bond=17.0, n_backing=1.49, n_gel=1.41)
    out = []
    for cam, centre, R in (("left", np.zeros(3), np.eye(3)), ("right", calib.right_centre_mm, calib.R)):
        d = refracted_paths(planes, centre, X).directions_left @ R.T
        uv, _ = cv2.projectPoints(d, np.zeros(3), np.zeros(3), calib.K(cam), calib.dist(cam))
        out.append(uv.reshape(-1, 2))
    return out[0], out[1]


def test_refraction_aware_triangulation_is_exact_and_linear_is_not():
    calib = _calib()
    rng = np.random.default_rng(2)
    X = np.column_stack([rng.uniform(-10, 14, 200), rng.uniform(-9, 9, 200), rng.uniform(17.3, 21.9, 200)])
    ul, ur = _exact_pixels(calib, X)
    err_refracted = np.linalg.norm(triangulate_refracted(calib, flat_stack_from_dict(STACK), ul, ur) - X, axis=1)
    err_linear = np.linalg.norm(triangulate_linear(calib, ul, ur) - X, axis=1)
    assert err_refracted.max() < 1e-6
    assert np.median(err_linear) > 0.5  # the pinhole model puts the markers several 0.1 mm off
    wrong = FlatStack(np.array([0, 0, 15.0]), np.array([0, 0, 1.0]), 2.0, 1.49, 1.0)  # gel as air
    assert np.median(np.linalg.norm(triangulate_refracted(calib, wrong, ul, ur) - X, axis=1)) > 0.5


def test_triangulation_of_nothing():
    calib, stack = _calib(), flat_stack_from_dict(STACK)
    assert triangulate_linear(calib, np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 3)
    assert triangulate_refracted(calib, stack, np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 3)


@pytest.mark.slow
def test_triangulation_against_a_generated_datasets_labels(tmp_path: Path):
    """A tiny dataset through the simulator: refraction-aware triangulation of the labels' ``uv`` gives
    their ``xyz_mm``; the stack comes from the sensor's hardware model as scripts/bench_matching.py does."""
    from transtac_sim.dataset.generate import generate
    from transtac_sim.sensor.assembly import build_sensor

    generate(FIXTURES / "tiny_rest.toml", tmp_path / "ds", frames=1, sequences=1)
    calib = load_calibration(tmp_path / "ds")
    sensor = build_sensor(FIXTURES / "tiny_sensor.toml")
    z_back = float(sensor.gel_origin_in_left_mm[2]) - sensor.hardware.backing.thickness_mm
    stack = flat_stack_from_dict({"point_mm": [0, 0, z_back], "normal": [0, 0, 1],
                                  "backing_thickness_mm": sensor.hardware.backing.thickness_mm,
                                  "n_backing": sensor.backing.refractive_index, "n_gel": sensor.gel.refractive_index})
    labels = json.loads(next((tmp_path / "ds").rglob("labels.json")).read_text())
    both = [m for m in labels["markers"] if m["left"]["visible"] and m["right"]["visible"]]
    assert len(both) >= 10
    ul, ur = (np.array([m[c]["uv"] for m in both]) for c in ("left", "right"))
    X = np.array([m["xyz_mm"] for m in both])
    assert np.abs(triangulate_refracted(calib, stack, ul, ur) - X).max() < 1e-4
    assert np.median(np.linalg.norm(triangulate_linear(calib, ul, ur) - X, axis=1)) > 0.5
