"""Rig and plan configs (TOML → pydantic, extra="forbid").

Every mistake a user can type becomes a `ConfigError` with one line naming the file, the key and
the allowed range, so the CLI can print it without a traceback.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

__all__ = [
    "ConfigError",
    "AxisConfig",
    "BusConfig",
    "LightConfig",
    "CameraConfig",
    "GeometryConfig",
    "RigConfig",
    "PlanConfig",
    "AutoExposureConfig",
    "load_rig",
    "load_plan",
    "format_validation_error",
    "load_config_data",
    "CONFIG_SUFFIXES",
]

VELOCITY_LIMIT = {"XM430-W350": 200, "XL430-W250": 265}
AxisRole = Literal["light_theta", "light_phi", "camera_theta", "camera_phi", "sample_azimuth"]


class ConfigError(ValueError):
    """A config file is wrong. The message is one line: file, key, what is allowed."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AxisConfig(_Strict):
    role: AxisRole
    id: int = Field(ge=0, le=252, description="Dynamixel ID")
    model: Literal["XM430-W350", "XL430-W250"] = "XM430-W350"
    gear_ratio: float = Field(1.0, gt=0, description="servo turns per axis turn")
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


class BusConfig(_Strict):
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


class LightConfig(_Strict):
    url: str = Field(description="serial device, or lightsim://NAME for the emulator")
    level: float = Field(1.0, gt=0, le=1, description="relative intensity used for the run")
    intensity_W_sr: tuple[float, float, float] | None = Field(
        None,
        description="radiant intensity per channel (R, G, B) at level 1, W/sr, from the "
        "source's calibration certificate; without it results are relative",
    )
    warmup_s: float = Field(0.0, ge=0, le=3600)


class CameraConfig(_Strict):
    backend: str = Field("sim", description='"sim", "folder" or "gphoto2"')
    folder: str | None = Field(None, description='"folder": where the tethering tool writes')
    trigger_command: tuple[str, ...] | None = Field(
        None, description='"folder": argv run per frame; "{exposure_s}" is replaced'
    )
    timeout_s: float = Field(30.0, gt=0, le=3600, description="wait for a frame, wall time")
    readout_s: float = Field(0.05, ge=0, description="lab time per frame beyond the exposure")


class GeometryConfig(_Strict):
    """`two-arm`: light and camera each on a spherical arm (elevation + azimuth axes).
    `inplane`: the light arm swings in one vertical plane on its side of the normal, the camera
    arm in the same plane with a signed angle (positive = across the normal from the light,
    the specular side), and an optional turntable (`sample_azimuth`) turns the sample."""

    preset: Literal["two-arm", "inplane"] = "two-arm"
    light_distance_m: float = Field(0.5, gt=0, le=10)
    camera_distance_m: float = Field(0.5, gt=0, le=10)
    min_separation_deg: float = Field(5.0, ge=0, le=90, description="light–camera occlusion")
    max_theta_deg: float = Field(85.0, gt=0, le=90)


class RigConfig(_Strict):
    name: str = "rig"
    clock: str = Field("system", description='"system" for a real rig, "sim" for the emulator')
    scene: str | None = Field(None, description="scene TOML (simulated rigs only), relative path")
    settle_s: float = Field(0.2, ge=0, le=60, description="wait after arrival before capture")
    move_timeout_s: float = Field(60.0, gt=0, le=3600)
    bus: BusConfig
    axes: tuple[AxisConfig, ...]
    light: LightConfig
    camera: CameraConfig = Field(default_factory=CameraConfig)
    geometry: GeometryConfig = Field(default_factory=GeometryConfig)

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
        return self

    def axis(self, role: str) -> AxisConfig:
        for a in self.axes:
            if a.role == role:
                return a
        raise KeyError(role)


class AutoExposureConfig(_Strict):
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


