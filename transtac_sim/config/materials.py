"""Material models (files in ``materials/*.toml``). Units: MPa, g/cm^3, 1/mm, nm."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, Field, TypeAdapter, field_validator

from transtac_sim.config.fields import STRICT
from transtac_sim.config.loader import parse_model, read_toml, resolve_named_file


class _Material(BaseModel):
    model_config = STRICT
    name: str = Field(min_length=1)


class Absorption(BaseModel):
    """Beer-Lambert absorption coefficients (1/mm) in the visible (RGB) and at 365 nm."""

    model_config = STRICT
    visible_rgb_per_mm: tuple[float, float, float] = Field(default=(0.0, 0.0, 0.0))
    uv365_per_mm: float = Field(default=0.0, ge=0.0, le=100.0)

    @field_validator("visible_rgb_per_mm")
    @classmethod
    def _nonnegative(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(c < 0.0 or c > 100.0 for c in v):
            raise ValueError("each absorption coefficient must be in [0, 100] 1/mm")
        return v


class Elastomer(_Material):
    """A hyperelastic, transparent solid (the gel)."""

    kind: Literal["elastomer"]
    youngs_modulus_mpa: float = Field(gt=0.0, le=1000.0)
    poisson_ratio: float = Field(ge=0.0, lt=0.5)
    density_g_cm3: float = Field(gt=0.0, le=25.0)
    refractive_index: float = Field(ge=1.0, le=3.0)
    absorption: Absorption = Absorption()


class Dielectric(_Material):
    """A rigid (or much stiffer) transparent solid: the backing."""

    kind: Literal["dielectric"]
    youngs_modulus_mpa: float = Field(gt=0.0, le=1e6)
    poisson_ratio: float = Field(ge=0.0, lt=0.5)
    refractive_index: float = Field(ge=1.0, le=3.0)
    absorption: Absorption = Absorption()


class Diffuse(_Material):
    """An opaque Lambertian surface (the housing)."""

    kind: Literal["diffuse"]
    reflectance_rgb: tuple[float, float, float]

    @field_validator("reflectance_rgb")
    @classmethod
    def _unit_interval(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(c < 0.0 or c > 1.0 for c in v):
            raise ValueError("each reflectance must be in [0, 1]")
        return v


Spectrum = list[tuple[float, float]]


class FluorescentPigment(_Material):
    """The marker pigment: absorbs near-UV, emits in the visible, and looks faint under white light."""

    kind: Literal["fluorescent_pigment"]
    excitation_spectrum: Spectrum = Field(description="[wavelength_nm, relative absorbance] pairs")
    emission_spectrum: Spectrum = Field(description="[wavelength_nm, relative emission] pairs")
    quantum_yield: float = Field(gt=0.0, le=1.0)
    uv365_absorptance: float = Field(gt=0.0, le=1.0, description="fraction of 365 nm light a marker absorbs")
    white_light_rgb: tuple[float, float, float] = Field(description="body colour seen under white light")
    white_light_opacity: float = Field(ge=0.0, le=1.0, description="0 = invisible, 1 = opaque")

    @field_validator("excitation_spectrum", "emission_spectrum")
    @classmethod
    def _valid_spectrum(cls, v: Spectrum) -> Spectrum:
        if len(v) < 2:
            raise ValueError("a spectrum needs at least two [wavelength_nm, value] pairs")
        wl = [w for w, _ in v]
        if any(b <= a for a, b in zip(wl, wl[1:], strict=False)) or wl[0] < 200 or wl[-1] > 1100:
            raise ValueError("wavelengths must increase, within [200, 1100] nm")
        if any(val < 0 for _, val in v):
            raise ValueError("spectrum values must be >= 0")
        return v


Material = Annotated[Union[Elastomer, Dielectric, Diffuse, FluorescentPigment], Field(discriminator="kind")]
_material_adapter: TypeAdapter = TypeAdapter(Material)


@cache
def load_material(name_or_path: str, relative_to: Path | None = None) -> Elastomer | Dielectric | Diffuse | FluorescentPigment:
    """Load ``materials/<name>.toml`` (or a path) and validate it."""
    path = resolve_named_file(name_or_path, "materials", relative_to)
    return parse_model(_material_adapter, read_toml(path), path)
