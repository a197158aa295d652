"""Scene spec (`configs/scenes/*.toml`): the material, sample, light, camera and sensor that the
simulated rig renders. pydantic with extra="forbid", so a typo is an error naming the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from plumbing.config import ConfigError, Strict, format_validation_error, load_config_data

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
    "TexturedMaterial",
    "LightSpec",
    "HolderSpec",
    "StrayLightSpec",
    "RenderSpec",
    "CameraSpec",
    "SensorSpec",
    "GeometryTruth",
    "load_scene",
    "world_scene",
]

RGB = tuple[float, float, float]


class DiffuseMaterial(Strict):
    type: Literal["diffuse"] = "diffuse"
    reflectance: RGB = Field((0.5, 0.5, 0.5), description="albedo ρ per channel, f = ρ/π")


class RoughConductorMaterial(Strict):
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


class RoughPlasticMaterial(Strict):
    type: Literal["roughplastic"] = "roughplastic"
    distribution: Literal["beckmann", "ggx"] = "beckmann"
    alpha: float = Field(0.1, gt=0, le=2)
    diffuse_reflectance: RGB = (0.5, 0.5, 0.5)
    int_ior: float = Field(1.49, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class PlasticMaterial(Strict):
    """Mitsuba `plastic`: smooth dielectric coating (a delta lobe) over a diffuse base."""

    type: Literal["plastic"] = "plastic"
    diffuse_reflectance: RGB = (0.5, 0.5, 0.5)
    int_ior: float = Field(1.49, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class ConductorMaterial(Strict):
    """Mitsuba `conductor`: a smooth mirror (delta lobe; invisible to a point light)."""

    type: Literal["conductor"] = "conductor"
    conductor: str | None = "none"
    eta: RGB | None = None
    k: RGB | None = None
    specular_reflectance: RGB = (1.0, 1.0, 1.0)


class RoughDielectricMaterial(Strict):
    """Mitsuba `roughdielectric` (reflection and transmission through a rough interface)."""

    type: Literal["roughdielectric"] = "roughdielectric"
    distribution: Literal["beckmann", "ggx"] = "beckmann"
    alpha: float = Field(0.1, gt=0, le=2)
    int_ior: float = Field(1.5046, gt=1)
    ext_ior: float = Field(1.000277, ge=1)


class MeasuredMaterial(Strict):
    """Mitsuba `measured`: an RGL tensor ``.bsdf`` file (Dupuy & Jakob 2018).

    A relative ``filename`` is resolved against the scene file's folder by `load_scene`.
    """

    type: Literal["measured"] = "measured"
    filename: str

    @model_validator(mode="after")
    def _file_exists(self) -> MeasuredMaterial:
        # Mitsuba would say so only when the first frame is rendered.
        if not Path(self.filename).is_file():
            raise ValueError(f"filename {self.filename!r}: no such file (an RGL .bsdf tensor)")
        return self


class ModelMaterial(Strict):
    """A `fitting.models` model wrapped as a Python Mitsuba BSDF (simulator.materials).

    ``parameters`` maps each model parameter to a scalar or an (R, G, B) triple; ``options``
    are the model's constructor options, e.g. {distribution = "ggx", fresnel = "schlick"}.
    """

    type: Literal["model"] = "model"
    model: str = "torrance-sparrow"
    options: dict[str, str] = Field(default_factory=dict)
    parameters: dict[str, float | RGB] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _renderable(self) -> ModelMaterial:
        """What the Python BSDF would refuse at the first render is refused when the scene is
        read — before a run directory exists (issue 22: a value found only at render time
        left a run that failed the same way on every resume)."""
        from fitting import models

        try:
            model = models.get(self.model, **self.options)
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(str(exc).strip("'\"").splitlines()[0]) from None
        known = {p.name: p for p in model.parameters}
        unknown = sorted(set(self.parameters) - set(known))
        if unknown:
            raise ValueError(
                f"{', '.join(unknown)}: not a parameter of {self.model} (parameters: "
                f"{', '.join(known)})"
            )
        missing = [n for n, p in known.items() if n not in self.parameters and p.default is None]
        if missing:
            raise ValueError(f"set parameters {', '.join(missing)} of {self.model}")
        for name, value in self.parameters.items():
            p = known[name]
            values = (value,) if isinstance(value, int | float) else value
            if not all(p.lower <= float(v) <= p.upper for v in values):
                raise ValueError(
                    f"{name} = {value}: outside {self.model}'s range [{p.lower:g}, {p.upper:g}]"
                )
        return self


class TexturedMaterial(Strict):
    """A spatially varying Lambert + Beckmann lobe (F ≡ 1): per texel of a ``texels`` × ``texels``
    grid over the sample, kd (per channel), ks and m drawn once from ``seed``.

    Rendered (simulator.texture) as Mitsuba bitmaps with nearest lookup in
    blendbsdf(diffuse ρ, roughconductor α): weight = ks, ρ = kd/(1 − ks), α = m, so per texel
    f = kd/π + ks·lobe_m exactly as for `BlendMaterial` (simulator.truth). kd is uniform in
    ``kd_range``, ks uniform in ``ks_range``, m log-uniform in ``m_range``. Texel (ix, iy) covers
    x ∈ [−s/2 + ix·t, −s/2 + (ix+1)·t) (t = s/texels), y likewise; its index is iy·texels + ix.
    """

    type: Literal["textured"] = "textured"
    texels: int = Field(32, ge=1, le=1024, description="texels per side of the sample")
    kd_range: tuple[RGB, RGB] = ((0.10, 0.10, 0.10), (0.60, 0.50, 0.40))
    ks_range: tuple[float, float] = (0.05, 0.40)
    m_range: tuple[float, float] = (0.10, 0.40)
    seed: int = 0

    @model_validator(mode="after")
    def _physical(self) -> TexturedMaterial:
        lo_ks, hi_ks = self.ks_range
        if not 0 <= lo_ks <= hi_ks < 1:
            raise ValueError("ks_range must satisfy 0 ≤ low ≤ high < 1")
        if not 0 < self.m_range[0] <= self.m_range[1] <= 2:
            raise ValueError("m_range must satisfy 0 < low ≤ high ≤ 2")
        lo, hi = np.asarray(self.kd_range[0]), np.asarray(self.kd_range[1])
        # ρ = kd/(1 − ks) is the diffuse albedo Mitsuba renders: it must stay ≤ 1.
        if np.any(lo < 0) or np.any(hi < lo) or np.any(hi / (1.0 - hi_ks) > 1.0):
            raise ValueError("kd_range must satisfy 0 ≤ low ≤ high and high/(1 − ks_high) ≤ 1")
        return self


class BlendMaterial(Strict):
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
    | TexturedMaterial
    | BlendMaterial,
    Field(discriminator="type"),
]
BlendMaterial.model_rebuild()


class SampleSpec(Strict):
    size_m: float = Field(0.05, gt=0, description="side of the square flat sample")


class LightSpec(Strict):
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
    # Beam non-uniformity: the lamp's radiant intensity falls off its axis, I(ψ) = I₀ (1 −
    # a (ψ/ψ_a)²) with a = `beam_falloff` at ψ_a = `beam_falloff_at_deg` (the rig aims the
    # axis at the sample centre, where the certificate's I₀ holds). A halogen lamp behind a
    # condenser or reflector: 1–5 % over a few degrees (lamp makers' beam plots); a bare
    # filament or an LED behind a diffuser: well under 1 %. The lab believes I₀ everywhere, so
    # each calibrated f is multiplied by 1 − a (ψ/ψ_a)² at its point. Rendered by Mitsuba's
    # `projector` emitter (a pinhole lamp with an intensity texture): point lamps only.
    beam_falloff: float = Field(0.0, ge=0, lt=1, description="intensity lost at ψ_a")
    beam_falloff_at_deg: float = Field(5.0, gt=0, lt=30)

    @model_validator(mode="after")
    def _beam_on_a_point_lamp(self) -> LightSpec:
        if self.beam_falloff > 0 and self.type != "point":
            raise ValueError(
                f"beam_falloff is rendered for a point lamp (Mitsuba projector); a {self.type} "
                "lamp's beam is its own (spot: beam_width_deg/cutoff_deg; area: Lambertian)"
            )
        return self

    def beam_profile(self, psi_rad):
        """I(ψ)/I₀: the relative radiant intensity at angle ψ (radians) off the lamp's axis."""
        x = np.asarray(psi_rad, float) / np.radians(self.beam_falloff_at_deg)
        return np.clip(1.0 - self.beam_falloff * x**2, 0.0, None)

    @property
    def area_m2(self) -> float:
        return float(np.pi * self.radius_m**2 if self.shape == "disk" else 4 * self.radius_m**2)

    @property
    def radiance_W_m2_sr(self) -> RGB:
        """Area light radiance L = I / A (Lambertian emitter: I along the normal = L·A)."""
        a = self.area_m2
        return tuple(float(i) / a for i in self.intensity_W_sr)  # type: ignore[return-value]


