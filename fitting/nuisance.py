"""The samples' shared errors as nuisance parameters of the fit (issue 17 item 3).

A shared error is one error for every sample it touches: the radiometric scale of a channel
(the lamp's certificate, its distance) multiplies every f of the run; an arm's encoder zero
shifts every angle that arm sets. Added to each sample's σ in quadrature it would average
away as 1/√N. Here each is a parameter of the posterior with the budget's prior, and the MCMC
marginalises it:

* ``scale_<CH>``: f_measured = s_CH · f_model, ln s_CH ~ N(0, σ_CH) — σ_CH the quadrature sum
  of the budget's ``scale…`` components of that channel (fitting.budget.scale_sigma). Sampled
  as ln s, so with amplitudes sampled as logarithms the ridge ln kd + ln s = const is straight
  (the differential-evolution moves follow straight ridges). Channels get independent scales:
  the marginal interval of each parameter is the same whether the channels' scale errors are
  correlated or not (a parameter sees its own channel's scale only; shared shape parameters
  see none, the model being homogeneous in its amplitudes).
* ``light_theta_zero``, ``camera_theta_zero`` (degrees): the true elevation of an arm is the
  recorded one plus δ ~ N(0, σ), so every direction that arm sets turns by δ about the
  horizontal axis normal to the arm's vertical plane (the arm's azimuth per capture comes
  from the samples' metadata ``gonio.arm_azimuths``, written by calibration; a table without
  it uses each sample's own azimuth, which is wrong near the normal, where pixels' azimuths
  scatter). On an ``inplane`` rig the camera's signed elevation is positive on the specular
  side (acquisition.kinematics): there θ_o grows with δ, on the light's side it shrinks.
* ``camera_phi_zero`` (degrees, two-arm rigs): the relative azimuth φ_o − φ_i moves by
  δ_camera_phi − δ_light_phi (an isotropic BRDF sees only the difference), σ their
  quadrature sum.
* ``sample_tilt_x``, ``sample_tilt_y`` (degrees): the sample's plane tilted on its holder by
  R_τ = R_y(τ_y) R_x(τ_x) (calibrate-rig's convention), every direction seen from the sample
  is R_τᵀ ω.
* ``sample_bow_um`` (µm, with the arms' positions): the sample is a dome h = s (1 − (x² + y²)/R²)
  of sagitta s over its half side R (the budget's "sample flatness (bow)"), so at the point
  (x, y) where a pixel meets it the normal leans by the slope −2 s (x, y)/R²: a tilt
  τ_y = 2 s x/R², τ_x = −2 s y/R² of that row alone (R_τ z ≈ (τ_y, −τ_x, 1)). Shared by every
  sample at the same place, it biases a fit that ignores it far beyond its size: 0.1 mm over
  25 mm (0.46° at the edge) moved the lamp-distance nuisance to −18 mm and m by 5.5 σ.
* ``camera_distance_mm`` (with the arms' positions): the camera's entrance pupil sits further
  along its line of sight than the rig file says, so each pixel's ray, traced from the true
  point, meets the sample elsewhere, where the lamp's direction and distance differ.
* ``flat_falloff_pct`` (%, with a flat field): the flat source's radiance falls as
  1 − a ρ/ρ_corner over the frame (ρ the squared tangent of the field angle), which the master
  flat divides into every frame: the measured f is the model's / (1 − a ρ/ρ_corner) at the
  row's pixel. Not an angle: a factor per row (fitting.likelihood).
* ``ambient_mW`` (mW m⁻² sr⁻¹, with the arms' positions): light the lamp does not cause leaves
  the sample as radiance L_a A (A its directional albedo, slowly varying), which calibration
  divides by the lamp's irradiance: the measured f gains L_a A r² / (I_c cos θ_i) per row (r
  the lamp's distance to the row's point, I_c the channel's intensity). Added, not a factor.
* ``linearity_pct`` (%, with the samples' ``bend_level``): the camera's bend b that calibration
  left in (calibration.linearity: y_m = y (1 + b y / Y)), with the bracket measurement's σ:
  taken out, what remains is centred on 0; not taken out (|β̂| < 3σ), the bend in the samples is
  β̂ ± σ, and the prior is centred on β̂. (Centred on 0 instead, a straight camera's intervals
  held the bend's σ around a bend the samples do not have: over the simulated coverage test's
  60 repeats ks's error/half-width had sd 0.79 and its 68 % interval covered 0.80; centred on
  β̂, sd 0.97 and 0.68, and over 256 repeats 0.69 / 0.93 for ks's 68 % / 95 %, error/half-width
  mean −0.04, sd 1.02 — tests/fitting/test_coverage_sim.py.) The merged
  flux moves by the factor 1 + b · level, level the fraction of the clip at which the merge
  read the sample (calibration.linearity.bend_level), read from the neighbouring regions'
  flux, never the sample's own (calibration.reduce._region_level says why): a factor per row.
  A correction decided by the 3σ test and not carried had moved ks and m by 4–8 of their σ in
  the 3 of 256 ideal-rig runs where noise alone passed the test.
* With the light's direction, the irradiance calibration divided by moves too: the measured f
  is the BRDF at the true directions times cos θ_i(true) / cos θ_i(recorded)
  (fitting.likelihood).

The fit reports each parameter's spread split by the law of total variance over the draws:
Var θ = E[Var(θ | δ)] + Var(E[θ | δ]); the second term (E[θ | δ] by least squares on the
nuisance draws, linear to first order in the small δ) is the systematic part, the rest the
statistical part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from brdfdata.directions import spherical_to_vector
from fitting.budget import scale_sigma

__all__ = [
    "SharedErrors",
    "is_nuisance_name",
    "shared_errors",
    "ANGLE_NUISANCES",
    "is_nuisance",
    "shifted_directions",
    "split_uncertainty",
    "carried_words",
    "with_nuisances",
    "nuisance_effect",
    "SamplerCoordinates",
    "sampler_coordinates",
    "arm_rows",
    "arm_positions_known",
    "measured_geometry",
    "to_si",
    "arm_deltas",
    "ARMS",
    "FACTOR_NUISANCES",
    "surface_point",
]

#: Prior box of a nuisance parameter, in its prior σ: wide enough never to bind (P(|z| > 6) ≈
#: 2e-9), finite so the sampler's box is.
PRIOR_BOX_SIGMA = 6.0

#: The arm angles a nuisance moves (radians, true − recorded): the two elevations, the camera's
#: azimuth relative to the light's, and the sample's tilt about x and y.
ARMS = ("light_theta", "camera_theta", "camera_phi", "tilt_x", "tilt_y", "light_r", "camera_r")
#: Angle nuisances: fitted name → (the arm angle it moves, how): "zero" by itself, "sag" times
#: the sine of the arm's elevation, "play" by −½ the side of the axis' last move (the arm lags
#: it), "play_light_phi" by +½ the side of the light's azimuth axis (its lag turns the light,
#: so the azimuth relative to it, the other way).
ANGLE_TERMS = {
    "light_theta_zero": ("light_theta", "zero"),
    "camera_theta_zero": ("camera_theta", "zero"),
    "camera_phi_zero": ("camera_phi", "zero"),
    "sample_tilt_x": ("tilt_x", "zero"),
    "sample_tilt_y": ("tilt_y", "zero"),
    "light_theta_sag": ("light_theta", "sag"),
    "camera_theta_sag": ("camera_theta", "sag"),
    "light_theta_play": ("light_theta", "play"),
    "camera_theta_play": ("camera_theta", "play"),
    "light_phi_play": ("camera_phi", "play_light_phi"),
    "camera_phi_play": ("camera_phi", "play"),
    "light_distance_mm": ("light_r", "zero"),
    "sample_bow_um": ("tilt", "bow"),
    "camera_distance_mm": ("camera_r", "zero"),
}
#: Units of a nuisance other than degrees, as their SI factor (the arm "light_r" is metres; the
#: bow's sagitta is metres, its tilt per row radians), and the word for the unit.
_SI = {"light_distance_mm": 1e-3, "sample_bow_um": 1e-6, "camera_distance_mm": 1e-3,
       "flat_falloff_pct": 1e-2, "ambient_mW": 1e-3, "linearity_pct": 1e-2}  # fmt: skip
_UNIT = {"light_distance_mm": "mm", "sample_bow_um": "µm", "camera_distance_mm": "mm",
         "flat_falloff_pct": "%", "ambient_mW": "mW/m²/sr", "linearity_pct": "%"}  # fmt: skip
#: Nuisances that multiply each row's f, or add to it, instead of moving its directions
#: (fitting.likelihood).
FACTOR_NUISANCES = ("flat_falloff_pct", "ambient_mW", "linearity_pct")


def to_si(name: str, value):
    """A nuisance's value in SI (radians for angles, metres for the lamp's distance)."""
    return np.asarray(value, dtype=np.float64) * _SI[name] if name in _SI else np.radians(value)


ANGLE_NUISANCES = tuple(ANGLE_TERMS)
#: Budget keys (sigma_deg) of the zeros → the nuisance, combined in quadrature.
_ZERO_KEYS = {
    "light_theta_zero": ("light_theta",),
    "camera_theta_zero": ("camera_theta",),
    "camera_phi_zero": ("camera_phi", "light_phi"),
    "sample_tilt_x": ("tilt_x",),
    "sample_tilt_y": ("tilt_y",),
}


@dataclass(frozen=True)
class SharedErrors:
    """What the fit carries: relative scale σ per channel, angle σ per nuisance (degrees), and
    the rig's kinematics preset (how a camera-elevation zero moves θ_o)."""

    scale_sigma: dict[str, float]
    angle_sigma_deg: dict[str, float]
    kinematics: str = "two-arm"
    #: Prior centres (degrees) of angle nuisances not centred on 0 (the gears' play).
    angle_center_deg: dict[str, float] = field(default_factory=dict)
    #: Budget components the fit carries (by name), for the words.
    carried: tuple[str, ...] = ()
    #: The sample's half side R (metres) when its bow is carried (``sample_bow_um``).
    bow_half_side_m: float | None = None
    #: The frame's intrinsics and corner ρ when the flat source's fall-off is carried.
    flat_field: dict | None = None
    #: Per channel, the lamp's intensity calibration divided by (W/sr) when ambient light is.
    ambient_intensity: dict | None = None

    def __bool__(self) -> bool:
        return bool(self.scale_sigma or self.angle_sigma_deg)


