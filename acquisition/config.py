"""Rig and plan configs (TOML → pydantic, extra="forbid").

Every mistake a user can type becomes a `ConfigError` (plumbing.config) with one line naming the
file, the key and the allowed range, so the CLI can print it without a traceback.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from acquisition.device_config import AravisConfig, Gphoto2Config, ScpiConfig
from plumbing.config import (
    ConfigError,
    Strict,
    format_validation_error,
    load_config_data,
)
from plumbing.inputs import MiB, check_nesting, read_input_text

__all__ = [
    "AxisConfig",
    "BusConfig",
    "LightConfig",
    "CameraConfig",
    "CAMERA_BACKEND_NAMES",
    "LIGHT_BACKEND_NAMES",
    "SampleConfig",
    "ReferenceConfig",
    "RigCalibrationConfig",
    "GeometryConfig",
    "CalibrationPhasesConfig",
    "DarkPhaseConfig",
    "FlatPhaseConfig",
    "ReferencePhaseConfig",
    "REFERENCE_POSES_DEG",
    "RigConfig",
    "PlanConfig",
    "AutoExposureConfig",
    "load_rig",
    "load_plan",
    "load_intrinsics",
    "load_arm_offsets",
    "ARM_OFFSETS_SCHEMA",
]

VELOCITY_LIMIT = {"XM430-W350": 200, "XL430-W250": 265}
_LIGHT_BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
AxisRole = Literal["light_theta", "light_phi", "camera_theta", "camera_phi", "sample_azimuth"]


class AxisConfig(Strict):
    role: AxisRole
    id: int = Field(ge=0, le=252, description="Dynamixel ID")
    model: Literal["XM430-W350", "XL430-W250"] = "XM430-W350"
    gear_ratio: float = Field(
        1.0,
        ge=0.01,
        le=1000,
        description="servo turns per axis turn (an arm's belt or gear reduction is 1 to ~100; "
        "beyond 1000 one servo tick moves the axis less than the servo can resolve)",
    )
    zero_offset_deg: float = Field(0.0, ge=-360, le=360, description="axis angle at servo tick 0")
    direction: Literal[1, -1] = 1
    min_deg: float = Field(ge=-360, le=360)
    max_deg: float = Field(ge=-360, le=360)
    profile_velocity: int = Field(60, ge=1, le=32767, description="0.229 rpm per unit")
    profile_acceleration: int = Field(20, ge=0, le=32767, description="214.577 rev/min² per unit")
    park_deg: float | None = Field(None, ge=-360, le=360, description="safe angle on stop")

    @model_validator(mode="after")
    def _range(self) -> AxisConfig:
        # Profile Velocity may not exceed the model's Velocity Limit (reg 44, factory value).
        vmax = VELOCITY_LIMIT[self.model]
        if self.profile_velocity > vmax:
            raise ValueError(
                f"profile_velocity {self.profile_velocity} exceeds the {self.model} velocity "
                f"limit {vmax} (0.229 rpm units)"
            )
        if self.min_deg >= self.max_deg:
            raise ValueError(f"min_deg ({self.min_deg}) must be below max_deg ({self.max_deg})")
        return self


class BusConfig(Strict):
    url: str = Field(description="serial device (/dev/ttyUSB0), or dxlsim://NAME for the emulator")
    baudrate: int = Field(57600, description="X-series ship at 57600")
    retries: int = Field(3, ge=0, le=20)
    on_alert: Literal["reboot", "stop"] = "stop"

    @field_validator("baudrate")
    @classmethod
    def _baud(cls, v: int) -> int:
        allowed = (9600, 57600, 115200, 1000000, 2000000, 3000000, 4000000, 4500000)
        if v not in allowed:
            raise ValueError(f"baudrate must be one of {allowed}")
        return v


# Light backends by name (factories in acquisition.rig.LIGHT_BACKENDS): "gonio-ascii" speaks
# docs/light-protocol.md on a serial line, "scpi" a SCPI supply through PyVISA.
LIGHT_BACKEND_NAMES = ("gonio-ascii", "scpi")


class LightConfig(Strict):
    backend: str = Field("gonio-ascii", description=f"one of {', '.join(LIGHT_BACKEND_NAMES)}")
    url: str = Field(
        description="serial device, lightsim://NAME for the emulator, a VISA resource "
        '(backend "scpi"), or "manual" for a lamp switched by hand (no monitor: drift is then '
        "uncorrected, and reports say so)"
    )
    scpi: ScpiConfig | None = Field(None, description='[light.scpi]: backend "scpi" settings')
    baudrate: int = Field(9600, description="serial speed of the light controller")
    level: float = Field(1.0, gt=0, le=1, description="relative intensity used for the run")
    intensity_W_sr: (
        tuple[
            Annotated[float, Field(gt=0, le=1e4)],
            Annotated[float, Field(gt=0, le=1e4)],
            Annotated[float, Field(gt=0, le=1e4)],
        ]
        | None
    ) = Field(
        None,
        description="radiant intensity per channel (R, G, B) at level 1, W/sr, from the "
        "source's calibration certificate; without it results are relative (a lamp has a "
        "positive intensity; 1e4 W/sr is beyond any source a gonioreflectometer aims at a "
        "sample)",
    )
    intensity_rel_sigma: float | None = Field(
        None,
        gt=0,
        lt=1,
        description="relative standard uncertainty (k = 1) of intensity_W_sr from the same "
        "certificate (e.g. 0.01 for 1 %); one error shared by the whole run, carried in the "
        "samples' uncertainty budget",
    )
    warmup_s: float = Field(0.0, ge=0, le=3600)
    ambient_sigma_W_m2_sr: float | None = Field(
        None,
        ge=0,
        lt=10,
        description="standard uncertainty (k = 1) of light the lamp does not cause reaching the "
        "sample (room lights, a monitor, daylight past the curtains), as a radiance: a dark lab "
        "with black curtains ~5e-4 W m⁻² sr⁻¹; measure it with the lamp off. Calibration divides "
        "it by the lamp's irradiance like the lamp's own light, so the fit carries it as an "
        "additive nuisance",
    )
    radius_m: float = Field(
        0.0,
        ge=0,
        le=0.05,
        description="radius of the lamp's exit aperture (a disk facing the sample), m; 0: a "
        "point. A lamp of radius r at distance d lights each point from a cone of half-angle "
        "r/d, which broadens a lobe; the fit averages its model over that disk (fitting."
        "likelihood, the lamp's extent)",
    )

    @field_validator("baudrate")
    @classmethod
    def _baud(cls, v: int) -> int:
        if v not in _LIGHT_BAUDS:
            raise ValueError(f"baudrate must be one of {_LIGHT_BAUDS}")
        return v

    @field_validator("backend")
    @classmethod
    def _backend(cls, v: str) -> str:
        if v not in LIGHT_BACKEND_NAMES:
            raise ValueError(
                f"unknown light backend {v!r}; known: {', '.join(LIGHT_BACKEND_NAMES)}"
            )
        return v

    @model_validator(mode="after")
    def _scpi(self) -> LightConfig:
        if self.backend == "scpi" and (self.manual or self.scpi is None):
            raise ValueError(
                'backend "scpi" needs url = a VISA resource (e.g. "ASRL/dev/ttyUSB1::INSTR") '
                "and a [light.scpi] table with full_scale"
            )
        return self

    @property
    def manual(self) -> bool:
        return self.url.strip().lower() == "manual"


# Camera backends by name (the factories register in acquisition.rig; the simulator registers
# "sim" at run time). Checked when the rig file loads, so a typo is one line before anything
# moves.
CAMERA_BACKEND_NAMES = ("sim", "folder", "gphoto2", "aravis")
ColorFilter = Literal["RGGB", "BGGR", "GRBG", "GBRG", "mono", "rgb"]


class CameraConfig(Strict):
    """The camera: which backend drives it, and what the lab knows about it (datasheet and
    calibration), which is what calibration uses — never what a simulator renders.

    Optics: the lens `focal_length_m` with `pixel_pitch_m` gives the pinhole f_x = f_y = f/p
    (principal point at the image centre) unless `[calibration] intrinsics` names the file
    `gonio calibrate-camera --json` wrote. Radiometry (camera irradiance equation, certified
    method): `f_number`, `pixel_pitch_m`, `quantum_efficiency`, `wavelength_m`, `gain_e_per_dn`;
    `black_level_dn` and `white_level_dn` (the measured clip level, which can sit far below
    2^bit_depth − 1) bound the usable counts.
    """

    backend: str = Field("sim", description=f"one of {', '.join(CAMERA_BACKEND_NAMES)}")
    model: str = Field("", description="make and model, for the record")
    resolution: tuple[int, int] = Field(description="image width, height in pixels")
    pixel_pitch_m: float = Field(gt=0, le=1e-3)
    focal_length_m: float | None = Field(None, gt=0, le=2.0)
    f_number: float = Field(gt=0, le=128)
    gain_e_per_dn: float = Field(gt=0, description="electrons per digital number (1/K)")
    black_level_dn: float = Field(ge=0)
    white_level_dn: float = Field(gt=0, description="highest unclipped DN (measured)")
    read_noise_e: float = Field(0.0, ge=0, description="temporal dark noise, electrons")
    linearity_error: float | None = Field(
        None,
        ge=0,
        lt=0.5,
        description="EMVA 1288 linearity error LE (fraction, from the datasheet: 0.1–1 % "
        "typical): named in the samples' uncertainty budget",
    )
    quantum_efficiency: float | None = Field(
        None, gt=0, le=1, description="at wavelength_m; needed for certified radiometry"
    )
    wavelength_m: float = Field(550e-9, gt=0, lt=1e-5, description="photon energy h·c/λ")
    color_filter: ColorFilter = Field(
        description='Bayer pattern of a RAW mosaic, "mono", or "rgb" (three values per pixel)'
    )
    bit_depth: int = Field(ge=8, le=32)
    exposure_min_s: float = Field(1e-5, gt=0, le=3600)
    exposure_max_s: float = Field(30.0, gt=0, le=3600)
    folder: str | None = Field(None, description='"folder": where the tethering tool writes')
    trigger_command: tuple[str, ...] | None = Field(
        None, description='"folder": argv run per frame; "{exposure_s}" is replaced'
    )
    timeout_s: float = Field(30.0, gt=0, le=3600, description="wait for a frame, wall time")
    readout_s: float = Field(0.05, ge=0, description="lab time per frame beyond the exposure")
    aravis: AravisConfig = Field(default_factory=AravisConfig, description="[camera.aravis]")
    gphoto2: Gphoto2Config = Field(default_factory=Gphoto2Config, description="[camera.gphoto2]")

    @field_validator("backend")
    @classmethod
    def _backend(cls, v: str) -> str:
        if v not in CAMERA_BACKEND_NAMES:
            raise ValueError(
                f"unknown camera backend {v!r}; known: {', '.join(CAMERA_BACKEND_NAMES)}"
            )
        return v

    @field_validator("resolution")
    @classmethod
    def _resolution(cls, v: tuple[int, int]) -> tuple[int, int]:
        if not all(8 <= n <= 100_000 for n in v):
            raise ValueError(f"resolution must be [width, height] in pixels, 8..100000 (got {v})")
        return v

    @model_validator(mode="after")
    def _levels(self) -> CameraConfig:
        if self.white_level_dn <= self.black_level_dn:
            raise ValueError(
                f"white_level_dn ({self.white_level_dn}) must be above black_level_dn "
                f"({self.black_level_dn})"
            )
        if self.white_level_dn > 2**self.bit_depth - 1:
            raise ValueError(
                f"white_level_dn ({self.white_level_dn}) exceeds 2^bit_depth − 1 "
                f"({2**self.bit_depth - 1})"
            )
        if self.exposure_min_s >= self.exposure_max_s:
            raise ValueError("exposure_min_s must be below exposure_max_s")
        return self

    @property
    def nominal_fx_px(self) -> float | None:
        """f/p from the datasheet (None without a focal length)."""
        if self.focal_length_m is None:
            return None
        return self.focal_length_m / self.pixel_pitch_m


class SampleConfig(Strict):
    """The sample as mounted. gonio assumes the holder brings the sample's top surface to the
    arms' common centre (the origin, docs/design.md §3); `thickness_m` and `holder` are recorded."""

    size_m: float = Field(gt=0, le=1, description="side of the square flat sample")
    thickness_m: float = Field(0.0, ge=0, le=0.1)
    orientation_mark: str = Field(
        "+x", description="how φ = 0 (+x) is marked on the sample, e.g. 'notch on the +x edge'"
    )
    holder: str = Field("", description="holder description, for the record")
    bow_sigma_m: float | None = Field(
        None,
        ge=0,
        le=0.005,
        description="standard uncertainty (k = 1, metres) of the sample's bow: the sagitta of a "
        "dome (or dish) over the sample's half side. A sheet (paper, foil, film) curls by "
        "0.1–1 mm over 50 mm, a painted card ~0.1 mm, a lapped tile ~10 µm; the fit carries it "
        "as a nuisance (fitting.nuisance: the local normal leans by the dome's slope)",
    )


