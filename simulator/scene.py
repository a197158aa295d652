"""Scene spec (`configs/scenes/*.toml`): the material, sample, light, camera and sensor that the
simulated rig renders. pydantic with extra="forbid", so a typo is an error naming the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from acquisition.config import ConfigError, format_validation_error, load_config_data

__all__ = [
    "Scene",
    "Material",
    "DiffuseMaterial",
    "RoughConductorMaterial",
    "RoughPlasticMaterial",
    "BlendMaterial",
    "PlasticMaterial",
    "ConductorMaterial",
    "RoughDielectricMaterial",
    "MeasuredMaterial",
    "ModelMaterial",
    "LightSpec",
    "HolderSpec",
    "StrayLightSpec",
    "RenderSpec",
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


class PlasticMaterial(_Strict):
    """Mitsuba `plastic`: smooth dielectric coating (a delta lobe) over a diffuse base."""

    type: Literal["plastic"] = "plastic"
    diffuse_reflectance: RGB = (0.5, 0.5, 0.5)
    int_ior: float = Field(1.49, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class ConductorMaterial(_Strict):
    """Mitsuba `conductor`: a smooth mirror (delta lobe; invisible to a point light)."""

    type: Literal["conductor"] = "conductor"
    conductor: str | None = "none"
    eta: RGB | None = None
    k: RGB | None = None
    specular_reflectance: RGB = (1.0, 1.0, 1.0)


class RoughDielectricMaterial(_Strict):
    """Mitsuba `roughdielectric` (reflection and transmission through a rough interface)."""

    type: Literal["roughdielectric"] = "roughdielectric"
    distribution: Literal["beckmann", "ggx"] = "beckmann"
    alpha: float = Field(0.1, gt=0, le=2)
    int_ior: float = Field(1.5046, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class MeasuredMaterial(_Strict):
    """Mitsuba `measured`: an RGL tensor ``.bsdf`` file (Dupuy & Jakob 2018).

    A relative ``filename`` is resolved against the scene file's folder by `load_scene`.
    """

    type: Literal["measured"] = "measured"
    filename: str


class ModelMaterial(_Strict):
    """A `fitting.models` model wrapped as a Python Mitsuba BSDF (simulator.materials).

    ``parameters`` maps each model parameter to a scalar or an (R, G, B) triple; ``options``
    are the model's constructor options, e.g. {distribution = "ggx", fresnel = "schlick"}.
    """

    type: Literal["model"] = "model"
    model: str = "torrance-sparrow"
    options: dict[str, str] = Field(default_factory=dict)
    parameters: dict[str, float | RGB] = Field(default_factory=dict)


class BlendMaterial(_Strict):
    """Mitsuba `blendbsdf`: f = (1 − weight)·first + weight·second."""

    type: Literal["blend"] = "blend"
    weight: float = Field(0.5, ge=0, le=1)
    first: Material
    second: Material


Material = Annotated[
    DiffuseMaterial
    | RoughConductorMaterial
    | RoughPlasticMaterial
    | PlasticMaterial
    | ConductorMaterial
    | RoughDielectricMaterial
    | MeasuredMaterial
    | ModelMaterial
    | BlendMaterial,
    Field(discriminator="type"),
]
BlendMaterial.model_rebuild()


class SampleSpec(_Strict):
    size_m: float = Field(0.05, gt=0, description="side of the square flat sample")


class LightSpec(_Strict):
    """The lamp, aimed at the sample centre.

    point  isotropic radiant intensity ``intensity_W_sr``.
    spot   Mitsuba `spot`: ``intensity_W_sr`` on axis, full inside ``beam_width_deg`` and falling
           smoothly to 0 at ``cutoff_deg`` (half-angles).
    area   a Lambertian disk (``shape = "disk"``, radius ``radius_m``) or square (``"rect"``,
           half-side ``radius_m``) facing the sample, with radiance L = I / A so that its
           intensity along its normal equals ``intensity_W_sr`` (I(θ) = L·A·cos θ) — the same
           far-field signal as a point light. It needs spp (see the planner).
    """

    type: Literal["point", "spot", "area"] = "point"
    intensity_W_sr: RGB = Field((10.0, 10.0, 10.0), description="radiant intensity at level 1")
    cutoff_deg: float = Field(20.0, gt=0, lt=90, description="spot: half-angle where it ends")
    beam_width_deg: float | None = Field(
        None, gt=0, lt=90, description="spot: half-angle of the flat core (default 3/4 cutoff)"
    )
    shape: Literal["disk", "rect"] = "disk"
    radius_m: float = Field(0.005, gt=0, description="area: disk radius or square half-side")
    drift_per_hour: float = Field(
        0.0, ge=-0.5, le=0.5, description="relative output change per hour since switch-on"
    )

    @property
    def area_m2(self) -> float:
        return float(np.pi * self.radius_m**2 if self.shape == "disk" else 4 * self.radius_m**2)

    @property
    def radiance_W_m2_sr(self) -> RGB:
        """Area light radiance L = I / A (Lambertian emitter: I along the normal = L·A)."""
        a = self.area_m2
        return tuple(float(i) / a for i in self.intensity_W_sr)  # type: ignore[return-value]


class HolderSpec(_Strict):
    """A raised square rim around the sample: four walls that can shadow the sample at grazing
    light and, if not black, reflect light onto it (interreflection → the path integrator)."""

    rim_height_m: float = Field(0.005, gt=0)
    wall_thickness_m: float = Field(0.005, gt=0)
    gap_m: float = Field(0.0, ge=0, description="between the sample edge and the wall")
    reflectance: RGB = Field((0.0, 0.0, 0.0), description="diffuse albedo; 0 = black holder")


class StrayLightSpec(_Strict):
    """Ambient stray light: a constant environment of radiance L_amb (W m⁻² sr⁻¹) over the whole
    sphere. On a Lambertian sample it adds exactly ρ·L_amb of radiance (∫ ρ/π L cos θ dω)."""

    radiance_W_m2_sr: RGB = Field((0.01, 0.01, 0.01))


class RenderSpec(_Strict):
    """Rendering quality knobs the planner turns into spp and path depth."""

    target_rel_noise: float = Field(
        0.01, gt=0, lt=1, description="relative σ per pixel aimed at for stochastic effects"
    )
    max_spp: int = Field(1024, ge=1)
    spp: int | None = Field(None, ge=1, description="override the planned spp (a square)")
    nominal_light_distance_m: float = Field(
        0.5, gt=0, description="light distance the area-light noise estimate assumes"
    )


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
    holder: HolderSpec | None = None
    stray_light: StrayLightSpec | None = None
    render: RenderSpec = Field(default_factory=RenderSpec)
    seed: int = 0


def _resolve_material_paths(material, base: Path) -> None:
    """Make relative ``measured`` filenames absolute (relative to the scene file), in place."""
    if not isinstance(material, dict):
        return
    if material.get("type") == "measured" and isinstance(material.get("filename"), str):
        f = Path(material["filename"]).expanduser()
        if not f.is_absolute():
            material["filename"] = str((base / f).resolve())
    for key in ("first", "second"):
        _resolve_material_paths(material.get(key), base)


def load_scene(path: str | Path) -> Scene:
    """Parse a scene TOML; errors are one-line `ConfigError`s naming the file and key."""
    path = Path(path)
    # The same loader as rig and plan configs: TOML or JSON only (configs are data, never
    # code), with one-line errors for a missing, unreadable or malformed file.
    data = load_config_data(path)
    _resolve_material_paths(data.get("material"), path.parent)
    try:
        return Scene.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, Scene)) from None
