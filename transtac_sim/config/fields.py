"""What the config models share: their settings and the field types several of them use."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, ConfigDict

#: Unknown keys are errors, a loaded model is immutable, and no float (alone or in a tuple or list) is nan or inf.
STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _nonzero(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if sum(c * c for c in v) < 1e-12:
        raise ValueError("must be a non-zero vector")
    return v


#: A direction in a file (the code normalises it): any vector but the zero vector.
Direction = Annotated[tuple[float, float, float], AfterValidator(_nonzero)]
