"""The perception package runs where the simulator cannot: it never imports the simulator's stages (the
import-linter contract in pyproject.toml) and works with Warp, Mitsuba and Dr.Jit absent."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_linter_contract_is_kept():
    exe = Path(sys.executable).with_name("lint-imports")
    res = subprocess.run([str(exe)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "1 kept, 0 broken" in res.stdout, res.stdout + res.stderr


def test_perception_works_with_the_simulator_libraries_missing(tmp_path: Path):
    code = """
import sys, importlib.abc
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split('.')[0] in {'warp', 'mitsuba', 'drjit', 'pytetwild', 'trimesh'}:
            raise ImportError('blocked ' + name)
sys.meta_path.insert(0, Block())
import numpy as np
from transtac_sim.perception import detect, track
from transtac_sim.perception.training import train
from transtac_sim.perception.detection.blob import detect_blobs
img = np.zeros((64, 64, 3), np.uint8); img[30:35, 30:35, 1] = 40
print(len(detect_blobs(img)))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "1"