def shared_errors(
    budget: list[dict] | None,
    channels: list[str],
    *,
    positions: bool = False,
    levels: bool = False,
) -> SharedErrors | None:
    """The shared errors of `budget` the fit can carry for `channels`; None when it states
    none with a size. With the arms' `positions` per capture (gonio.arm_poses), the lamp's
    distance is carried as itself (its direction and 1/r² per pixel) instead of as a scale.
    With the samples' `levels` (their ``bend_level`` column), the camera's bend as calibration
    measured it from the brackets (``linearity_pct``)."""
    angles: dict[str, float] = {}
    distance = [
        c
        for c in budget or []
        if positions
        and c.get("light_distance_sigma_m")
        and isinstance(c.get("relative_sigma"), dict)
    ]
    if distance:
        angles["light_distance_mm"] = 1e3 * float(distance[0]["light_distance_sigma_m"])
        budget = [c for c in budget or [] if c is not distance[0]]
    scales = {}
    carried = [str(distance[0]["component"])] if distance else []
    for ch in channels:
        sig = scale_sigma(budget, ch)
        if sig is not None and sig > 0:
            scales[ch] = sig
    if scales:
        carried += [
            str(c.get("component"))
            for c in budget or []
            if str(c.get("component", "")).startswith("scale")
            and isinstance(c.get("relative_sigma"), dict)
        ]
    centers: dict[str, float] = {}
    kinematics = "two-arm"
    bow_half_side = flat_field = ambient = None
    for comp in budget or []:
        bend = comp.get("measured")
        is_bend = str(comp.get("component", "")).startswith("linearity")
        if levels and is_bend and isinstance(bend, dict) and bend.get("sigma"):
            # the bend the samples hold: β̂ ± σ left in, 0 ± σ once taken out (module docstring)
            angles["linearity_pct"] = 100.0 * float(bend["sigma"])
            if not bend.get("corrected"):
                centers["linearity_pct"] = 100.0 * float(bend["beta"])
            carried.append(str(comp.get("component")))
        if positions and comp.get("ambient_sigma_W_m2_sr") and comp.get("intensity_W_sr"):
            angles["ambient_mW"] = 1e3 * float(comp["ambient_sigma_W_m2_sr"])
            ambient = {str(k): float(v) for k, v in comp["intensity_W_sr"].items()}
            carried.append(str(comp.get("component")))
        if positions and comp.get("bow_sigma_m") and comp.get("half_side_m"):
            # the bow needs each row's place on the sample: the arms' positions give it
            angles["sample_bow_um"] = 1e6 * float(comp["bow_sigma_m"])
            bow_half_side = float(comp["half_side_m"])
            carried.append(str(comp.get("component")))
        if positions and comp.get("camera_distance_sigma_m"):
            angles["camera_distance_mm"] = 1e3 * float(comp["camera_distance_sigma_m"])
            carried.append(str(comp.get("component")))
        if positions and comp.get("falloff_sigma") and isinstance(comp.get("field"), dict):
            angles["flat_falloff_pct"] = 100.0 * float(comp["falloff_sigma"])
            flat_field = dict(comp["field"])
            carried.append(str(comp.get("component")))
        name = str(comp.get("component", ""))
        sig = comp.get("sigma_deg")
        if name.startswith("arm angles: encoder zeros") and isinstance(sig, dict) and sig:
            kinematics = str(comp.get("kinematics", kinematics))
            n0 = len(angles)
            for nuis, keys in _ZERO_KEYS.items():
                if kinematics == "inplane" and nuis == "camera_phi_zero":
                    continue  # no azimuth arms: a turntable's zero turns both directions alike
                total = math.sqrt(sum(float(sig[k]) ** 2 for k in keys if sig.get(k) is not None))
                if total > 0:
                    angles[nuis] = total
            if len(angles) > n0:
                carried.append(name)
        elif name.startswith("arm angles: gear backlash"):
            kinematics = str(comp.get("kinematics", kinematics))
            play, sag = comp.get("play_deg"), comp.get("sag_sigma_deg")
            if play:
                for nuis in (
                    "light_theta_play", "camera_theta_play", "light_phi_play", "camera_phi_play"
                ):  # fmt: skip
                    if kinematics == "inplane" and nuis.endswith("phi_play"):
                        continue
                    # the datasheet's play ± 50 %: gears wear and horns differ
                    angles[nuis], centers[nuis] = 0.5 * float(play), float(play)
            if sag:
                angles["light_theta_sag"] = angles["camera_theta_sag"] = float(sag)
            if play or sag:
                carried.append(name)
    out = SharedErrors(
        scales, angles, kinematics, centers, tuple(carried), bow_half_side, flat_field, ambient
    )
    return out if out else None


