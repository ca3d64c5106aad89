"""Stereo geometry of the TransTac's camera pair: calibration and rectification (``calibration``),
matching marker detections across the two views (``matching``, ``delaunay``; the image-based baselines
in ``image_matchers``) and triangulating them, linearly or through the flat backing and gel
(``triangulation``).

Pixels are in the recorded (distorted) image, OpenCV convention; 3D points are in mm in the left camera's
OpenCV frame (x right, y down, z forward), like the datasets' ``xyz_mm`` (DESIGN.md sections 3 and 6).
"""

from __future__ import annotations

from transtac_sim.perception.stereo.calibration import StereoCalibration, load_calibration
from transtac_sim.perception.stereo.delaunay import match_delaunay
from transtac_sim.perception.stereo.image_matchers import image_matcher
from transtac_sim.perception.stereo.matching import Matcher, MatchParams, match_epipolar_nn, match_hungarian
from transtac_sim.perception.stereo.triangulation import (
    FlatStack,
    load_flat_stack,
    triangulate_linear,
    triangulate_refracted,
)

MATCHERS: dict[str, Matcher] = {
    "delaunay": match_delaunay,
    "hungarian": match_hungarian,
    "epipolar_nn": match_epipolar_nn,
}

__all__ = ["MATCHERS", "FlatStack", "MatchParams", "Matcher", "StereoCalibration", "image_matcher", "load_calibration",
           "load_flat_stack", "match_delaunay", "match_epipolar_nn", "match_hungarian", "triangulate_linear",
           "triangulate_refracted"]
