"""Typed, validated configuration: scene files, hardware models and materials (TOML)."""

from __future__ import annotations

from pathlib import Path

from transtac_sim.config.errors import ConfigError
from transtac_sim.config.hardware import HardwareModel
from transtac_sim.config.loader import parse_model, read_toml, resolve_named_file
from transtac_sim.config.materials import load_material
from transtac_sim.config.scene import Scene

__all__ = ["ConfigError", "HardwareModel", "Scene", "load_hardware", "load_material", "load_scene"]


def load_hardware(name_or_path: str | Path, relative_to: Path | None = None) -> tuple[HardwareModel, Path]:
    """A hardware model by name (``hardware_models/<name>.toml``) or path, and the file it came from."""
    try:
        path = resolve_named_file(str(name_or_path), "hardware_models", relative_to)
    except FileNotFoundError as e:
        raise ConfigError(name_or_path, [("", str(e))]) from None
    return parse_model(HardwareModel, read_toml(path), path), path


def load_scene(path: str | Path) -> Scene:
    """Parse and validate a scene file (its own keys; the referenced files are checked on assembly)."""
    path = Path(path)
    return parse_model(Scene, read_toml(path), path)