class PlanConfig(_Strict):
    """A sampling plan (angles in degrees; φ from +x toward +y).

    - `isotropic`: every (θ_i, θ_o, Δφ) with φ_i = 0 and φ_o = Δφ (Δφ = 180° is the plane of
      incidence, specular side).
    - `inplane`: θ_i × θ_o in the plane of incidence, on the specular side (φ_o = 180°) and,
      with `both_sides`, the retro side (φ_o = 0°); θ_o = 0 is measured once.
    - `hemisphere`: every (θ_i, φ_i, θ_o, φ_o) of the four lists; a θ list may be replaced by
      `theta_step_deg` (0, step, ... ≤ `theta_max_deg`) and a φ list by `phi_step_deg`
      (0, step, ... < 360). At θ = 0 the azimuth is meaningless, so those poses appear once.
    - `rusinkiewicz`: every (θ_h, θ_d, φ_d) with φ_h = 0 (isotropic BRDF), converted to
      (ω_i, ω_o) by fitting.rusinkiewicz.from_half_diff; poses below the horizon or beyond the
      rig's reach are skipped with their reason.
    - `explicit`: the (θ_i, φ_i, θ_o, φ_o) list `poses_deg`.
    - `adaptive`: two phases in one run — the coarse plan `prescan` (any other type), then
      fine poses around each incidence's peak (`refine_span_deg`, `refine_step_deg`, see
      `acquisition.plans.refine_around_peak`), decided from the pre-scan frames.

    Exposure: `exposure_mode = "fixed"` takes every bracket of `exposures_s` at every pose;
    `"auto"` brackets per pose as `auto_exposure` says (then `exposures_s` is unused).
    An adaptive plan's exposure settings apply to both phases (the prescan's are ignored).
    """

    name: str = "plan"
    type: Literal["isotropic", "explicit", "hemisphere", "inplane", "rusinkiewicz", "adaptive"] = (
        "isotropic"
    )
    theta_i_deg: tuple[float, ...] = ()
    theta_o_deg: tuple[float, ...] = ()
    delta_phi_deg: tuple[float, ...] = (180.0,)
    phi_i_deg: tuple[float, ...] = ()
    phi_o_deg: tuple[float, ...] = ()
    theta_step_deg: float | None = Field(None, gt=0, le=90)
    theta_max_deg: float = Field(80.0, gt=0, lt=90)
    phi_step_deg: float | None = Field(None, gt=0, le=360)
    both_sides: bool = Field(True, description="inplane: also the retro side (φ_o = φ_i)")
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
        if self.type in ("isotropic", "inplane") and not (self.theta_i_deg and self.theta_o_deg):
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
        if self.type == "explicit" and not self.poses_deg:
            raise ValueError("an explicit plan needs poses_deg")
        for pose in self.poses_deg:
            ti, pi, to, po = pose
            if not (0 <= ti < 90 and 0 <= to < 90):
                raise ValueError(f"pose {list(pose)}: theta out of range [0, 90) deg")
            if not (-360 <= pi <= 360 and -360 <= po <= 360):
                raise ValueError(f"pose {list(pose)}: phi out of range [-360, 360] deg")
        return self


