"""Reading camera images and finding them on disk: a single image, a folder of images, or a dataset folder
(the UV images of its complete frames). Images are 8-bit, BGR (OpenCV's order), H x W x 3 (``read_image``
also returns grey H x W images, for calibration boards)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.dataset_files import complete_frames, pick_sequence, sequences
from transtac_sim.perception.errors import PerceptionInputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class ImageRef:
    path: Path  # where the file is
    name: str  # as reported: the path as given, or relative to the dataset folder


def is_dataset(folder: Path) -> bool:
    return (folder / "sequences").is_dir()


def find_images(target: Path) -> list[ImageRef]:
    """The images a command works on: ``target`` itself, the images in a folder (sorted by name), or a dataset's UV
    images (``dataset_uv_images``). Raises PerceptionInputError when there are none."""
    target = Path(target)
    if not target.exists():
        raise PerceptionInputError(target, "no such file or folder", "check the path")
    if target.is_file():
        return [ImageRef(target, str(target))]
    if is_dataset(target):
        refs, what = dataset_uv_images(target), "no complete frame with UV images under sequences/"
    else:
        refs = [ImageRef(p, str(p)) for p in sorted(target.iterdir())
                if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        what = f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder"
    if not refs:
        raise PerceptionInputError(target, what, "point to an image, a folder of images or a dataset folder")
    return refs


def dataset_uv_images(dataset: Path) -> list[ImageRef]:
    """The ``<camera>_uv.png`` images of every complete frame of a dataset, in sequence and frame order, named
    relative to it. A complete frame without a camera's UV image that other frames have raises PerceptionInputError
    naming it."""
    frames = [f for seq in sequences(dataset) for f in complete_frames(dataset, seq)]
    names = tuple(sorted({p.name for f in frames for p in f.glob("*_uv.png")}))
    return [ref for refs in _frame_files(dataset, frames, names) for ref in refs]


def _frame_files(dataset: Path, frames: list[Path], files: tuple[str, ...]) -> list[tuple[ImageRef, ...]]:
    """The ImageRefs of ``files`` in each of a dataset's complete ``frames`` (folders), named relative to the dataset;
    a frame without one of them raises PerceptionInputError naming it."""
    refs = []
    for fdir in frames:
        if missing := [f for f in files if not (fdir / f).is_file()]:
            raise PerceptionInputError(fdir, f"complete frame without {', '.join(missing)}",
                                       "check the dataset with `transtac-sim validate`")
        refs.append(tuple(ImageRef(fdir / f, str((fdir / f).relative_to(dataset))) for f in files))
    return refs


def sequence_files(dataset: Path, sequence: str | None, files: tuple[str, ...]) -> list[tuple[ImageRef, ...]]:
    """Per complete frame of a dataset's sequence (``sequence``, or its first), in frame order, the ImageRefs of
    ``files`` (e.g. ``("left_uv.png", "right_uv.png")``), named relative to the dataset folder. Frames without
    ``labels.json`` are unfinished and left out; a complete frame without one of ``files``, or a sequence with no
    complete frame, raises PerceptionInputError naming it."""
    dataset = Path(dataset)
    seq = pick_sequence(dataset, sequence)
    frames = complete_frames(dataset, seq)
    if not frames:
        raise PerceptionInputError(dataset / "sequences" / seq, "no complete frame (none has labels.json)",
                                   "let `transtac-sim generate` finish this sequence, or pick another one")
    return _frame_files(dataset, frames, files)


def read_image(path: Path) -> np.ndarray:
    """An 8-bit image as stored: (H, W) grey, or (H, W, 3) BGR (an alpha channel dropped). A missing, unreadable
    or empty file, or one that is not 8-bit, raises PerceptionInputError naming it."""
    path = Path(path)
    if not path.is_file():
        raise PerceptionInputError(path, "image not found", "check the path")
    if path.stat().st_size == 0:
        raise PerceptionInputError(path, "the file is empty", "re-export or re-record the image")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise PerceptionInputError(path, "not a readable image", "use PNG, JPEG, BMP or TIFF")
    if image.dtype != np.uint8:
        raise PerceptionInputError(path, f"{image.dtype} pixels, 8-bit expected", "save the image as 8-bit")
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    return image[:, :, :3] if image.ndim == 3 and image.shape[2] == 4 else image


def read_color_image(path: Path) -> np.ndarray:
    """An 8-bit BGR image (H, W, 3) (``read_image``); a single-channel file raises PerceptionInputError naming it."""
    image = read_image(path)
    if image.ndim == 2:
        raise PerceptionInputError(path, "grayscale image, the detector needs the colour (BGR) UV image",
                                   "record the camera in colour")
    return image
