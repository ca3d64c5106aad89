"""``transtac-sim validate DIR``: check a dataset folder against the contract of DESIGN.md section 4
(docs/formats.md): the structure of each JSON file first, then the files against each other."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Annotated, Literal, TypeVar

import cv2
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from transtac_sim.config.errors import problem_lines, validation_problems
from transtac_sim.dataset import contract

Point = tuple[float, float]
Vec3 = tuple[float, float, float]
Quad = tuple[float, float, float, float]
Matrix3 = tuple[Vec3, Vec3, Vec3]
Pixels = Annotated[int, Field(gt=0)]


class _Json(BaseModel):
    """A JSON object of the contract: the keys it documents are checked, others are allowed; numbers are finite."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class Outputs(_Json):
    cameras: list[Literal["left", "right"]] = Field(min_length=1)
    illuminations: list[Literal["uv", "white"]]
    aovs: list[str]


class ResolvedScene(_Json):
    outputs: Outputs


class Sample(_Json):
    sequence: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$", description="a folder name under sequences/")
    frame: int = Field(ge=0)
    status: Literal["done", "failed"]


class Manifest(_Json):
    format_version: str
    scene: ResolvedScene
    samples: list[Sample]


class Calibration(_Json):
    image_size: tuple[Pixels, Pixels]
    model: Literal["pinhole", "fisheye"]
    K_left: Matrix3
    dist_left: list[float] = Field(min_length=4)
    K_right: Matrix3
    dist_right: list[float] = Field(min_length=4)
    R: Matrix3
    T: Vec3


class View(_Json):
    uv: Point | None
    uv_centroid: Point | None
    visible: bool
    bbox: Quad | None

    @model_validator(mode="after")
    def _visible_is_placed(self) -> View:
        if self.visible and (self.uv is None or self.bbox is None):
            raise ValueError("a visible marker needs its uv and bbox (null only where it is not visible)")
        return self


class Marker(_Json):
    id: int
    xyz_rest_mm: Vec3
    xyz_mm: Vec3
    left: View | None = None
    right: View | None = None


class IndenterState(_Json):
    name: str
    pose_mm: tuple[Quad, Quad, Quad, Quad]
    force_n: Vec3
    depth_mm: float


class Solver(_Json):
    converged: bool
    iterations: int
    residual: float
    seconds: float


class Labels(_Json):
    sequence: str
    frame: int
    time_s: float
    indenters: list[IndenterState]
    solver: Solver
    markers: list[Marker]


M = TypeVar("M", bound=_Json)


