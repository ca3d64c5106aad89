"""Camera model applied after the render: lens distortion, exposure and gain, vignetting, noise, 8 bits."""

from transtac_sim.camera.model import CameraEffects, CameraModel, project

__all__ = ["CameraEffects", "CameraModel", "project"]