def is_nuisance(spec) -> bool:  # fitting.priors.ParameterSpec
    return getattr(spec, "prior_sigma", None) is not None


def _rotate_elevation(w: np.ndarray, arm_phi: np.ndarray, delta) -> np.ndarray:
    """Directions w (N, 3) turned by δ (radians; scalar or (W, 1)) about the horizontal axis
    a = (−sin φ, cos φ, 0) normal to the arm's vertical plane (Rodrigues): positive δ raises
    the arm away from the normal, toward its azimuth φ. Written out by component
    (w' = w cos δ + (a × w) sin δ + a (a·w)(1 − cos δ) with a_z = 0): the least squares and
    the chain call it thousands of times, and numpy's cross and stack cost more than the sums."""
    sp, cp = _sincos(arm_phi)
    d = np.asarray(delta, dtype=np.float64)
    c, s = np.cos(d), np.sin(d)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    along = (cp * y - sp * x) * (1.0 - c)  # (a·w)(1 − cos δ)
    return np.stack(
        [x * c + cp * z * s - sp * along, y * c + sp * z * s + cp * along,
         z * c - (sp * y + cp * x) * s],
        axis=-1,
    )  # fmt: skip


_SINCOS: dict[int, tuple] = {}


def _sincos(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sin φ, cos φ) of an arm-azimuth array, kept for the array's life (the rows' azimuths are
    the same arrays call after call)."""
    hit = _SINCOS.get(id(phi))
    if hit is not None and hit[0] is phi:
        return hit[1], hit[2]
    out = (np.sin(phi), np.cos(phi))
    if len(_SINCOS) > 64:
        _SINCOS.clear()
    _SINCOS[id(phi)] = (phi, *out)
    return out


def _turn_camera(v: np.ndarray, arm_phi_i, arm_phi_o, delta_rad: dict, kinematics: str):
    """Vectors v (N, 3) carried by the camera arm when its angles are off by `delta_rad`: its
    elevation about the axis normal to its plane, then its azimuth about the vertical."""
    d_o = delta_rad.get("camera_theta", 0.0)
    if kinematics == "inplane":
        # positive camera elevation is across the normal from the light (the specular side)
        side = np.where(np.cos(arm_phi_o - arm_phi_i) < 0.0, 1.0, -1.0)
        d_o = np.asarray(d_o, dtype=np.float64) * side
    v = _rotate_elevation(v, arm_phi_o, d_o)
    d_phi = np.asarray(delta_rad.get("camera_phi", 0.0), dtype=np.float64)
    if np.any(d_phi != 0):
        c, s = np.cos(d_phi)[..., None], np.sin(d_phi)[..., None]
        x, y = v[..., 0:1], v[..., 1:2]
        v = np.concatenate([x * c - y * s, x * s + y * c, v[..., 2:3]], axis=-1)
    return v


def _into_sample(v: np.ndarray, delta_rad: dict) -> np.ndarray:
    tx = np.asarray(delta_rad.get("tilt_x", 0.0), dtype=np.float64)
    ty = np.asarray(delta_rad.get("tilt_y", 0.0), dtype=np.float64)
    if np.any(tx != 0) or np.any(ty != 0):
        return _untilt(v, tx, ty)
    return v


def shifted_directions(
    wi: np.ndarray,
    wo: np.ndarray,
    arm_phi_i: np.ndarray,
    arm_phi_o: np.ndarray,
    delta_rad: dict,
    kinematics: str,
) -> tuple[np.ndarray, np.ndarray]:
    """(ω_i, ω_o) of the samples, each (N, 3) or (W, N, 3), when the arm angles are off by
    `delta_rad` ({arm in ARMS: radians, scalar, (W, 1) or (W, N)}; module docstring). Each arm
    turns about the axis normal to its own vertical plane, whose azimuth `arm_phi_*` is the
    arm's (the pose's, also where the arm stands on the normal), not the pixel's."""
    wi = _rotate_elevation(wi, arm_phi_i, delta_rad.get("light_theta", 0.0))
    wo = _turn_camera(wo, arm_phi_i, arm_phi_o, delta_rad, kinematics)
    return _into_sample(wi, delta_rad), _into_sample(wo, delta_rad)