class ReferenceConfig(Strict):
    """The reference target for reference-target radiometry (calibration.reference): a
    Lambertian standard of certified albedo, or a certified f_ref(θ_i, θ_o[, Δφ]) table."""

    type: Literal["lambertian", "table"] = "lambertian"
    albedo: tuple[float, float, float] | None = Field(
        None, description="certified directional-hemispherical reflectance per channel (R, G, B)"
    )
    albedo_sigma: float = Field(
        0.0, ge=0, lt=0.5, description="relative 1-σ of the certificate (e.g. 0.005 = 0.5 %)"
    )
    table: str | None = Field(None, description="f_ref table file (CSV/TOML), relative path")
    table_sigma: float = Field(0.0, ge=0, lt=0.5, description="relative 1-σ of the table")
    size_m: float = Field(gt=0, le=1, description="side of the square target")

    @model_validator(mode="after")
    def _kind(self) -> ReferenceConfig:
        if self.type == "lambertian":
            if self.albedo is None:
                raise ValueError("a lambertian reference needs albedo = [R, G, B]")
            if not all(0 < a <= 1 for a in self.albedo):
                raise ValueError(f"albedo must be in (0, 1] (got {list(self.albedo)})")
        elif self.table is None:
            raise ValueError('a "table" reference needs table = "FILE"')
        return self

    @property
    def rel_sigma(self) -> float:
        return self.albedo_sigma if self.type == "lambertian" else self.table_sigma


