"""Atomic file writes: write to a temporary name in the same folder, then rename over the target, so a
reader (or a resumed run) never sees a half-written file. The temporary file is created with mode 0666, so the
file ends with the permissions the process's umask gives a plain ``open`` (``tempfile.mkstemp`` would give 0600)."""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np


def atomic_write(path: Path, write: Callable[[IO[bytes]], None]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_json(path: Path, obj) -> Path:
    return atomic_write(path, lambda f: f.write((json.dumps(obj, indent=1) + "\n").encode()))


def write_npz(path: Path, **arrays: np.ndarray) -> Path:
    return atomic_write(path, lambda f: np.savez_compressed(f, **arrays))