def measured_geometry(
    wi: np.ndarray, wo: np.ndarray, rows: dict, delta: dict, kinematics: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ω_i, ω_o, irradiance ratio) of the samples in the world the nuisances describe. The
    ratio is what calibration's irradiance I cos θ_i / r² of the recorded geometry misses; the
    measured f is the BRDF at (ω_i', ω_o') times it.

    With the arms' positions (calibration recorded them): each pixel's ray, from the camera's
    position along −ω_o, meets the sample at p; the lamp moves `delta["light_r"]` metres along
    its arm and turns with its elevation, the camera and its rays turn with theirs, so the
    pixel meets the sample at p' (a camera turned about the sample's centre sees its points
    turned too: ~|p|·δ, which moves ω_i by |p|·δ/r) and sees the lamp at L' − p':
    ratio = cos θ_i' / cos θ_i · |L − p|² / |L' − p'|². Without them, the directions alone
    turn (:func:`shifted_directions`) and the ratio is cos θ_i' / cos θ_i."""
    if "light_pos" not in rows:
        wi2, wo2 = shifted_directions(wi, wo, rows["phi_i"], rows["phi_o"], delta, kinematics)
        return wi2, wo2, wi2[..., 2] / wi[:, 2]
    light, cam = rows["light_pos"], rows["cam_pos"]
    p = rows["point"] if "point" in rows else surface_point(cam, wo)
    d_c = delta.get("camera_r")
    cam_true = cam
    if d_c is not None:  # the pupil further along the line of sight: the same rays from there
        cam_true = (
            cam * (1.0 + np.asarray(d_c, dtype=np.float64) / np.linalg.norm(cam, axis=1))[..., None]
        )
    light_new = light
    d_r = delta.get("light_r")
    if d_r is not None:
        r = np.linalg.norm(light, axis=1)
        light_new = light * (1.0 + np.asarray(d_r, dtype=np.float64) / r)[..., None]
    light_new = _rotate_elevation(light_new, rows["phi_i"], delta.get("light_theta", 0.0))
    cam_new = _turn_camera(cam_true, rows["phi_i"], rows["phi_o"], delta, kinematics)
    # The camera sits on its arm (acquisition.kinematics: its orientation is the arm's forward
    # kinematics), so an arm error turns its rays by the rotation that moved it: the same pixel
    # looks along the turned ray, at the normal as anywhere else.
    ray = _turn_camera(-wo, rows["phi_i"], rows["phi_o"], delta, kinematics)
    p_new = cam_new - (cam_new[..., 2] / ray[..., 2])[..., None] * ray
    to_new, to_old = light_new - p_new, light - p
    r2_new, r2_old = np.sum(to_new**2, axis=-1), np.sum(to_old**2, axis=-1)
    wi2 = _into_sample(to_new / np.sqrt(r2_new)[..., None], delta)
    wo2 = _into_sample(-ray, delta)
    return wi2, wo2, r2_old / r2_new * wi2[..., 2] / wi[:, 2]