# Units live in key names (`distance_m`, `exposure_s`, `min_deg`), never in values: a value
# is a plain number in the key's unit. These suffixes name the unit, longest first.
_UNIT_SUFFIXES = (
    ("_W_sr", "W/sr"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_mm", "mm"),
    ("_cm", "cm"),
    ("_um", "µm"),
    ("_ms", "ms"),
    ("_us", "µs"),
    ("_m", "m"),
    ("_s", "s"),
)
_SI_SUFFIX = {"_rad": "_deg", "_mm": "_m", "_cm": "_m", "_um": "_m", "_ms": "_s", "_us": "_s"}
_NUMBER_WITH_UNIT = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*([^\d\s].*?)\s*$")
_RANGE_TYPES = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")


def _unit_of(key: str) -> tuple[str, str] | None:
    """(suffix, unit name) of a unit-carrying key, e.g. "min_deg" → ("_deg", "deg")."""
    for suffix, unit in _UNIT_SUFFIXES:
        if key.endswith(suffix) and len(key) > len(suffix):
            return suffix, unit
    return None


def _fields_at(model: type[BaseModel] | None, loc: tuple) -> set[str] | None:
    """Field names of the (nested) model that holds the last key of `loc`, if known."""
    for part in loc[:-1]:
        if model is None:
            return None
        if isinstance(part, int):
            continue
        info = model.model_fields.get(str(part))
        model = _submodel(info.annotation) if info is not None else None
    return set(model.model_fields) if model is not None else None


def _submodel(annotation: object) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = _submodel(arg)
        if found is not None:
            return found
    return None


def _unit_hint(e: dict, loc: tuple, model: type[BaseModel] | None) -> str | None:
    """A one-line explanation when the mistake is about units, else None."""
    keys = [p for p in loc if isinstance(p, str)]
    if not keys:
        return None
    key = keys[-1]
    unit = _unit_of(key)
    got = e.get("input")
    if e["type"] == "extra_forbidden" and unit is not None and unit[0] in _SI_SUFFIX:
        want = key[: -len(unit[0])] + _SI_SUFFIX[unit[0]]
        fields = _fields_at(model, loc)
        if fields is None or want in fields:
            return (
                f"unknown key; gonio configs use SI units and degrees: write {want} "
                f"(in {dict(_UNIT_SUFFIXES)[_SI_SUFFIX[unit[0]]]}) instead of {key}"
            )
    if unit is not None and e["type"] in ("tuple_type", "list_type"):
        return f"{key} is a list of numbers in {unit[1]}, e.g. [30.0] (got {got!r})"
    if unit is not None and isinstance(got, str):
        m = _NUMBER_WITH_UNIT.match(got)
        if m:
            return (
                f"{key} is in {unit[1]} (the unit is in the key name); write a plain number "
                f"in {unit[1]}, without a unit string (got {got!r})"
            )
        return f"{key} is a number in {unit[1]}; write it without quotes (got {got!r})"
    if unit is not None and e["type"] in _RANGE_TYPES:
        return f"{e['msg']}; {key} is in {unit[1]} (got {got!r})"
    return None


def format_validation_error(
    path: Path | str, err: ValidationError, model: type[BaseModel] | None = None
) -> str:
    """First pydantic error as one line: `file: key.path: message (got value)`.

    `model` (the validated class) lets an unknown key like `distance_mm` be answered with the
    real key (`distance_m`) when it exists.
    """
    e = err.errors()[0]
    loc = tuple(e["loc"])
    where = ".".join(str(p) for p in loc)
    msg = e["msg"].removeprefix("Value error, ").removeprefix("Assertion failed, ")
    hint = _unit_hint(e, loc, model)
    if hint is not None:
        return f"{path}: {where}: {hint}"
    if e["type"] == "extra_forbidden":
        msg = "unknown key (check the spelling; see the commented example configs in configs/)"
    elif e["type"] == "missing":
        msg = "required key is missing"
    got = e.get("input")
    tail = (
        f" (got {got!r})"
        if e["type"] not in ("missing", "extra_forbidden") and loc and _short(got)
        else ""
    )
    if not loc:  # a whole-file check (duplicate ids, missing roles): its message names the key
        return f"{path}: {msg}{tail}"
    return f"{path}: {where}: {msg}{tail}"


def _short(v: object) -> bool:
    return not isinstance(v, dict | list | tuple) or len(repr(v)) < 60


CONFIG_SUFFIXES = (".toml", ".json")


def load_config_data(path: Path | str) -> dict:
    """Parse a config file. Configs are data: TOML (or JSON), never code, so other formats
    (YAML can construct objects, Python would run) are refused by suffix."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such file")
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory; give a .toml config file")
    if path.suffix.lower() not in CONFIG_SUFFIXES:
        raise ConfigError(
            f"{path}: configs must be TOML (.toml) or JSON (.json) files, not "
            f"{path.suffix or 'files without a suffix'!r}; convert it to TOML"
        )
    try:
        with open(path, "rb") as fh:
            if path.suffix.lower() == ".json":
                data = json.load(fh)
                if not isinstance(data, dict):
                    raise ConfigError(f"{path}: a JSON config must be an object {{...}}")
                return data
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None


def load_rig(path: Path | str) -> RigConfig:
    data = load_config_data(path)
    try:
        rig = RigConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, RigConfig)) from None
    if rig.scene is not None:
        # Scene paths are relative to the rig file, so configs can be moved together.
        scene = Path(rig.scene)
        if not scene.is_absolute():
            scene = (Path(path).parent / scene).resolve()
        rig = rig.model_copy(update={"scene": str(scene)})
    return rig


def load_plan(path: Path | str) -> PlanConfig:
    data = load_config_data(path)
    try:
        return PlanConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(path, err, PlanConfig)) from None
