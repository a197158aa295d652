"""Scene spec (`configs/scenes/*.toml`): the material, sample, light, camera and sensor that the
simulated rig renders. pydantic with extra="forbid", so a typo is an error naming the key.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from acquisition.config import ConfigError, format_validation_error

__all__ = [
    "Scene",
    "Material",
    "DiffuseMaterial",
    "RoughConductorMaterial",
    "RoughPlasticMaterial",
    "BlendMaterial",
    "LightSpec",
    "CameraSpec",
    "SensorSpec",
    "load_scene",
]

RGB = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DiffuseMaterial(_Strict):
    type: Literal["diffuse"] = "diffuse"
    reflectance: RGB = Field((0.5, 0.5, 0.5), description="albedo ρ per channel, f = ρ/π")


class RoughConductorMaterial(_Strict):
    """Mitsuba `roughconductor`. alpha is the RMS slope m for Beckmann."""

    type: Literal["roughconductor"] = "roughconductor"
    distribution: Literal["beckmann", "ggx"] = "beckmann"
    alpha: float = Field(0.2, gt=0, le=2)
    # Mitsuba conductor preset name ("Au", "Cu", "Al", ..., or "none" = perfect mirror, F ≡ 1),
    # or explicit eta/k per channel.
    conductor: str | None = "none"
    eta: RGB | None = None
    k: RGB | None = None
    specular_reflectance: RGB = (1.0, 1.0, 1.0)


class RoughPlasticMaterial(_Strict):
    type: Literal["roughplastic"] = "roughplastic"
    distribution: Literal["beckmann", "ggx"] = "beckmann"
    alpha: float = Field(0.1, gt=0, le=2)
    diffuse_reflectance: RGB = (0.5, 0.5, 0.5)
    int_ior: float = Field(1.49, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class BlendMaterial(_Strict):
    """Mitsuba `blendbsdf`: f = (1 − weight)·first + weight·second."""

    type: Literal["blend"] = "blend"
    weight: float = Field(0.5, ge=0, le=1)
    first: Material
    second: Material


Material = Annotated[
    DiffuseMaterial | RoughConductorMaterial | RoughPlasticMaterial | BlendMaterial,
    Field(discriminator="type"),
]
BlendMaterial.model_rebuild()


class SampleSpec(_Strict):
    size_m: float = Field(0.05, gt=0, description="side of the square flat sample")


class LightSpec(_Strict):
    type: Literal["point"] = "point"
    intensity_W_sr: RGB = Field((10.0, 10.0, 10.0), description="radiant intensity at level 1")


class CameraSpec(_Strict):
    resolution: tuple[int, int] = (64, 64)
    fov_deg: float = Field(12.0, gt=0, lt=170, description="horizontal field of view")
    f_number: float = Field(4.0, gt=0)
    format: Literal["exr", "dng"] = "exr"


class SensorSpec(_Strict):
    """EMVA 1288 sensor: e = Poisson(QE·photons·(1+PRNU) + dark·t), DN = black + K·(e + read)."""

    pixel_pitch_m: float = Field(5e-6, gt=0)
    quantum_efficiency: float = Field(0.6, gt=0, le=1)
    wavelength_m: float = Field(550e-9, gt=0, description="photon energy h·c/λ for W → photons")
    full_well_e: float = Field(30000.0, gt=0)
    read_noise_e: float = Field(3.0, ge=0)
    dark_current_e_s: float = Field(0.0, ge=0)
    prnu: float = Field(0.0, ge=0, lt=0.2)
    dsnu_e: float = Field(0.0, ge=0)
    gain_e_per_dn: float = Field(2.0, gt=0, description="electrons per digital number, 1/K")
    black_level_dn: float = Field(64.0, ge=0)
    adc_bits: int = Field(14, ge=8, le=16)
    bayer: Literal["RGGB"] | None = None
    vignetting: bool = False
    noise: bool = True


class Scene(_Strict):
    name: str = "scene"
    material: Material = Field(default_factory=DiffuseMaterial)
    sample: SampleSpec = Field(default_factory=SampleSpec)
    light: LightSpec = Field(default_factory=LightSpec)
    camera: CameraSpec = Field(default_factory=CameraSpec)
    sensor: SensorSpec = Field(default_factory=SensorSpec)
    seed: int = 0


def load_scene(path: str | Path) -> Scene:
    """Parse a scene TOML; errors are one-line `ConfigError`s naming the file and key."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such file")
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        return Scene.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err)) from None