def surface_point(cam_pos: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Where each pixel's ray, from the camera at `cam_pos` back along −ω_o, meets the sample
    plane z = 0 (each (N, 3))."""
    return cam_pos - (cam_pos[:, 2] / wo[:, 2])[:, None] * wo


def arm_deltas(rows: dict[str, np.ndarray], natural_rad: dict[str, np.ndarray]) -> dict:
    """{arm: (W, N) radians} from the angle nuisances' values {name: (W,) radians} and the rows'
    arm data (:func:`arm_rows`)."""
    out: dict[str, np.ndarray] = {}
    for name, value in natural_rad.items():
        arm, how = ANGLE_TERMS[name]
        if how == "zero":
            coef = 1.0
        elif how == "sag":
            coef = rows["sin_" + arm]
        elif how == "play":
            coef = -0.5 * rows["side_" + arm]
        elif how == "bow":  # the dome's slope at each row's point (module docstring)
            v = np.asarray(value, dtype=np.float64)[:, None]
            for tilt, term in (("tilt_y", v * rows["bow_x"]), ("tilt_x", -v * rows["bow_y"])):
                out[tilt] = out[tilt] + term if tilt in out else term
            continue
        else:  # play_light_phi: the light lags its move, φ_o − φ_i the other way
            coef = 0.5 * rows["side_light_phi"]
        term = np.asarray(value, dtype=np.float64)[:, None] * coef
        out[arm] = out[arm] + term if arm in out else term
    return out


def _untilt(w: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """R_τᵀ w: a holder-frame direction in the frame of a sample tilted by R_τ = R_y(τ_y)
    R_x(τ_x) (calibrate-rig's convention, calibration.arm_offsets.tilt_rotation)."""
    cx, sx = np.cos(tx)[..., None], np.sin(tx)[..., None]
    cy, sy = np.cos(ty)[..., None], np.sin(ty)[..., None]
    x, y, z = w[..., 0:1], w[..., 1:2], w[..., 2:3]
    x, z = cy * x - sy * z, sy * x + cy * z  # R_yᵀ
    y, z = cx * y + sx * z, -sx * y + cx * z  # then R_xᵀ
    return np.concatenate(
        [np.broadcast_to(x, np.broadcast_shapes(x.shape, y.shape)), y, z], axis=-1
    )


def split_uncertainty(
    parameters: dict[str, dict], names: list[str], natural_draws: np.ndarray
) -> dict[str, dict]:
    """Each non-nuisance parameter's summary with ``sd_total`` (half its 16–84 % width: the
    draws hold every error), ``sd_sys`` and ``sd_stat`` — its spread split by the share of
    variance the nuisance draws explain (module docstring), sd_stat² + sd_sys² = sd_total²."""
    nuis = [i for i, n in enumerate(names) if is_nuisance_name(n)]
    if not nuis:
        return parameters
    z = natural_draws[:, nuis] - natural_draws[:, nuis].mean(axis=0)
    out = {}
    for i, name in enumerate(names):
        q = dict(parameters[name])
        if i not in nuis:
            y = natural_draws[:, i] - natural_draws[:, i].mean()
            coef, *_ = np.linalg.lstsq(z, y, rcond=None)
            var = float(np.var(y))
            share = float(np.clip(np.var(z @ coef) / var, 0.0, 1.0)) if var > 0 else 0.0
            total = 0.5 * (q["p84"] - q["p16"])
            q["sd_total"] = total
            q["sd_sys"] = total * math.sqrt(share)
            q["sd_stat"] = total * math.sqrt(1.0 - share)
        out[name] = q
    return out


def is_nuisance_name(name: str) -> bool:
    return name.startswith("scale_") or name in ANGLE_NUISANCES or name in FACTOR_NUISANCES


def carried_words(shared: SharedErrors, names: list[str], natural_draws: np.ndarray) -> str:
    """One line: which shared errors the intervals carry, each nuisance's prior σ and what the
    data made of it (posterior median ± sd)."""
    parts = []
    for i, name in enumerate(names):
        if not is_nuisance_name(name):
            continue
        col = natural_draws[:, i]
        if name.startswith("scale_"):
            prior = 100 * shared.scale_sigma[name.removeprefix("scale_")]
            parts.append(
                f"{name} {100 * (np.median(col) - 1):+.2f} ± {100 * np.std(col):.2f} % "
                f"(prior ± {prior:.3g} %)"
            )
        else:
            prior = shared.angle_sigma_deg[name]
            centre = shared.angle_center_deg.get(name, 0.0)
            unit = " " + _UNIT[name] if name in _UNIT else "°"
            parts.append(
                f"{name} {np.median(col):+.3f} ± {np.std(col):.3f}{unit} "
                f"(prior {centre:+.3g} ± {prior:.3g}{unit})"
            )
    return "shared errors marginalised as nuisance parameters (in every interval): " + "; ".join(
        parts
    )


def with_nuisances(space, shared: SharedErrors):  # ParameterSpace
    """`space` with the nuisance parameters of `shared` appended (module docstring)."""
    import dataclasses

    from fitting.priors import ParameterSpec

    k = PRIOR_BOX_SIGMA
    extra = [
        ParameterSpec(
            f"scale_{ch}",
            "scale",
            ch,
            "1",
            math.exp(-k * sig),
            math.exp(k * sig),
            True,
            prior_sigma=sig,
        )  # fmt: skip
        for ch, sig in shared.scale_sigma.items()
        if ch in space.channels
    ]
    for name, sig in shared.angle_sigma_deg.items():
        c = shared.angle_center_deg.get(name, 0.0)
        unit = _UNIT.get(name, "deg")
        extra.append(ParameterSpec(name, name, None, unit, c - k * sig, c + k * sig, False,
                                   prior_sigma=sig, prior_center=c))  # fmt: skip
    return dataclasses.replace(space, specs=space.specs + tuple(extra), shared_errors=shared)


def nuisance_effect(draws: np.ndarray, nuisance_cols: list[int]) -> np.ndarray:
    """The part of the draws (S, D) the nuisance parameters account for: their own deviation
    from the mean and, in every other column, its least-squares regression on them
    (E[θ | δ] − E[θ], linear in the small δ). draws − effect are the draws at the nuisances'
    mean — the statistical part, which the mismatch widening may scale (fitting.mismatch)
    without scaling the systematic part."""
    effect = np.zeros_like(draws)
    if not nuisance_cols:
        return effect
    z = draws[:, nuisance_cols] - draws[:, nuisance_cols].mean(axis=0)
    other = [i for i in range(draws.shape[1]) if i not in nuisance_cols]
    y = draws[:, other] - draws[:, other].mean(axis=0)
    coef, *_ = np.linalg.lstsq(z, y, rcond=None)
    effect[:, other] = z @ coef
    effect[:, nuisance_cols] = z
    return effect


@dataclass(frozen=True)
class SamplerCoordinates:
    """Where the sampler walks when a channel's scale s is a nuisance of a model homogeneous
    in its amplitudes A (f(c·A) = c·f(A), fitting.budget.amplitude_parameters): the data see
    only s·A, so in (A, s) the posterior is a curved ridge that ensemble moves cross slowly
    (R̂ 1.4 after 600 steps on the realistic rig). The sampler takes y = (s·A, s) instead —
    ln A + ln s for an amplitude sampled as a logarithm, A·s for a linear one — where the
    likelihood does not depend on s at all and s keeps its prior: the same posterior (the
    density carries the Jacobian |∂x/∂y| = 1/s per linear amplitude), sampled without a ridge.
    ``pairs``: (amplitude column, its channel's ln-s column, amplitude sampled as log)."""

    pairs: tuple[tuple[int, int, bool], ...]

    def to_sampler(self, x: np.ndarray) -> np.ndarray:
        y = np.array(x, dtype=np.float64, copy=True)
        for a, s, log in self.pairs:
            y[..., a] = x[..., a] + x[..., s] if log else x[..., a] * np.exp(x[..., s])
        return y

    def from_sampler(self, y: np.ndarray) -> np.ndarray:
        x = np.array(y, dtype=np.float64, copy=True)
        for a, s, log in self.pairs:
            x[..., a] = y[..., a] - y[..., s] if log else y[..., a] * np.exp(-y[..., s])
        return x

    def log_jacobian(self, y: np.ndarray) -> np.ndarray:
        """ln |∂x/∂y| at y (..., D): −ln s for every linear amplitude."""
        out = np.zeros(np.shape(y)[:-1])
        for _a, s, log in self.pairs:
            if not log:
                out = out - y[..., s]
        return out

    def wrap(self, log_prob):
        """ln p_y(y) = ln p_x(x(y)) + ln |∂x/∂y|."""

        def log_prob_y(y: np.ndarray) -> np.ndarray:
            return log_prob(self.from_sampler(y)) + self.log_jacobian(y)

        return log_prob_y

    def split(self, log_like, log_prior):
        """(ln L_y, ln π_y) for a sampler that weighs the two apart (parallel tempering raises
        only the likelihood to β): ln L at x(y), and ln π at x(y) with ln |∂x/∂y|."""

        def log_like_y(y: np.ndarray) -> np.ndarray:
            return log_like(self.from_sampler(y))

        def log_prior_y(y: np.ndarray) -> np.ndarray:
            return log_prior(self.from_sampler(y)) + self.log_jacobian(y)

        return log_like_y, log_prior_y

    def bounds(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A box holding the image of the box [lo, hi] (for placing the first walkers)."""
        ylo, yhi = lo.copy(), hi.copy()
        for a, s, log in self.pairs:
            if log:
                ylo[a], yhi[a] = lo[a] + lo[s], hi[a] + hi[s]
            else:
                ylo[a] = min(lo[a] * math.exp(lo[s]), lo[a] * math.exp(hi[s]))
                yhi[a] = max(hi[a] * math.exp(lo[s]), hi[a] * math.exp(hi[s]))
        return ylo, yhi


def sampler_coordinates(space, model, x: np.ndarray) -> SamplerCoordinates | None:
    """The coordinates for `space` (None: sample θ itself): every amplitude of a channel with
    a scale nuisance, when the model is homogeneous in its amplitudes at x (checked)."""
    from fitting.budget import amplitude_parameters

    scale_col = {s.channel: i for i, s in enumerate(space.specs) if s.base == "scale"}
    if not scale_col:
        return None
    nat = space.natural_dict(np.atleast_2d(x))
    ch0 = space.channels[0]
    values = {k: float(v[0, 0]) for k, v in space.channel_params(nat, ch0).items()}
    amps = amplitude_parameters(model, values)
    pairs = []
    for i, spec in enumerate(space.specs):
        if spec.base in amps and spec.channel in scale_col:
            pairs.append((i, scale_col[spec.channel], bool(spec.log)))
        elif spec.base in amps and spec.channel is None and len(scale_col) == 1:
            pairs.append((i, next(iter(scale_col.values())), bool(spec.log)))
    return SamplerCoordinates(tuple(pairs)) if pairs else None


def arm_positions_known(metadata: dict) -> bool:
    """Whether calibration recorded the arms' positions for every capture it lists
    (``gonio.arm_poses``): then the lamp's distance can be carried as itself."""
    import json

    try:
        poses = json.loads(metadata.get("gonio.arm_poses") or "{}")
    except (ValueError, TypeError):
        return False
    return bool(poses) and all(
        isinstance(p, dict) and "light_m" in p and "camera_m" in p for p in poses.values()
    )


def arm_rows(  # table: SampleTable
    table, bow_half_side_m: float | None = None, flat_field: dict | None = None
) -> dict[str, np.ndarray]:
    """Per row: the arms' azimuths (``phi_i``, ``phi_o``), the sines of the elevation axes
    (``sin_light_theta``, ``sin_camera_theta``) and the side of each axis' last move
    (``side_<axis>``: ±1, 0 unknown), from the metadata ``gonio.arm_poses`` (calibration, per
    capture) where the table has it and lists the row's capture; else the row's own φ and sin θ
    and no side (a table from elsewhere: near the normal the row's φ is a poor stand-in).
    With the arms' positions and a carried bow (`bow_half_side_m`, R), also ``bow_x``, ``bow_y``:
    2 (x, y)/R² at the row's point on the sample (the dome's tilt per metre of sagitta). With
    `flat_field` (the budget's intrinsics) and the rows' pixels, ``field_r2``: ρ/ρ_corner."""
    import json

    n = len(table.f)
    out = {
        "phi_i": np.array(table.phi_i, dtype=np.float64, copy=True),
        "phi_o": np.array(table.phi_o, dtype=np.float64, copy=True),
        "sin_light_theta": np.sin(np.asarray(table.theta_i, dtype=np.float64)),
        "sin_camera_theta": np.sin(np.asarray(table.theta_o, dtype=np.float64)),
    }
    for axis in ("light_theta", "camera_theta", "light_phi", "camera_phi"):
        out["side_" + axis] = np.zeros(n)
    if "bend_level" in table.extra:  # the camera's remaining bend scales with it (linearity)
        out["bend_level"] = np.asarray(table.extra["bend_level"], dtype=np.float64)
    px, py = table.extra.get("pixel_x"), table.extra.get("pixel_y")
    if flat_field and px is not None and py is not None:
        u = (np.asarray(px, np.float64) - flat_field["cx"]) / flat_field["fx"]
        v = (np.asarray(py, np.float64) - flat_field["cy"]) / flat_field["fy"]
        out["field_r2"] = (u * u + v * v) / flat_field["r2_corner"]
    text = table.metadata.get("gonio.arm_poses")
    ids = table.extra.get("capture_id")
    if not text or ids is None:
        return out
    try:
        known = {int(k): v for k, v in json.loads(text).items()}
    except (ValueError, TypeError, AttributeError):
        return out
    # One pass per capture over the capture list, then one gather per column: a run's rows
    # are millions, its captures thousands.
    caps, inverse = np.unique(np.asarray(ids, dtype=np.int64), return_inverse=True)
    per = {k: np.full(caps.size, np.nan) for k in out}
    per_light, per_cam = np.full((caps.size, 3), np.nan), np.full((caps.size, 3), np.nan)
    for j, cid in enumerate(caps):
        pose = known.get(int(cid))
        if not isinstance(pose, dict):
            continue
        per["phi_i"][j], per["phi_o"][j] = pose["phi"]
        for axis, angle in pose.get("axis", {}).items():
            per["sin_" + axis][j] = math.sin(angle)
        for axis, side in pose.get("approach", {}).items():
            if "side_" + axis in per:
                per["side_" + axis][j] = side
        if "light_m" in pose and "camera_m" in pose:
            per_light[j], per_cam[j] = pose["light_m"], pose["camera_m"]
    for k, col in per.items():
        value = col[inverse]
        keep = np.isfinite(value)
        out[k][keep] = value[keep]
    light_pos, cam_pos = per_light[inverse], per_cam[inverse]
    if np.all(np.isfinite(light_pos)) and np.all(np.isfinite(cam_pos)):
        out["light_pos"], out["cam_pos"] = light_pos, cam_pos
        point = surface_point(cam_pos, spherical_to_vector(table.theta_o, table.phi_o))
        out["point"] = point
        if bow_half_side_m:
            k = 2.0 / bow_half_side_m**2
            out["bow_x"], out["bow_y"] = k * point[:, 0], k * point[:, 1]
    return out
