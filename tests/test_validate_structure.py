"""``validate`` on well-formed JSON of the wrong shape: every problem is a ``<file>: <key>: <what>`` line (no
traceback), and the manifest's samples must match the frame folders."""

from __future__ import annotations

import json
import shutil
from functools import reduce
from operator import getitem
from pathlib import Path

import pytest
from test_dataset_format import _dataset
from typer.testing import CliRunner

from transtac_sim.cli import app
from transtac_sim.dataset import contract
from transtac_sim.dataset.validate import validate_dataset

LABELS = "sequences/seq_00000/000000/labels.json"
DROP = object()


def _set(path: Path, keys: tuple, value) -> None:
    """Set the item at ``keys`` in the JSON file ``path`` to ``value`` (DROP deletes it; ``()`` is the whole file)."""
    data = json.loads(path.read_text())
    if not keys:
        data = value
    elif value is DROP:
        del reduce(getitem, keys[:-1], data)[keys[-1]]
    else:
        reduce(getitem, keys[:-1], data)[keys[-1]] = value
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(("file", "keys", "value", "problem"), [
    (LABELS, ("markers", 0, "id"), DROP, f"{LABELS}: markers[0].id: required key is missing"),
    (LABELS, ("markers",), None, f"{LABELS}: markers: should be a list"),
    (LABELS, ("markers", 0, "left", "uv"), None, f"{LABELS}: markers[0].left: a visible marker needs its uv and bbox"),
    ("manifest.json", ("samples",), DROP, "manifest.json: samples: required key is missing"),
    ("manifest.json", (), [], "manifest.json: should hold keys and values"),
    ("calibration.json", ("image_size",), 640, "calibration.json: image_size: should be a list (got 640)"),
    ("calibration.json", ("R",), [[1.0, 0.0], [0.0, 1.0]], "calibration.json: R[2]: missing: the list is too short"),
], ids=["marker without id", "markers null", "visible without uv", "no samples", "manifest a list", "image_size 640",
        "R 2x2"])
def test_wrong_structure_is_a_problem_line(tmp_path: Path, file: str, keys: tuple, value, problem: str):
    _dataset(tmp_path, sequences=1)
    _set(tmp_path / file, keys, value)
    problems = validate_dataset(tmp_path)
    assert any(p.startswith(problem) for p in problems), problems


def test_samples_and_frame_folders_must_match(tmp_path: Path):
    _dataset(tmp_path, sequences=2)
    assert validate_dataset(tmp_path) == []
    _set(tmp_path / "manifest.json", ("samples", 3), DROP)  # seq_00001 frame 1
    shutil.rmtree(contract.frame_dir(tmp_path, "seq_00000", 1))
    assert validate_dataset(tmp_path) == [
        "sequences/seq_00001/000001: a frame folder that manifest.json's samples do not list",
        "sequences/seq_00000/000001: listed as done in manifest.json, but its labels.json is missing",
    ]


def test_command_names_the_file_and_exits_1(tmp_path: Path):
    _dataset(tmp_path, sequences=1)
    _set(tmp_path / "calibration.json", ("image_size",), 640)
    r = CliRunner().invoke(app, ["validate", str(tmp_path)])
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output  # not a traceback
    assert "calibration.json: image_size" in r.output and "1 problem(s)" in r.output