class RigCalibrationConfig(Strict):
    """Geometric calibration files that `gonio calibrate` uses (relative to the rig file)."""

    intrinsics: str | None = Field(
        None,
        description="JSON written by `gonio calibrate-camera --json` (overrides the "
        "nominal focal length)",
    )
    arm_offsets: str | None = Field(
        None, description="JSON written by `gonio calibrate-rig` (arm zero offsets, tilt)"
    )
    flat_source_falloff_sigma: float | None = Field(
        None,
        ge=0,
        le=0.15,
        description="standard uncertainty (k = 1) of the flat-field source's radiance fall-off "
        "from the optical axis to the frame's corner, from its uniformity spec (an "
        "integrating sphere's port ≤ 1 %, LED panels 2–5 %): the flat carries the source's "
        "profile into every frame, so the fit carries it as a nuisance",
    )


class GeometryConfig(Strict):
    """`two-arm`: light and camera each on a spherical arm (elevation + azimuth axes).
    `inplane`: the light arm swings in one vertical plane on its side of the normal, the camera
    arm in the same plane with a signed angle (positive = across the normal from the light,
    the specular side), and an optional turntable (`sample_azimuth`) turns the sample."""

    preset: Literal["two-arm", "inplane"] = "two-arm"
    light_distance_m: float = Field(0.5, gt=0, le=10)
    light_distance_sigma_m: float | None = Field(
        None,
        ge=0,
        lt=1,
        description="standard uncertainty (k = 1) of light_distance_m: how well the lamp's "
        "distance was measured (a tape to a filament: ~2–5 mm). With the lamp's certified "
        "scale it is a shared scale error 2σ/r in the samples' budget",
    )
    camera_distance_m: float = Field(0.5, gt=0, le=10)
    camera_distance_sigma_m: float | None = Field(
        None,
        ge=0,
        lt=1,
        description="standard uncertainty (k = 1) of camera_distance_m, to the lens' entrance "
        "pupil (inside the lens: known to ~5–10 mm without a pupil measurement). Each pixel's "
        "ray then meets the sample slightly elsewhere; the fit carries it as a nuisance",
    )
    axis_zero_sigma_deg: (
        dict[
            Literal["light_theta", "light_phi", "camera_theta", "camera_phi"],
            Annotated[float, Field(ge=0, le=5)],
        ]
        | None
    ) = Field(
        None,
        description="standard uncertainty (k = 1, degrees) of each arm axis' zero where no "
        "`gonio calibrate-rig` measured it (mounting: a few 0.1°). The fit carries these "
        "shared angle errors as nuisance parameters; an arm-offsets file's own σ replaces them",
    )
    sample_tilt_sigma_deg: float | None = Field(
        None,
        ge=0,
        le=5,
        description="standard uncertainty (k = 1, degrees) of the sample's tilt on its holder "
        "about x and about y, where no `gonio calibrate-rig` measured it (tape or a burr "
        "under an edge: ~0.1–0.3°); carried by the fit like the axes' zeros",
    )
    backlash_deg: float | None = Field(
        None,
        ge=0,
        le=5,
        description="the gears' play b of every arm axis (datasheet: Dynamixel X-series "
        "~0.25–0.35°): an arm lags its last move by b/2. The fit carries one play per axis "
        "with this value ± 50 % as its prior, the side of each pose from the run's moves",
    )
    arm_sag_deg: float | None = Field(
        None,
        ge=0,
        le=5,
        description="how far an elevation arm may sag under its load when horizontal (k = 1, "
        "degrees; a 0.5 m arm on an XM430: ~0.1–0.3°): true θ = θ + c·sin θ. The fit carries "
        "c per elevation arm with this σ",
    )
    camera_roll_deg: float = Field(
        0.0,
        ge=-180,
        le=180,
        description="how the camera sits on its arm: the turn of the sensor about its optical "
        "axis, degrees, from the rig's zero mount (at the arms' zero the camera looks down the "
        "normal with the image's top toward −x, its right toward +y). The camera's orientation "
        "at every pose follows from it and the axes (acquisition.kinematics); `gonio "
        "calibrate-rig` measures the rest of it",
    )
    min_separation_deg: float = Field(5.0, ge=0, le=90, description="light–camera occlusion")
    max_theta_deg: float = Field(85.0, gt=0, le=90)