class HolderSpec(Strict):
    """A raised square rim around the sample: four walls that can shadow the sample at grazing
    light and, if not black, reflect light onto it (interreflection → the path integrator)."""

    rim_height_m: float = Field(0.005, gt=0)
    wall_thickness_m: float = Field(0.005, gt=0)
    gap_m: float = Field(0.0, ge=0, description="between the sample edge and the wall")
    reflectance: RGB = Field((0.0, 0.0, 0.0), description="diffuse albedo; 0 = black holder")


class StrayLightSpec(Strict):
    """Ambient stray light: a constant environment of radiance L_amb (W m⁻² sr⁻¹) over the whole
    sphere. On a Lambertian sample it adds exactly ρ·L_amb of radiance (∫ ρ/π L cos θ dω)."""

    radiance_W_m2_sr: RGB = Field((0.01, 0.01, 0.01))


class RenderSpec(Strict):
    """Rendering quality knobs the planner turns into spp and path depth."""

    target_rel_noise: float = Field(
        0.01, gt=0, lt=1, description="relative σ per pixel aimed at for stochastic effects"
    )
    max_spp: int = Field(1024, ge=1)
    spp: int | None = Field(None, ge=1, description="override the planned spp (a square)")
    nominal_light_distance_m: float = Field(
        0.5, gt=0, description="light distance the area-light noise estimate assumes"
    )


