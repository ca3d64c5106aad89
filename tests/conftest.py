"""Shared fixtures: temporary scene/hardware/material files and a private mesh cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _private_mesh_cache(tmp_path_factory, monkeypatch):
    """Tests never read or fill the user's mesh cache."""
    monkeypatch.setenv("TRANSTAC_SIM_CACHE", str(tmp_path_factory.mktemp("cache")))


@pytest.fixture
def repo_copy(tmp_path: Path) -> Path:
    """A scratch copy of scenes/, hardware_models/ and materials/ that a test may edit."""
    for d in ("scenes", "hardware_models", "materials"):
        shutil.copytree(REPO / d, tmp_path / d)
    return tmp_path


def edit(path: Path, old: str, new: str) -> Path:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new, 1))
    return path
