"""Reading TOML files into validated models, with errors that name the file and key."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, TypeAdapter, ValidationError

from transtac_sim.config.errors import ConfigError, from_validation_error

M = TypeVar("M", bound=BaseModel)

#: The repository root: hardware_models/, materials/ and scenes/ live here.
REPO_ROOT = Path(__file__).resolve().parents[2]


def read_toml(path: Path) -> dict:
    """Parse a TOML file; a missing or malformed file is a ConfigError naming it."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(path, [("", "file not found")])
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, [("", f"not valid TOML: {e}")]) from None


def parse_model(model: type[M] | TypeAdapter, data: dict, source: str | Path) -> M:
    """Validate ``data`` against ``model`` (a model class or a TypeAdapter); errors name ``source``
    and the offending keys."""
    try:
        if isinstance(model, TypeAdapter):
            return model.validate_python(data)
        return model.model_validate(data)
    except ValidationError as e:
        raise from_validation_error(source, e) from None


def resolve_named_file(name_or_path: str, folder: str, relative_to: Path | None = None) -> Path:
    """Find ``name_or_path``: a path (absolute, or relative to ``relative_to``), or a bare name looked
    up as ``<repo>/<folder>/<name>.toml``."""
    candidates = []
    p = Path(name_or_path)
    if p.suffix:
        candidates += [p] if p.is_absolute() else [(relative_to or Path.cwd()) / p, Path.cwd() / p]
    else:
        candidates.append(REPO_ROOT / folder / f"{name_or_path}.toml")
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise FileNotFoundError(f"no file for {name_or_path!r} (looked at: {', '.join(map(str, candidates))})")