class CameraSpec(Strict):
    """The simulated camera. Its exposure is quantised as a real sensor's is, and it reports the
    exposure it took (frame metadata ``exposure_s``; the asked one is ``exposure_commanded_s``):
    ``exposure_step_s`` is a CMOS sensor's line period (machine-vision cameras: 10–30 µs; the
    exposure is a whole number of lines, the nearest), ``shutter_speeds_s`` a DSLR's table
    (1/3-stop steps; the nearest in log). Neither: the exposure asked for."""

    resolution: tuple[int, int] = (64, 64)
    fov_deg: float = Field(12.0, gt=0, lt=170, description="horizontal field of view")
    f_number: float = Field(4.0, gt=0)
    format: Literal["exr", "dng"] = "exr"
    exposure_step_s: float = Field(0.0, ge=0, lt=1)
    shutter_speeds_s: tuple[Annotated[float, Field(gt=0)], ...] = ()

    def exposure_taken_s(self, asked_s: float) -> float:
        """The exposure this camera takes when asked for `asked_s` (class docstring)."""
        if self.shutter_speeds_s:
            table = np.asarray(self.shutter_speeds_s, dtype=np.float64)
            return float(table[np.argmin(np.abs(np.log(table / asked_s)))])
        if self.exposure_step_s > 0:
            return max(1, round(asked_s / self.exposure_step_s)) * self.exposure_step_s
        return float(asked_s)


