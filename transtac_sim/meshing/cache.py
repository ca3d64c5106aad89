"""On-disk cache of gel meshes, keyed by a hash of everything that determines them.

Location: ``$TRANSTAC_SIM_CACHE/meshes`` (default ``~/.cache/transtac_sim/meshes``). Entries are written
to a temporary name and renamed, so a killed run never leaves a half-written mesh behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from importlib.metadata import version
from pathlib import Path

import numpy as np

from transtac_sim.meshing.gel_mesh import GelMesh

#: Bump when the meshing code changes what it produces for the same inputs.
MESHER_VERSION = 1


def cache_dir() -> Path:
    root = os.environ.get("TRANSTAC_SIM_CACHE") or Path.home() / ".cache" / "transtac_sim"
    return Path(root) / "meshes"


def mesh_key(**inputs) -> str:
    """Hash of the meshing inputs (floats rounded to 1 nm) plus the mesher and pytetwild versions."""
    def clean(x):
        if isinstance(x, float):
            return round(x, 6)
        if isinstance(x, (list, tuple)):
            return [clean(i) for i in x]
        return x

    payload = {k: clean(v) for k, v in sorted(inputs.items())}
    payload["_mesher"] = MESHER_VERSION
    payload["_pytetwild"] = version("pytetwild")
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:20]


def load_cached(key: str) -> GelMesh | None:
    path = cache_dir() / f"{key}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return GelMesh(z["vertices_mm"], z["tets"])


def store(key: str, mesh: GelMesh) -> Path:
    d = cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".npz.tmp")
    with os.fdopen(fd, "wb") as f:
        np.savez_compressed(f, vertices_mm=mesh.vertices_mm, tets=mesh.tets)
    path = d / f"{key}.npz"
    os.replace(tmp, path)
    return path