def _load(path: Path, where: str, model: type[M]) -> tuple[M | None, list[str]]:
    """``path`` parsed as ``model``, or None and what is wrong, each line naming ``where`` (and the key)."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None, [f"{where}: missing"]
    except (OSError, ValueError) as e:
        return None, [f"{where}: unreadable ({e})"]
    try:
        return model.model_validate(data), []
    except ValidationError as e:
        return None, problem_lines(where, validation_problems(e))


def validate_dataset(root: Path) -> list[str]:
    """Every problem found, as ``<file>: <what>``; an empty list means the dataset is valid."""
    root = Path(root)
    manifest, problems = _load(root / "manifest.json", "manifest.json", Manifest)
    calib, more = _load(root / "calibration.json", "calibration.json", Calibration)
    problems += more
    if manifest is not None:
        if manifest.format_version != contract.FORMAT_VERSION:
            problems.append(f"manifest.json: format_version {manifest.format_version!r}, "
                            f"expected {contract.FORMAT_VERSION!r}")
        problems += _sample_problems(root, manifest.samples)
        problems += _listed_frame_problems(root, manifest, calib.image_size if calib else None)
    problems += [f"coco/{split}.json: missing" for split in ("train", "val", "test")
                 if not (root / "coco" / f"{split}.json").is_file()]
    return problems


def _sample_problems(root: Path, samples: list[Sample]) -> list[str]:
    """Frames listed twice in the manifest, and frame folders it does not list."""
    listed = Counter((s.sequence, s.frame) for s in samples)
    problems = [f"manifest.json: samples: {seq} frame {frame} is listed {n} times"
                for (seq, frame), n in listed.items() if n > 1]
    folders = {contract.frame_dir(root, seq, frame) for seq, frame in listed}
    problems += [f"{d.relative_to(root)}: a frame folder that manifest.json's samples do not list"
                 for d in sorted(root.glob("sequences/*/*")) if d.is_dir() and d not in folders]
    return problems


def _listed_frame_problems(root: Path, manifest: Manifest, size: tuple[int, int] | None) -> list[str]:
    """Each frame the manifest lists as done: its labels (against the manifest and the calibration's image
    ``size``, when readable) and its images; marker ids must agree across the frames of a sequence."""
    outputs = manifest.scene.outputs
    problems: list[str] = []
    ids_of_sequence: dict[str, set[int]] = {}
    for sample in manifest.samples:
        if sample.status != "done":
            continue
        d = contract.frame_dir(root, sample.sequence, sample.frame)
        where = d.relative_to(root)
        if not (d / "labels.json").is_file():
            problems.append(f"{where}: listed as done in manifest.json, but its labels.json is missing")
            continue
        labels, more = _load(d / "labels.json", f"{where}/labels.json", Labels)
        problems += more + _image_problems(d, where, outputs, size)
        if labels is None:
            continue
        problems += [f"{where}/labels.json: {p}" for p in _label_problems(labels, sample, outputs.cameras, size)]
        ids = {m.id for m in labels.markers}
        if ids_of_sequence.setdefault(sample.sequence, ids) != ids:
            problems.append(f"{where}/labels.json: marker ids differ from earlier frames of {sample.sequence}")
    return problems


def _image_problems(d: Path, where: Path, outputs: Outputs, size: tuple[int, int] | None) -> list[str]:
    problems = []
    for cam in outputs.cameras:
        for ill in outputs.illuminations:
            p = d / contract.image_name(cam, ill)
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                problems.append(f"{where}/{p.name}: missing or unreadable")
            elif size is not None and (img.shape[1], img.shape[0]) != size:
                w, h = size
                problems.append(f"{where}/{p.name}: {img.shape[1]}x{img.shape[0]}, calibration says {w}x{h}")
        if "depth" in outputs.aovs and not (d / contract.depth_name(cam)).is_file():
            problems.append(f"{where}/{contract.depth_name(cam)}: missing")
    return problems


def _label_problems(labels: Labels, sample: Sample, cameras: list[str], size: tuple[int, int] | None) -> list[str]:
    """What is wrong in one frame's (well-formed) labels, without the file's name."""
    problems = []
    if (labels.sequence, labels.frame) != (sample.sequence, sample.frame):
        problems.append(f"says {labels.sequence}/{labels.frame}")
    ids = [m.id for m in labels.markers]
    if len(set(ids)) != len(ids):
        problems.append("repeated marker ids")
    for m in labels.markers:
        if lacking := [cam for cam in cameras if getattr(m, cam) is None]:
            problems.append(f"marker {m.id} lacks {lacking}")
        elif size is not None:
            problems += [f"marker {m.id} {cam} {p}" for cam in cameras for p in _view_problems(getattr(m, cam), size)]
    return problems


def _view_problems(v: View, size: tuple[int, int]) -> list[str]:
    """A visible marker's uv and bbox must lie in the image (pixel centres from 0 to size - 1)."""
    if not v.visible:
        return []
    w, h = size
    (u, vv), (x0, y0, x1, y1) = v.uv, v.bbox
    problems = []
    if not (-0.5 <= u <= w - 0.5 and -0.5 <= vv <= h - 0.5):
        problems.append(f"visible at {list(v.uv)}, outside {w}x{h}")
    if not (x0 <= x1 and y0 <= y1 and x0 >= -0.5 and y0 >= -0.5 and x1 <= w - 0.5 and y1 <= h - 0.5):
        problems.append(f"bbox {list(v.bbox)} outside the image")
    return problems