class SensorSpec(Strict):
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
    # Response non-linearity, an instrument error: collected electrons e read as
    # e·(1 + β·e/full_well), a gain that drifts by β from dark to full well. EMVA 1288
    # datasheets give linearity errors of ~0.1–1 % for machine-vision sensors (β of the same
    # order); 0 = perfectly linear, and the stage does not run.
    nonlinearity: float = Field(0.0, ge=0, lt=0.5, description="β of e·(1 + β·e/full_well)")


_AxisRole = Literal["light_theta", "light_phi", "camera_theta", "camera_phi", "sample_azimuth"]


class GeometryTruth(Strict):
    """The rig's true geometry where it differs from the rig file (a systematic error the lab
    does not know), each applied by the world to the angles the servos' encoders report:

    - `axis_zero_error_deg`: added to each axis' angle as the rig file's zero offsets compute it
      (true = believed + error), e.g. a camera arm remounted 0.3° off;
    - `backlash_deg`: the play b between the servo horn and the arm (the encoder sits on the
      servo's output shaft, so it cannot see it): the arm lags the direction it last moved by
      b/2 (true = believed − sign(last move)·b/2). Dynamixel X-series gears: ~0.25–0.35°
      (ROBOTIS e-Manual, "backlash" in each model's spec table);
    - `compliance_deg`: sag of an elevation arm under its own weight, ∝ the gravity torque, i.e.
      ∝ sin of the arm's angle from vertical: true θ = believed θ + c·sin θ (c = the sag when
      horizontal; a 0.5 m aluminium arm on an XM430 sags ~0.1–0.3°). Elevation roles only;
    - `light_distance_error_m`: the lamp's true distance from the sample centre minus the rig
      file's `light_distance_m`. A tape measure to a lamp's filament is good to a few mm
      (~2–5 mm on a 0.5 m arm; the filament sits inside an envelope). It scales the
      irradiance the lab believes by (r/(r+δ))², so every calibrated f by ≈ 1 − 2δ/r.
    - `camera_distance_error_m`: the camera's true distance (its entrance pupil) from the
      sample centre minus the rig file's `camera_distance_m`, along its line of sight: the lab
      traces each pixel's ray from the wrong point, so it puts the pixel's surface point, and
      with it the lamp's distance and angle there, slightly off. Radiance does not fall with
      distance, so f moves only through that irradiance, E(x_true)/E(x_believed) (a pupil
      inside a lens is known to ~5–10 mm);
    - `sample_bow_m`: the sample's non-flatness, a smooth dome (negative: a dish) of sagitta s
      over its half-side R: height h(x, y) = s (1 − (x² + y²)/R²), so its local normal leans by
      the slopes (∂h/∂x, ∂h/∂y) = −2 s (x, y)/R² while the lab believes it flat. A sheet sample
      (paper, foil, film) curls by 0.1–1 mm over 50 mm; a lapped tile is flat to ~10 µm. The
      irradiance at a point follows its true normal: each calibrated f × n'·ω_i / n·ω_i ≈
      1 − (h_x ω_i,x + h_y ω_i,y)/ω_i,z (and a lobe's peak moves by the slope). The heights
      themselves (≤ 1 mm at 0.5 m) are not rendered, only the normals (Mitsuba `normalmap`).
    - `sample_tilt_deg`: the sample plane's tilt on its holder, {"x": τ_x, "y": τ_y}, in the
      convention `gonio calibrate-rig` reports (calibration.arm_offsets.tilt_rotation: a point
      p of the sample's frame sits at R_y(τ_y) R_x(τ_x) p in the rig's). A holder seated on a
      burr or a sample on tape: a few tenths of a degree. Rendered by putting the arms in the
      sample's frame (positions and the camera's roll rotated by R_τᵀ), which is the same
      world; what is on the holder (sample, board, reference target) tilts with it.
    - `camera_roll_error_deg`: the camera's true turn about its optical axis on its arm minus
      the rig file's `camera_roll_deg` (a camera screwed onto a plate by one ¼-20 thread sits
      a degree or two off unless keyed; `gonio calibrate-rig` measures it). The world's arms
      carry the camera by their own forward kinematics (simulator.arms).

    Encoder quantisation (4096 ticks per revolution) needs no setting: the emulated servos
    position and report whole ticks (0.088°/tick), as the real ones do."""

    axis_zero_error_deg: dict[_AxisRole, float] = Field(default_factory=dict)
    backlash_deg: dict[_AxisRole, float] = Field(default_factory=dict)
    compliance_deg: dict[Literal["light_theta", "camera_theta"], float] = Field(
        default_factory=dict
    )
    light_distance_error_m: float = 0.0
    camera_distance_error_m: float = 0.0
    sample_bow_m: float = Field(0.0, ge=-0.005, le=0.005)
    sample_tilt_deg: dict[Literal["x", "y"], float] = Field(default_factory=dict)
    camera_roll_error_deg: float = Field(0.0, ge=-30, le=30)