class RigConfig(Strict):
    """What the lab knows about its instrument: devices, axes, geometry, the sample, the camera,
    the reference target and the calibration files. Calibration reads only this (frozen into
    the run) and what the run recorded; a simulator's scene is the emulated world, never read
    by calibration."""

    name: str = "rig"
    clock: str = Field("system", description='"system" for a real rig, "sim" for the emulator')
    scene: str | None = Field(None, description="scene TOML (simulated rigs only), relative path")
    settle_s: float = Field(0.2, ge=0, le=60, description="wait after arrival before capture")
    move_timeout_s: float = Field(60.0, gt=0, le=3600)
    bus: BusConfig
    axes: tuple[AxisConfig, ...]
    light: LightConfig
    camera: CameraConfig
    sample: SampleConfig
    geometry: GeometryConfig = Field(default_factory=GeometryConfig)
    reference: ReferenceConfig | None = None
    calibration: RigCalibrationConfig = Field(default_factory=RigCalibrationConfig)

    @model_validator(mode="after")
    def _unique(self) -> RigConfig:
        ids = [a.id for a in self.axes]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicate servo id {dup[0]} in [[axes]] (each id must be unique)")
        roles = [a.role for a in self.axes]
        duprole = sorted({r for r in roles if roles.count(r) > 1})
        if duprole:
            raise ValueError(f"duplicate axis role {duprole[0]!r} in [[axes]]")
        need = {"light_theta", "light_phi", "camera_theta", "camera_phi"}
        if self.geometry.preset == "inplane":
            need = {"light_theta", "camera_theta"}
            extra = set(roles) - need - {"sample_azimuth"}
            if extra:
                raise ValueError(
                    f"the inplane preset has no {sorted(extra)[0]!r} axis (roles: light_theta, "
                    "camera_theta, optional sample_azimuth)"
                )
        if not need <= set(roles):
            raise ValueError(
                f"the {self.geometry.preset} preset needs axes with roles {sorted(need)}"
            )
        if self.camera.focal_length_m is None and self.calibration.intrinsics is None:
            raise ValueError(
                "camera.focal_length_m is missing: give the lens focal length, or "
                "[calibration] intrinsics = FILE (from `gonio calibrate-camera --json`)"
            )
        return self

    def axis(self, role: str) -> AxisConfig:
        for a in self.axes:
            if a.role == role:
                return a
        raise KeyError(role)


