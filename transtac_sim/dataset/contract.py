"""The dataset layout (DESIGN.md section 4): names and paths in one place.

```
<dataset>/manifest.json  calibration.json
<dataset>/sequences/<sequence>/<frame:06d>/{left,right}_{uv,white}.png  {left,right}_depth.exr  labels.json
<dataset>/coco/<split>.json
```
A frame is complete when its ``labels.json`` exists: it is written last, atomically, after every image.
Wall-clock fields (``solver.seconds`` in labels, ``timings`` and ``machine`` in the manifest) are the only
parts that differ between two runs of the same scene and seed on the same machine and variant.
"""

from __future__ import annotations

from pathlib import Path

#: Version of this layout; bump it with a migration note in the README when the contract changes.
FORMAT_VERSION = "1.0"
CAMERAS = ("left", "right")
ILLUMINATIONS = ("uv", "white")
#: Keys holding wall-clock times: excluded when comparing datasets for determinism.
TIMING_KEYS = frozenset({"seconds", "timings", "machine", "created_utc"})


def sequence_name(index: int) -> str:
    return f"seq_{index:05d}"


def frame_dir(root: Path, sequence: str, frame: int) -> Path:
    return Path(root) / "sequences" / sequence / f"{frame:06d}"


def image_name(camera: str, illumination: str) -> str:
    return f"{camera}_{illumination}.png"


def depth_name(camera: str) -> str:
    return f"{camera}_depth.exr"


def without_timings(obj):
    """``obj`` (parsed JSON) with every wall-clock field removed, for byte-for-byte comparisons."""
    if isinstance(obj, dict):
        return {k: without_timings(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [without_timings(v) for v in obj]
    return obj