def bow_slopes(sagitta_m: float, half_side_m: float, x_m, y_m) -> tuple:
    """(∂h/∂x, ∂h/∂y) of the dome h = s (1 − (x² + y²)/R²) (GeometryTruth.sample_bow_m)."""
    k = -2.0 * sagitta_m / half_side_m**2
    return k * np.asarray(x_m, float), k * np.asarray(y_m, float)


class Scene(Strict):
    name: str = "scene"
    material: Material = Field(default_factory=DiffuseMaterial)
    sample: SampleSpec = Field(default_factory=SampleSpec)
    light: LightSpec = Field(default_factory=LightSpec)
    camera: CameraSpec = Field(default_factory=CameraSpec)
    sensor: SensorSpec = Field(default_factory=SensorSpec)
    holder: HolderSpec | None = None
    stray_light: StrayLightSpec | None = None
    render: RenderSpec = Field(default_factory=RenderSpec)
    geometry: GeometryTruth = Field(default_factory=GeometryTruth)
    # The reference target's true BRDF (what the lab's certificate describes); unset: a
    # Lambertian of the rig file's certified albedo.
    reference_target: Material | None = None
    # Radiance of the flat-field source (integrating sphere port); unset: the level a lab
    # would set for the flat exposure (half the full well on axis, SimCamera.flat_radiance).
    flat_source_radiance_W_m2_sr: float | None = Field(None, gt=0)
    # The flat source's own non-uniformity, a flat-field error the lab cannot see: its radiance
    # falls by this fraction from the frame's centre to its corner, quadratically in the
    # pixel's off-axis ρ = r²/f² (L = L₀(1 − a ρ/ρ_corner)). Integrating spheres: ≤ 1 % over
    # a port; LED flat panels: 2–5 % (vendors' uniformity specs). The flat then carries it
    # into every frame: calibrated f × 1/(1 − a ρ/ρ_corner) ≈ 1 + a ρ/ρ_corner.
    flat_source_falloff: float = Field(0.0, gt=-0.5, lt=1)  # < 0: brighter at the corners
    seed: int = 0

    @model_validator(mode="after")
    def _beam_without_stray_light(self) -> Scene:
        # With stray light the lamp's level must change in the loaded scene (the ambient term
        # does not scale with it), and Mitsuba's projector takes no new intensity once loaded
        # (measured: a changed `scale` or texture leaves the render as it was).
        if self.light.beam_falloff > 0 and self.stray_light is not None:
            raise ValueError(
                "light.beam_falloff cannot be combined with [stray_light] (the lamp's level "
                "could not change in the render); leave one of them out"
            )
        return self


def _resolve_material_paths(material, base: Path) -> None:
    """Make ``measured`` filenames absolute, in place: ``data:REL`` through the data resolver
    (brdfdata.data_paths, honours $GONIO_DATA), any other relative path against the scene file."""
    if not isinstance(material, dict):
        return
    if material.get("type") == "measured" and isinstance(material.get("filename"), str):
        from brdfdata.data_paths import SCHEME, resolve_data_uri

        if material["filename"].startswith(SCHEME):
            material["filename"] = resolve_data_uri(material["filename"])
            return
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
    _resolve_material_paths(data.get("reference_target"), path.parent)
    try:
        return Scene.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, Scene)) from None