# Reference poses (θ_i, φ_i, θ_o, φ_o in deg): the 0°/45° geometry of reflectance-standard
# certificates, and two more geometries so a pose-dependent error (f_ref, geometry) shows up as
# scatter between poses (the Birge ratio of calibration.reference.combine_scales).
REFERENCE_POSES_DEG = (
    (0.0, 0.0, 45.0, 180.0),
    (30.0, 0.0, 30.0, 90.0),
    (45.0, 0.0, 10.0, 270.0),
)


class DarkPhaseConfig(Strict):
    """Dark frames (lens capped): `count` per exposure; by default every exposure the plan may
    take (its brackets, or its auto-exposure ladder), so every frame has its master dark."""

    count: int = Field(16, ge=2, le=1000, description="frames per exposure")
    exposures_s: tuple[float, ...] | None = None


class FlatPhaseConfig(Strict):
    """Flat field (the camera facing a uniform source: integrating sphere port or diffuser)."""

    count: int = Field(32, ge=2, le=1000)
    exposure_s: float | None = Field(
        None, gt=0, le=60, description="default: the plan's longest exposure"
    )


class ReferencePhaseConfig(Strict):
    """Reference-target captures (the target in the sample's place, the rig's [reference])."""

    poses_deg: tuple[tuple[float, float, float, float], ...] = REFERENCE_POSES_DEG
    exposures_s: tuple[float, ...] | None = Field(
        None, description="default: the plan's shortest, middle and longest exposures"
    )


class CalibrationPhasesConfig(Strict):
    """Calibration captures a plan asks for; `gonio acquire` records them into
    RUN/calibration/ before the first measurement pose, in this order: darks, flat, reference.
    Each step that needs hands (cap the lens, mount the flat source, swap in the target) asks
    the operator first."""

    dark: DarkPhaseConfig | None = None
    flat: FlatPhaseConfig | None = None
    reference: ReferencePhaseConfig | None = None

    @property
    def empty(self) -> bool:
        return self.dark is None and self.flat is None and self.reference is None


class AutoExposureConfig(Strict):
    """Auto-exposure per pose (`exposure_mode = "auto"`): bracket until the sample region has an
    unsaturated frame and enough signal (decision logic: `acquisition.exposure`).

    Levels are linear fractions of the camera's clip level (0 = black, 1 = clipped). Exposures
    are taken on the ladder start_s·ratio^k within [min_s, max_s], so a finite set of master
    darks covers every frame and repeated decisions are exactly reproducible.
    """

    start_s: float = Field(0.002, gt=0, le=60, description="first exposure of every pose")
    min_s: float = Field(1e-4, gt=0, le=60, description="shortest exposure allowed")
    max_s: float = Field(1.0, gt=0, le=60, description="longest exposure allowed")
    ratio: float = Field(4.0, gt=1.0, le=64.0, description="ladder step between exposures")
    target_signal: float = Field(
        0.25, gt=0, lt=1, description="wanted level of the signal percentile (fraction of clip)"
    )
    signal_percentile: float = Field(
        50.0, ge=0, le=100, description="which sample-region pixel must reach target_signal"
    )
    saturation_level: float = Field(
        0.9, gt=0, le=1, description="a pixel at or above this level counts as saturated"
    )
    max_brackets: int = Field(4, ge=1, le=16, description="frames per pose at most")

    @model_validator(mode="after")
    def _order(self) -> AutoExposureConfig:
        if not self.min_s <= self.start_s <= self.max_s:
            raise ValueError(
                f"need min_s ({self.min_s}) <= start_s ({self.start_s}) <= max_s ({self.max_s})"
            )
        if self.target_signal >= self.saturation_level:
            raise ValueError(
                f"target_signal ({self.target_signal}) must be below saturation_level "
                f"({self.saturation_level})"
            )
        return self


