"""The real-device pipeline: marker detection, tracking (and, next, stereo matching and triangulation).

It reads camera images and a calibration file and nothing else, so it runs on a real TransTac sensor's
images as well as on generated datasets. It never imports the simulator's stages (physics, meshing,
rendering, dataset generation, labels, scene and hardware configuration) nor Warp or Mitsuba: the
import-linter contract in ``pyproject.toml`` checks that in the test suite.

Conventions (as the datasets'): pixels in the recorded (distorted) image, OpenCV convention (the centre
of the top-left pixel is (0, 0), u right, v down); images are 8-bit BGR as OpenCV reads them.
"""