def world_scene(scene: Scene, rig) -> Scene:  # acquisition.config.RigConfig
    """The emulated world's truth for `rig`: what the scene states, and — for every camera,
    sensor, sample and lamp quantity the scene leaves unstated — the rig file's description.

    So by default the world is exactly what the lab believes it has; a value the scene states
    that differs from the rig file is a systematic error the lab does not know about (what
    calibration must then cope with, as on a real instrument). Only fields *set* in the scene
    (pydantic's `model_fields_set`) count as stated.
    """
    cam, s = rig.camera, scene
    camera_upd: dict = {}
    if "resolution" not in s.camera.model_fields_set:
        camera_upd["resolution"] = tuple(cam.resolution)
    if "fov_deg" not in s.camera.model_fields_set:
        fx = _rig_fx(rig)
        w = (camera_upd.get("resolution") or s.camera.resolution)[0]
        # Mitsuba's fov_axis="x" spans the full width: f_x = (W/2) / tan(fov/2).
        camera_upd["fov_deg"] = float(np.degrees(2.0 * np.arctan((w / 2.0) / fx)))
    if "f_number" not in s.camera.model_fields_set:
        camera_upd["f_number"] = cam.f_number
    if "format" not in s.camera.model_fields_set:
        # What such a camera writes: a RAW mosaic as DNG, three linear values per pixel as EXR.
        camera_upd["format"] = "dng" if cam.color_filter == "RGGB" else "exr"
    sensor_upd: dict = {}
    stated = s.sensor.model_fields_set
    for key, value in (
        ("pixel_pitch_m", cam.pixel_pitch_m),
        ("quantum_efficiency", cam.quantum_efficiency),
        ("wavelength_m", cam.wavelength_m),
        ("gain_e_per_dn", cam.gain_e_per_dn),
        ("black_level_dn", cam.black_level_dn),
        ("read_noise_e", cam.read_noise_e),
        ("adc_bits", cam.bit_depth),
    ):
        if key not in stated and value is not None:
            sensor_upd[key] = value
    if "bayer" not in stated:
        if cam.color_filter not in ("RGGB", "rgb"):
            raise ConfigError(
                f"camera.color_filter {cam.color_filter!r}: the simulated camera emulates an "
                "RGGB mosaic or an rgb sensor"
            )
        sensor_upd["bayer"] = "RGGB" if cam.color_filter == "RGGB" else None
    if "full_well_e" not in stated:
        # The lab's white level is the clip it measured; the simulated sensor clips where its
        # well is full, 6 σ_read above that level (simulator.camera.SimCamera.clip_level_dn).
        gain = sensor_upd.get("gain_e_per_dn", s.sensor.gain_e_per_dn)
        black = sensor_upd.get("black_level_dn", s.sensor.black_level_dn)
        read = sensor_upd.get("read_noise_e", s.sensor.read_noise_e)
        sensor_upd["full_well_e"] = (cam.white_level_dn - black) * gain + 6.0 * read
    update: dict = {
        "camera": s.camera.model_copy(update=camera_upd),
        "sensor": s.sensor.model_copy(update=sensor_upd),
    }
    if "size_m" not in s.sample.model_fields_set:
        update["sample"] = s.sample.model_copy(update={"size_m": rig.sample.size_m})
    if "intensity_W_sr" not in s.light.model_fields_set and rig.light.intensity_W_sr is not None:
        update["light"] = s.light.model_copy(
            update={"intensity_W_sr": tuple(rig.light.intensity_W_sr)}
        )
    return s.model_copy(update=update)


def _rig_fx(rig) -> float:
    if rig.calibration.intrinsics is not None:
        from acquisition.config import load_intrinsics

        return float(load_intrinsics(rig.calibration.intrinsics, rig.camera.resolution)["fx"])
    return float(rig.camera.nominal_fx_px)