class PlanConfig(Strict):
    """A sampling plan (angles in degrees; φ from +x toward +y).

    - `isotropic`: every (θ_i, θ_o, Δφ) with φ_i = 0 and φ_o = Δφ (Δφ = 180° is the plane of
      incidence, specular side).
    - `inplane`: θ_i × θ_o in the plane of incidence, on the specular side (φ_o = 180°) and,
      with `both_sides`, the retro side (φ_o = 0°); θ_o = 0 is measured once.
    - `hemisphere`: every (θ_i, φ_i, θ_o, φ_o) of the four lists; a θ list may be replaced by
      `theta_step_deg` (0, step, ... ≤ `theta_max_deg`) and a φ list by `phi_step_deg`
      (0, step, ... < 360). At θ = 0 the azimuth is meaningless, so those poses appear once.
    - `rusinkiewicz`: every (θ_h, θ_d, φ_d) with φ_h = 0 (isotropic BRDF), converted to
      (ω_i, ω_o) by brdfdata.rusinkiewicz.from_half_diff; poses below the horizon or beyond the
      rig's reach are skipped with their reason.
    - `explicit`: the (θ_i, φ_i, θ_o, φ_o) list `poses_deg`.
    - `adaptive`: two phases in one run — the coarse plan `prescan` (any other type), then
      fine poses around each incidence's peak (`refine_span_deg`, `refine_step_deg`, see
      `acquisition.plans.refine_around_peak`), decided from the pre-scan frames.
    - `anisotropic`: in-plane scans θ_i × θ_o with the sample turned to every orientation ψ of
      `orientations_deg` (≥ 4 distinct mod 180°, what a lobe (α_x, α_y, φ₀) needs), on the
      specular side and, with `both_sides`, the retro side (`acquisition.plans.anisotropic_poses`).
    - `retro`: for every θ_i, the camera on rings around the light's direction at the rig's
      `min_separation_deg` plus each of `retro_offsets_deg`, as close to retro-reflection as the
      rig allows; the gap left is reported (`acquisition.plans.retro_poses`).

    Exposure: `exposure_mode = "fixed"` takes every bracket of `exposures_s` at every pose;
    `"auto"` brackets per pose as `auto_exposure` says (then `exposures_s` is unused).
    An adaptive plan's exposure settings apply to both phases (the prescan's are ignored).
    """

    name: str = "plan"
    type: Literal[
        "isotropic",
        "explicit",
        "hemisphere",
        "inplane",
        "rusinkiewicz",
        "adaptive",
        "anisotropic",
        "retro",
    ] = "isotropic"
    theta_i_deg: tuple[float, ...] = ()
    theta_o_deg: tuple[float, ...] = ()
    delta_phi_deg: tuple[float, ...] = (180.0,)
    phi_i_deg: tuple[float, ...] = ()
    phi_o_deg: tuple[float, ...] = ()
    theta_step_deg: float | None = Field(None, gt=0, le=90)
    theta_max_deg: float = Field(80.0, gt=0, lt=90)
    phi_step_deg: float | None = Field(None, gt=0, le=360)
    both_sides: bool = Field(
        True, description="inplane, anisotropic: also the retro side (φ_o = φ_i)"
    )
    orientations_deg: tuple[float, ...] = Field(
        (), description="anisotropic: sample orientations ψ (azimuth of the plane of incidence)"
    )
    retro_offsets_deg: tuple[float, ...] = Field(
        (0.0, 1.0, 2.0, 4.0, 8.0, 15.0, 25.0),
        description="retro: ring radii beyond the rig's min_separation_deg",
    )
    theta_h_deg: tuple[float, ...] = ()
    theta_d_deg: tuple[float, ...] = ()
    phi_d_deg: tuple[float, ...] = ()
    poses_deg: tuple[tuple[float, float, float, float], ...] = Field(
        (), description="explicit (θ_i, φ_i, θ_o, φ_o) list"
    )
    exposures_s: tuple[float, ...] = Field((0.002,), min_length=1)
    order: Literal["raster", "nearest"] = "nearest"
    skip_unreachable: bool = Field(
        True, description="drop grid poses the rig cannot reach (explicit poses always error)"
    )
    exposure_mode: Literal["fixed", "auto"] = "fixed"
    auto_exposure: AutoExposureConfig = Field(default_factory=AutoExposureConfig)
    prescan: PlanConfig | None = Field(None, description="adaptive: the coarse phase-1 plan")
    refine_span_deg: float = Field(10.0, gt=0, le=45, description="adaptive: patch half-width")
    refine_step_deg: float = Field(2.5, gt=0, le=45, description="adaptive: fine spacing")
    calibration: CalibrationPhasesConfig = Field(default_factory=CalibrationPhasesConfig)

    @field_validator("theta_i_deg", "theta_o_deg", "theta_h_deg", "theta_d_deg")
    @classmethod
    def _theta(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for t in v:
            if not 0.0 <= t < 90.0:
                raise ValueError(f"angle {t} out of range [0, 90) deg")
        return v

    @field_validator("delta_phi_deg", "phi_i_deg", "phi_o_deg", "phi_d_deg")
    @classmethod
    def _phi(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for p in v:
            if not 0.0 <= p <= 360.0:
                raise ValueError(f"angle {p} out of range [0, 360] deg")
        return v

    @field_validator("exposures_s")
    @classmethod
    def _exp(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for t in v:
            if not (0 < t <= 60 and math.isfinite(t)):
                raise ValueError(f"exposure {t} s out of range (0, 60] s")
        return v

    @model_validator(mode="after")
    def _content(self) -> PlanConfig:
        if self.type in ("isotropic", "inplane", "anisotropic") and not (
            self.theta_i_deg and self.theta_o_deg
        ):
            raise ValueError(f"an {self.type} plan needs theta_i_deg and theta_o_deg lists")
        if self.type == "hemisphere":
            for key in ("theta_i_deg", "theta_o_deg"):
                if not getattr(self, key) and self.theta_step_deg is None:
                    raise ValueError(f"a hemisphere plan needs {key} or theta_step_deg")
            for key in ("phi_i_deg", "phi_o_deg"):
                if not getattr(self, key) and self.phi_step_deg is None:
                    raise ValueError(f"a hemisphere plan needs {key} or phi_step_deg")
        if self.type == "rusinkiewicz" and not (
            self.theta_h_deg and self.theta_d_deg and self.phi_d_deg
        ):
            raise ValueError("a rusinkiewicz plan needs theta_h_deg, theta_d_deg and phi_d_deg")
        if self.type == "adaptive":
            if self.prescan is None:
                raise ValueError("an adaptive plan needs a [prescan] plan")
            if self.prescan.type == "adaptive":
                raise ValueError("an adaptive plan's prescan cannot itself be adaptive")
            if self.refine_step_deg > self.refine_span_deg:
                raise ValueError(
                    f"refine_step_deg ({self.refine_step_deg}) must not exceed "
                    f"refine_span_deg ({self.refine_span_deg})"
                )
        if self.type == "anisotropic":
            distinct = {round(o % 180.0, 9) for o in self.orientations_deg}
            if len(distinct) < 4:  # acquisition.plans.MIN_ORIENTATIONS (α_x, α_y, φ₀ + a check)
                raise ValueError(
                    "an anisotropic plan needs orientations_deg with ≥ 4 sample orientations "
                    f"distinct mod 180 deg; got {sorted(distinct)}"
                )
        if self.type == "retro":
            if not self.theta_i_deg:
                raise ValueError("a retro plan needs theta_i_deg")
            if not self.retro_offsets_deg or min(self.retro_offsets_deg) < 0:
                raise ValueError("retro_offsets_deg must list offsets ≥ 0 deg")
        if self.type == "explicit" and not self.poses_deg:
            raise ValueError("an explicit plan needs poses_deg")
        for pose in self.poses_deg:
            ti, pi, to, po = pose
            if not (0 <= ti < 90 and 0 <= to < 90):
                raise ValueError(f"pose {list(pose)}: theta out of range [0, 90) deg")
            if not (-360 <= pi <= 360 and -360 <= po <= 360):
                raise ValueError(f"pose {list(pose)}: phi out of range [-360, 360] deg")
        return self


def _resolve(base: Path, value: str | None) -> str | None:
    if value is None:
        return None
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def load_rig(path: Path | str) -> RigConfig:
    """Parse and check a rig file. Paths in it (scene, calibration files, reference table) are
    relative to the rig file, so configs move together; the files they name must exist, and an
    intrinsics file must hold what `gonio calibrate-camera --json` writes — checked here, so a
    mistake is one line before any device is opened."""
    path = Path(path)
    data = load_config_data(path)
    try:
        rig = RigConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, RigConfig)) from None
    base = path.parent
    cal = rig.calibration.model_copy(
        update={
            "intrinsics": _resolve(base, rig.calibration.intrinsics),
            "arm_offsets": _resolve(base, rig.calibration.arm_offsets),
        }
    )
    update: dict = {"scene": _resolve(base, rig.scene), "calibration": cal}
    scpi = rig.light.scpi
    if scpi is not None and scpi.visa_library.endswith("@sim") and len(scpi.visa_library) > 4:
        # a pyvisa-sim definition file travels with the rig file, like the other paths
        sim = _resolve(base, scpi.visa_library[:-4])
        if not Path(sim).is_file():
            raise ConfigError(f"{path}: light.scpi.visa_library: no such file {sim}")
        update["light"] = rig.light.model_copy(
            update={"scpi": scpi.model_copy(update={"visa_library": f"{sim}@sim"})}
        )
    for key, file in (("intrinsics", cal.intrinsics), ("arm_offsets", cal.arm_offsets)):
        if file is not None and not Path(file).is_file():
            raise ConfigError(f"{path}: calibration.{key}: no such file {file}")
    if cal.intrinsics is not None:
        load_intrinsics(cal.intrinsics, rig.camera.resolution, where=f"{path}: ")
    if cal.arm_offsets is not None:
        load_arm_offsets(cal.arm_offsets, where=f"{path}: ")
    if rig.reference is not None and rig.reference.table is not None:
        table = _resolve(base, rig.reference.table)
        if not Path(table).is_file():
            raise ConfigError(f"{path}: reference.table: no such file {table}")
        update["reference"] = rig.reference.model_copy(update={"table": table})
    return rig.model_copy(update=update)


def _read_json(file: str | Path, where: str, what: str) -> dict:
    try:
        text = read_input_text(file, f"{what} JSON file", 16 * MiB)
        check_nesting(text, file, f"{what} JSON file")
        doc = json.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{where}{file}: not a readable {what} JSON file ({exc})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{where}{file}: not a {what} JSON object")
    return doc


def load_intrinsics(
    file: str | Path, resolution: tuple[int, int] | None = None, *, where: str = ""
) -> dict:
    """fx, fy, cx, cy (px) and dist (OpenCV k1, k2, p1, p2, k3) from the JSON that
    `gonio calibrate-camera --json` writes; checked to be finite, positive focal lengths and a
    principal point inside the image."""
    doc = _read_json(file, where, "camera intrinsics")
    try:
        out = {k: float(doc[k]) for k in ("fx", "fy", "cx", "cy")}
        dist = [float(v) for v in doc.get("dist", [])]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(
            f"{where}{file}: intrinsics need fx, fy, cx, cy (px) and dist, as written by "
            f"`gonio calibrate-camera --json` (bad or missing {exc})"
        ) from None
    vals = [*out.values(), *dist]
    if not all(math.isfinite(v) for v in vals) or out["fx"] <= 0 or out["fy"] <= 0:
        raise ConfigError(f"{where}{file}: intrinsics must be finite with fx, fy > 0")
    if resolution is not None:
        w, h = resolution
        if not (0 <= out["cx"] < w and 0 <= out["cy"] < h):
            raise ConfigError(
                f"{where}{file}: principal point ({out['cx']:g}, {out['cy']:g}) px lies outside "
                f"the {w}×{h} image of camera.resolution; was it calibrated on this camera?"
            )
    out["dist"] = (dist + [0.0] * 5)[:5] if dist else [0.0] * 5
    return out


ARM_OFFSETS_SCHEMA = "gonio.arm-offsets/1"


def load_arm_offsets(file: str | Path, *, where: str = "") -> dict:
    """Arm zero offsets and sample-plane tilt (degrees) from `gonio calibrate-rig --out FILE`:
    {"schema": "gonio.arm-offsets/1", "offsets_deg": {ROLE: δ}, "tilt_deg": {"x": τx,
    "y": τy}, "camera_roll_deg": δρ, "sigma_deg": {...}, ...}. True axis angle = measured + δ;
    the camera's roll = the rig file's camera_roll_deg + δρ (0 in files written before it)."""
    doc = _read_json(file, where, "arm offsets")
    if doc.get("schema") != ARM_OFFSETS_SCHEMA:
        raise ConfigError(
            f"{where}{file}: not an arm-offsets file (schema {doc.get('schema')!r}, expected "
            f"{ARM_OFFSETS_SCHEMA!r}; write it with `gonio calibrate-rig`)"
        )
    try:
        offsets = {str(k): float(v) for k, v in doc["offsets_deg"].items()}
        tilt = {k: float(doc["tilt_deg"][k]) for k in ("x", "y")}
        roll = float(doc.get("camera_roll_deg", 0.0))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"{where}{file}: offsets_deg / tilt_deg missing or bad ({exc})") from None
    vals = [*offsets.values(), *tilt.values(), roll]
    if not all(math.isfinite(v) and abs(v) < 30 for v in vals):
        raise ConfigError(
            f"{where}{file}: offsets, tilt and camera roll must be finite and below 30 deg"
        )
    bad = set(offsets) - {
        "light_theta",
        "light_phi",
        "camera_theta",
        "camera_phi",
        "sample_azimuth",
    }
    if bad:
        raise ConfigError(f"{where}{file}: unknown axis role {sorted(bad)[0]!r} in offsets_deg")
    return {**doc, "offsets_deg": offsets, "tilt_deg": tilt, "camera_roll_deg": roll}


def load_plan(path: Path | str) -> PlanConfig:
    data = load_config_data(path)
    try:
        return PlanConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, PlanConfig)) from None
