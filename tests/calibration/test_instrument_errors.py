"""Instrument errors in the simulated world (simulator.scene: GeometryTruth, SensorSpec), each
enabled alone at a stated size: it moves what the lab recovers by what a first-order calculation
predicts (within 20 % of that prediction), and a disabled one never runs.

The lab's view is the real path: `calibrate_rig` (board views through the real driver stack,
solvePnP, the arm-offset fit) for the arm errors; acquisition and `reduce_run` for the camera's
non-linearity. Truth is the scene's stated error, never the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquisition.operator import AutoOperator
from acquisition.rig import build_rig
from gonio.backends import prepare_backends
from gonio.rig_calibration import calibrate_rig
from simulator.scene import GeometryTruth, load_scene
from tests.support.board_rig import BOARD, board_rig
from tests.support.effect_runs import effect_run, paired_rows
from tests.support.paths import REPO

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(67)

#: The arm-offset fit's own precision on these 12 views is ~0.02° (test_calibrate_rig: σ <
#: 0.05°), so each error is made large enough that 20 % of its predicted effect (≥ 0.05°) is
#: well above it. Sizes are still within what real rigs show (backlash of a worn horn, the sag
#: of a long arm).
BACKLASH_DEG = 1.5
SAG_DEG = 0.5


def _calibrate(tmp_path, geometry: GeometryTruth):
    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    rig = board_rig()
    world = prepare_backends(rig, scene.model_copy(update={"geometry": geometry}))
    dev = build_rig(rig)
    try:
        doc = calibrate_rig(rig, dev, BOARD, tmp_path / "arms.json", world.hands(AutoOperator()))
    finally:
        dev.close()
    used = [v for v in doc["views"] if v["used"]]
    assert len(used) >= 10
    return doc, world, rig


def test_backlash_shifts_the_recovered_zero_by_the_mean_lag(tmp_path) -> None:
    """Play b on the camera elevation: each view's arm lags the direction it came from by b/2,
    so the fitted constant offset (least squares over equally weighted views) is the mean of
    −sign(move)·b/2 over the views, the first move starting from the park angle."""
    doc, world, rig = _calibrate(
        tmp_path, GeometryTruth(backlash_deg={"camera_theta": BACKLASH_DEG})
    )
    park = next(a.park_deg for a in rig.axes if a.role == "camera_theta")
    prev, sign, lags = park, 0.0, []
    for v in doc["views"]:
        theta = v["axes_deg"]["camera_theta"]
        if abs(theta - prev) > 1e-6:
            sign = math.copysign(1.0, theta - prev)
        prev = theta
        if v["used"]:
            lags.append(-sign * BACKLASH_DEG / 2)
    predicted = float(np.mean(lags))
    assert abs(predicted) > 0.2  # the plan's views do not cancel the lag out
    got = doc["offsets_deg"]["camera_theta"]
    assert abs(got - predicted) <= 0.2 * abs(predicted), (got, predicted)
    assert world.effect_counts["backlash"] > 0 and world.effect_counts["compliance"] == 0


#: 0.6° and −0.4°: a sample seated on a burr; 20 % of each (≥ 0.08°) is well above the fit's
#: ~0.02° precision on these views.
TILT_DEG = {"x": 0.6, "y": -0.4}


def test_sample_tilt_is_recovered_by_the_rig_calibration(tmp_path) -> None:
    """A tilted sample (and so a tilted board on the holder): `gonio calibrate-rig` fits the
    sample plane's tilt in the convention the scene states it in (R_y(τ_y) R_x(τ_x)), so the
    first-order prediction of what it recovers is the tilt itself."""
    doc, world, _ = _calibrate(tmp_path, GeometryTruth(sample_tilt_deg=TILT_DEG))
    for axis, tilt in TILT_DEG.items():
        got = doc["tilt_deg"][axis]
        print(f"sample tilt {axis}: stated {tilt:+.2f}°, recovered {got:+.3f}°")
        assert abs(got - tilt) <= 0.2 * abs(tilt), (axis, got, tilt)
    assert world.effect_counts["sample_tilt"] > 0 and world.effect_counts["backlash"] == 0


def test_arm_sag_shifts_the_recovered_zero_by_the_mean_sag(tmp_path) -> None:
    """Sag c·sin θ of the camera arm: the fitted constant offset is the mean of c·sin θ_k over
    the views (first order in c: sin of the true angle ≈ sin of the believed one)."""
    doc, world, _ = _calibrate(tmp_path, GeometryTruth(compliance_deg={"camera_theta": SAG_DEG}))
    sags = [
        SAG_DEG * math.sin(math.radians(v["axes_deg"]["camera_theta"]))
        for v in doc["views"]
        if v["used"]
    ]
    predicted = float(np.mean(sags))
    got = doc["offsets_deg"]["camera_theta"]
    assert abs(got - predicted) <= 0.2 * predicted, (got, predicted)
    assert world.effect_counts["compliance"] > 0 and world.effect_counts["backlash"] == 0


def test_a_world_without_instrument_errors_runs_none(tmp_path) -> None:
    """The demo scene states no arm error: after a whole board calibration none has run."""
    world = prepare_backends(board_rig(), load_scene(REPO / "configs" / "scenes" / "demo.toml"))
    world.true_axes_rad()
    world.arm_pose()
    assert sum(world.effect_counts.values()) == 0


#: β = 5 %: a poor sensor's non-linearity (machine-vision datasheets: 0.1–1 %, consumer CMOS
#: up to a few %), large so the effect (β·u ≈ 1–4 %) stands far above DN rounding (< 0.1 %).
BETA = 0.05


def _signal_fraction(run_dir, table, full_well_e: float, gain_e_per_dn: float) -> np.ndarray:
    """ū = mean electrons of each sample's 4×4 block / full well, from the linear run's frames."""
    from acquisition.store import RunStore
    from calibration.decode import decode_frame

    store = RunStore.open(run_dir)
    try:
        paths = {int(r.id): r.frame_path for r in store.captures()}
    finally:
        store.close()
    cache: dict[int, np.ndarray] = {}
    u = np.empty(len(table))
    chans = {"R": 0, "G": 1, "B": 2}
    for j, (cid, x, y, ch) in enumerate(
        zip(table.extra["capture_id"], table.extra["pixel_x"], table.extra["pixel_y"],
            table.channel.astype(str), strict=True)
    ):  # fmt: skip
        if cid not in cache:
            fr = decode_frame(run_dir / paths[int(cid)])
            cache[cid] = (fr.dn - fr.black_level) * gain_e_per_dn
        x0, y0 = int(round(x - 1.5)), int(round(y - 1.5))
        u[j] = cache[cid][y0 : y0 + 4, x0 : x0 + 4, chans[ch]].mean() / full_well_e
    return u


def test_nonlinearity_moves_f_by_beta_times_the_signal_fraction(tmp_path) -> None:
    """A response e·(1 + β e/FW): with the lamp's certified scale (no reference target to
    cancel it; flats are uniform, so their normalised gain is unchanged), each calibrated f is
    multiplied by ≈ 1 + β ū, ū the sample's signal as a fraction of the full well (first order
    in β; the block mean of e² over e adds < 1 % of the effect for these smooth images)."""
    from acquisition.config import load_rig
    from simulator.scene import world_scene

    linear = effect_run(tmp_path / "linear", 0.0)
    bent = effect_run(tmp_path / "bent", BETA)
    world = world_scene(load_scene(REPO / "configs" / "scenes" / "demo.toml"),
                        load_rig(REPO / "configs" / "rigs" / "sim.toml"))  # fmt: skip
    a, b, good = paired_rows(linear, bent)
    ratio = bent.f[b][good] / linear.f[a][good]
    u = _signal_fraction(tmp_path / "linear", linear, world.sensor.full_well_e,
                         world.sensor.gain_e_per_dn)[a][good]  # fmt: skip
    assert u.max() > 0.2  # the run spans a useful part of the well
    bright = u > 0.05  # where the predicted effect (≥ 0.25 %) is well above DN rounding
    effect = (ratio[bright] - 1.0) / (BETA * u[bright])
    assert 0.8 <= np.median(effect) <= 1.2, np.median(effect)


#: 10 mm on the 0.5 m light arm: 2.5× a careful tape measure's error, so the effect (−4 %) is
#: far above DN rounding and the sample's ±3 % spread of distances changes it by < 5 %.
LIGHT_DISTANCE_ERROR_M = 0.010


def test_light_distance_error_moves_f_by_minus_two_delta_over_r(tmp_path) -> None:
    """The lamp 10 mm further than the rig file says: the lab's irradiance I cos θ_i / r² is
    too large by ((r + δ)/r)², so each calibrated f is multiplied by (r/(r + δ))² ≈ 1 − 2δ/r
    (first order in δ/r = 0.02; the second-order term adds 3δ²/r² = 0.12 % to the 4 % effect)."""
    from acquisition.config import load_rig

    r = load_rig(REPO / "configs" / "rigs" / "sim.toml").geometry.light_distance_m
    exact = effect_run(tmp_path / "exact", 0.0)
    far = effect_run(
        tmp_path / "far", 0.0, GeometryTruth(light_distance_error_m=LIGHT_DISTANCE_ERROR_M)
    )
    a, b, good = paired_rows(exact, far)
    good &= exact.f[a] > 0
    _matches_first_order(f"light distance +{LIGHT_DISTANCE_ERROR_M * 1e3:.0f} mm",
                         far.f[b] / exact.f[a], np.full(a.size, -2.0 * LIGHT_DISTANCE_ERROR_M / r),
                         good, 100)  # fmt: skip


#: 5 % from centre to corner: an LED flat panel's uniformity spec (integrating spheres ≤ 1 %).
FLAT_FALLOFF = 0.05


def test_flat_source_falloff_moves_f_by_the_inverse_profile(tmp_path) -> None:
    """A flat source whose radiance falls as 1 − a ρ/ρ_corner: the master flat's gain carries
    that profile (its normalisation is the fitted value on the optical axis, where the profile
    is 1), so each calibrated f is divided by it: f × 1/(1 − a ρ/ρ_corner), ρ at the sample's
    4×4 block centre (the profile is smooth: its mean over a block differs from its centre
    value by < 1e-4 of a here)."""
    from simulator.camera import flat_source_profile
    from simulator.render import Renderer

    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    k = Renderer(scene).intrinsics
    profile = flat_source_profile(k)
    exact = effect_run(tmp_path / "exact", 0.0, flat_falloff=0.0)
    bent = effect_run(tmp_path / "falloff", 0.0, flat_falloff=FLAT_FALLOFF)
    a, b, good = paired_rows(exact, bent)
    good &= exact.f[a] > 0
    # pixel_x, pixel_y: the block's centre in index units (pixel i spans [i, i + 1))
    px = np.floor(exact.extra["pixel_x"][a][good] + 0.5).astype(int)
    py = np.floor(exact.extra["pixel_y"][a][good] + 0.5).astype(int)
    predicted = 1.0 / (1.0 - FLAT_FALLOFF * profile[py, px]) - 1.0
    measured = bent.f[b][good] / exact.f[a][good] - 1.0
    far = predicted > 0.01  # where the effect (≥ 1 %) stands far above DN rounding
    assert far.sum() > 100
    effect = measured[far] / predicted[far]
    print(f"flat falloff {FLAT_FALLOFF:.0%}: measured/predicted median {np.median(effect):.3f}"
          f" over {far.sum()} samples")  # fmt: skip
    assert 0.8 <= np.median(effect) <= 1.2, np.median(effect)


def _surface_point(origin: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """Where rays from `origin` along `ray` (each (N, 3)) meet the sample plane z = 0."""
    return origin - (origin[:, 2] / ray[:, 2])[:, None] * ray


def _matches_first_order(label: str, ratio, predicted, keep, min_samples: int) -> None:
    """The issue's bound: over the `keep` samples, the median of the measured effect (ratio − 1)
    over the predicted one is 1 within 20 %; prints both so a run shows the figures."""
    effect = (ratio[keep] - 1.0) / predicted[keep]
    assert keep.sum() > min_samples, (label, keep.sum())
    size = 100 * np.abs(predicted[keep])
    print(f"{label}: predicted {size.min():.2f}–{size.max():.2f} %, measured/predicted median "
          f"{np.median(effect):.3f} over {keep.sum()} samples")  # fmt: skip
    assert 0.8 <= np.median(effect) <= 1.2, (label, np.median(effect))


def _believed_rays(run_dir, table, rows):
    """Per sample `rows` of `table`: the camera and lamp positions the rig's kinematics give for
    its capture's measured axes, and the pixel ray's direction −ω_o (the lab's geometry, which
    a noise-free run without geometric errors shares with the world)."""
    from acquisition.config import load_rig
    from acquisition.kinematics import Kinematics
    from acquisition.store import RunStore

    kin = Kinematics(load_rig(REPO / "configs" / "rigs" / "sim.toml"))
    with RunStore.open(run_dir) as store:
        axes = {int(r.id): r.axes_measured for r in store.captures()}  # radians
    cid = table.extra["capture_id"][rows]
    cam = np.array([kin.camera_position_m(axes[int(c)]) for c in cid])
    lamp = np.array([kin.light_position_m(axes[int(c)]) for c in cid])
    to, po = table.theta_o[rows], table.phi_o[rows]
    d = -np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=1)
    return cam, lamp, d


#: 25 mm: a camera's entrance pupil sits somewhere inside its lens, known to ~5–10 mm; 2.5×
#: that so the effect (≤ ~1 % at the sample's edge) stands above DN rounding (~1e-4 per block).
CAMERA_DISTANCE_ERROR_M = 0.025


def test_camera_distance_error_moves_f_by_the_irradiance_at_the_true_point(tmp_path) -> None:
    """The camera 25 mm further along its line of sight than the rig file says, over a
    Lambertian sample: radiance does not fall with distance, so the only change is where each
    pixel's ray really meets the sample. The lab traces the ray from the believed centre C to
    x_b (z = 0); it really starts at C' = C (1 + δ/|C|) with the same direction (the camera
    still aims at the sample centre), so it meets the sample at x_t = C' + s' d, s' = −C'_z/d_z.
    The lab divides by the irradiance at x_b, E ∝ cos θ_i / r² = (L − x)_z / |L − x|³, so each
    calibrated f is multiplied by E(x_t)/E(x_b) (exact for a Lambertian; computed here from the
    rig's kinematics and each sample's recorded ω_o, not by calibration)."""
    from simulator.scene import DiffuseMaterial

    matte = {"material": DiffuseMaterial(reflectance=(0.6, 0.4, 0.2))}
    exact = effect_run(tmp_path / "exact", 0.0, **matte)
    far = effect_run(
        tmp_path / "far",
        0.0,
        GeometryTruth(camera_distance_error_m=CAMERA_DISTANCE_ERROR_M),
        **matte,
    )
    a, b, good = paired_rows(exact, far)
    good &= exact.f[a] > 0
    cam, lamp, d = _believed_rays(tmp_path / "exact", exact, a)
    x_b = _surface_point(cam, d)
    cam_t = cam * (1.0 + CAMERA_DISTANCE_ERROR_M / np.linalg.norm(cam, axis=1))[:, None]
    x_t = _surface_point(cam_t, d)

    def irradiance(x):
        v = lamp - x
        return v[:, 2] / np.linalg.norm(v, axis=1) ** 3

    predicted = irradiance(x_t) / irradiance(x_b) - 1.0
    # where the prediction (≥ 0.1 %) stands well above DN rounding
    big = good & (np.abs(predicted) > 1e-3)
    _matches_first_order(f"camera distance +{CAMERA_DISTANCE_ERROR_M * 1e3:.0f} mm",
                         far.f[b] / exact.f[a], predicted, big, 50)  # fmt: skip


#: 5 % at 3° off the axis: a halogen lamp behind a condenser (lamp makers' beam plots: 1–5 % over
#: a few degrees); the sample's corners sit up to ~4° off it, so the effect spans 0–9 %.
BEAM_FALLOFF, BEAM_AT_DEG = 0.05, 3.0


def test_beam_nonuniformity_moves_f_by_the_lamps_profile_at_each_point(tmp_path) -> None:
    """A lamp whose intensity falls off its axis as I₀ (1 − a (ψ/ψ_a)²), aimed at the sample
    centre: the lab believes I₀ at every point, so each calibrated f is multiplied by
    1 − a (ψ/ψ_a)², ψ the angle at the lamp between its axis (towards the centre) and the
    sample's surface point x = C + s d on z = 0 (exact for any material: only the irradiance
    changes; computed here from the rig's kinematics and each sample's recorded ω_o)."""
    exact = effect_run(tmp_path / "exact", 0.0)
    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    light = scene.light.model_copy(
        update={"beam_falloff": BEAM_FALLOFF, "beam_falloff_at_deg": BEAM_AT_DEG}
    )
    beamed = effect_run(tmp_path / "beam", 0.0, light=light)
    a, b, good = paired_rows(exact, beamed)
    good &= exact.f[a] > 0
    cam, lamp, d = _believed_rays(tmp_path / "exact", exact, a)
    x = _surface_point(cam, d)
    to_x = (x - lamp) / np.linalg.norm(x - lamp, axis=1)[:, None]
    axis = -lamp / np.linalg.norm(lamp, axis=1)[:, None]
    psi_deg = np.degrees(np.arccos(np.clip(np.sum(to_x * axis, axis=1), -1.0, 1.0)))
    predicted = -BEAM_FALLOFF * (psi_deg / BEAM_AT_DEG) ** 2
    big = good & (np.abs(predicted) > 1e-3)  # well above DN rounding
    _matches_first_order(f"beam falloff {BEAM_FALLOFF:.0%} at {BEAM_AT_DEG:g}° (ψ up to "
                         f"{psi_deg[big].max():.2f}°)", beamed.f[b] / exact.f[a], predicted, big,
                         100)  # fmt: skip


#: A 0.5 mm dome over the 50 mm sample: a curled sheet (paper, foil: 0.1–1 mm); its edges lean
#: by 2s/R = 2.3°, so the effect spans 0 to ~±5 % over the plan's incidences.
BOW_M = 5e-4


def test_sample_bow_moves_f_by_the_tilt_of_the_local_normal(tmp_path) -> None:
    """A sample bowed into the dome h = s (1 − (x² + y²)/R²) over a Lambertian: the lab believes
    it flat, but each point is lit along its true normal n' = (−h_x, −h_y, 1)/‖·‖ (slopes
    −2 s (x, y)/R²), so each calibrated f is multiplied, to first order in the slope, by
    1 − (h_x ω_i,x + h_y ω_i,y)/ω_i,z, ω_i the lamp's direction at the sample's point x (from
    the rig's kinematics and each sample's recorded ω_o; the 0.5 mm heights move x by < 1 mm·
    tan θ_o, which moves the prediction by < 0.1 % of itself)."""
    from acquisition.config import load_rig
    from simulator.scene import DiffuseMaterial

    half = load_rig(REPO / "configs" / "rigs" / "sim.toml").sample.size_m / 2
    matte = {"material": DiffuseMaterial(reflectance=(0.6, 0.4, 0.2))}
    flat = effect_run(tmp_path / "flat", 0.0, **matte)
    bowed = effect_run(tmp_path / "bowed", 0.0, GeometryTruth(sample_bow_m=BOW_M), **matte)
    a, b, good = paired_rows(flat, bowed)
    good &= flat.f[a] > 0
    cam, lamp, d = _believed_rays(tmp_path / "flat", flat, a)
    x = _surface_point(cam, d)
    wi = (lamp - x) / np.linalg.norm(lamp - x, axis=1)[:, None]
    h_x, h_y = -2.0 * BOW_M * x[:, 0] / half**2, -2.0 * BOW_M * x[:, 1] / half**2
    predicted = -(h_x * wi[:, 0] + h_y * wi[:, 1]) / wi[:, 2]
    big = good & (np.abs(predicted) > 1e-3)  # well above DN rounding
    _matches_first_order(f"bow {BOW_M * 1e3:g} mm", bowed.f[b] / flat.f[a], predicted, big, 100)


#: The lamp 2 % brighter than its certificate: a certificate's k = 2 uncertainty is 1–3 %
#: (NIST SP 250-89), so 2 % is a plausible error of one lamp.
CERT_ERROR = 0.02


def test_certificate_error_moves_f_by_the_lamps_true_over_certified_intensity(tmp_path) -> None:
    """The lab divides by the certificate's intensity I_c; the lamp gives I_c (1 + ε): every
    calibrated f is multiplied by 1 + ε, exactly (the irradiance is linear in I)."""
    from acquisition.config import load_rig
    from simulator.scene import world_scene

    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    world = world_scene(scene, load_rig(REPO / "configs" / "rigs" / "sim.toml"))
    bright = world.light.model_copy(
        update={"intensity_W_sr": tuple(i * (1 + CERT_ERROR) for i in world.light.intensity_W_sr)}
    )
    exact = effect_run(tmp_path / "exact", 0.0, light=world.light)
    off = effect_run(tmp_path / "off", 0.0, light=bright)
    a, b, good = paired_rows(exact, off)
    good &= exact.f[a] > 0
    _matches_first_order(f"certificate +{CERT_ERROR:.0%}", off.f[b] / exact.f[a],
                         np.full(a.size, CERT_ERROR), good, 100)  # fmt: skip


#: 0.02 W m⁻² sr⁻¹ of ambient light: a lit room around an open rig (a dark lab with black
#: curtains: ~0.0005), so the effect (~1–3 % of f) stands far above DN rounding.
STRAY_RADIANCE = 0.02


def test_stray_light_moves_f_by_pi_l_over_the_lamps_irradiance(tmp_path) -> None:
    """Ambient radiance L_amb over a Lambertian sample adds ρ·L_amb to its radiance, and the lab
    divides by the lamp's irradiance E = I cos θ_i / r² only: each calibrated f = ρ/π gains
    ρ L_amb / E, i.e. is multiplied by 1 + π L_amb r² / (I cos θ_i), with I the lamp's
    intensity, r and θ_i at the sample's point (from the rig's kinematics and ω_o)."""
    from acquisition.config import load_rig
    from simulator.scene import DiffuseMaterial, StrayLightSpec, world_scene

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    matte = {"material": DiffuseMaterial(reflectance=(0.6, 0.4, 0.2))}
    exact = effect_run(tmp_path / "exact", 0.0, **matte)
    stray = StrayLightSpec(radiance_W_m2_sr=(STRAY_RADIANCE,) * 3)
    lit = effect_run(tmp_path / "lit", 0.0, stray_light=stray, **matte)
    a, b, good = paired_rows(exact, lit)
    good &= (exact.f[a] > 0) & (exact.channel[a].astype(str) == "G")
    cam, lamp, d = _believed_rays(tmp_path / "exact", exact, a)
    x = _surface_point(cam, d)
    to_lamp = lamp - x
    r2 = np.sum(to_lamp**2, axis=1)
    cos_i = to_lamp[:, 2] / np.sqrt(r2)
    intensity = world_scene(load_scene(REPO / "configs" / "scenes" / "demo.toml"), rig)
    i_g = intensity.light.intensity_W_sr[1]
    predicted = np.pi * STRAY_RADIANCE * r2 / (i_g * cos_i)
    _matches_first_order(f"stray light {STRAY_RADIANCE} W/m²/sr", lit.f[b] / exact.f[a],
                         predicted, good, 50)  # fmt: skip


#: A 5 mm lamp disk (realistic.toml's) over a glossy Beckmann lobe (m = 0.05, where a lamp's size
#: matters most): the peak loses ~0.4 % and the flanks gain up to ~1 % (far above DN rounding,
#: small enough for the lowest order: ρ²/m² = 0.04).
LAMP_RADIUS_M, GLOSSY_M, GLOSSY_W, GLOSSY_RHO = 0.005, 0.05, 0.3, 0.5


def _beckmann(s: np.ndarray, m: float) -> np.ndarray:
    """Beckmann D in slope space: exp(−|s|²/m²) / (π m² cos⁴θ_h), cos⁻⁴θ_h = (1 + |s|²)²."""
    q = np.sum(s**2, axis=-1)
    return np.exp(-q / m**2) * (1 + q) ** 2 / (np.pi * m**2)


def test_lamp_size_smooths_a_glossy_lobe_by_its_curvature(tmp_path) -> None:
    """A lamp disk of radius a instead of a point: from a sample point the lamp spans a disk of
    angular radius ρ = a/|L − p| around ω_i, so the measured f is the BRDF averaged over it. The
    average of a disk is symmetric, so the first order vanishes; to second order the half
    vector's slope s = h_xy/h_z moves by δs = J δω with ⟨δω δωᵀ⟩ = ρ²/4 (a uniform disk), so
    the lobe gains ½ tr(∇²D Σ)/D with Σ = (ρ²/4) J Jᵀ (J, ∇²D by central differences of the
    analytic Beckmann D); the diffuse part is unchanged, so f × (1 + lobe share ·
    ½ tr(∇²D Σ)/D), and × cos ψ for the disk's Lambertian emission seen ψ off its axis (G,
    1/cos θ vary slowly: their second order, ~ρ², is < 1 % of the lobe's ρ²/m²)."""
    from acquisition.config import load_rig
    from simulator.scene import (
        BlendMaterial,
        DiffuseMaterial,
        LightSpec,
        RoughConductorMaterial,
        world_scene,
    )

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    glossy = BlendMaterial(
        weight=GLOSSY_W,
        first=DiffuseMaterial(reflectance=(GLOSSY_RHO,) * 3),
        second=RoughConductorMaterial(alpha=GLOSSY_M, conductor="none"),
    )
    world = world_scene(load_scene(REPO / "configs" / "scenes" / "demo.toml"), rig)
    disk = LightSpec(type="area", shape="disk", radius_m=LAMP_RADIUS_M,
                     intensity_W_sr=world.light.intensity_W_sr)  # fmt: skip
    # A bracket: the peak is ~100× the diffuse part, unsaturated only in the short exposure.
    bracket = (0.016, 0.0004)
    point = effect_run(
        tmp_path / "point", 0.0, None, None, bracket, material=glossy, light=world.light
    )
    area = effect_run(tmp_path / "area", 0.0, None, None, bracket, material=glossy, light=disk)
    a, b, good = paired_rows(point, area)
    good &= (point.f[a] > 0) & (point.channel[a].astype(str) == "G")
    cam, lamp, d = _believed_rays(tmp_path / "point", point, a)
    x = _surface_point(cam, d)
    wo = -d
    wi = (lamp - x) / np.linalg.norm(lamp - x, axis=1)[:, None]
    rho = LAMP_RADIUS_M / np.linalg.norm(lamp - x, axis=1)
    axis = lamp / np.linalg.norm(lamp, axis=1)[:, None]
    cos_psi = np.sum(wi * axis, axis=1)

    def slope(w_in):
        h = w_in + wo
        return h[:, :2] / h[:, 2:3]

    e1 = np.cross(wi, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(wi, e1)
    eps = 1e-5
    jac = np.stack([(slope(wi + eps * e) - slope(wi - eps * e)) / (2 * eps) for e in (e1, e2)],
                   axis=2)  # (N, 2 slope, 2 lamp-plane)  # fmt: skip
    sigma = (rho**2 / 4)[:, None, None] * jac @ np.transpose(jac, (0, 2, 1))
    s0, h = slope(wi), 1e-4
    hess = np.empty((len(s0), 2, 2))
    for i in range(2):
        for j in range(2):
            di, dj = np.eye(2)[i] * h, np.eye(2)[j] * h
            hess[:, i, j] = (
                _beckmann(s0 + di + dj, GLOSSY_M) - _beckmann(s0 + di - dj, GLOSSY_M)
                - _beckmann(s0 - di + dj, GLOSSY_M) + _beckmann(s0 - di - dj, GLOSSY_M)
            ) / (4 * h * h)  # fmt: skip
    lobe_rel = 0.5 * np.einsum("nij,nji->n", hess, sigma) / _beckmann(s0, GLOSSY_M)
    share = 1.0 - (1 - GLOSSY_W) * GLOSSY_RHO / np.pi / point.f[a]
    predicted = cos_psi * (1.0 + share * lobe_rel) - 1.0
    big = good & (np.abs(predicted) > 2e-3) & (share > 0.5)  # near the peak, well above DN
    _matches_first_order(f"lamp disk {LAMP_RADIUS_M * 1e3:g} mm on m = {GLOSSY_M}",
                         area.f[b] / point.f[a], predicted, big, 20)  # fmt: skip


def test_encoder_quantisation_puts_every_arm_on_a_whole_tick(tmp_path) -> None:
    """The emulated servos position and report whole ticks of 360°/4096 (XM430: 0.088°), as
    the real ones do: the angle each capture records is zero + direction·k·0.088°/gear for an
    integer k, and lies within half a tick (0.044°) of the plan's commanded angle — the
    quantisation error, which the lab records and so never mistakes."""
    from acquisition.config import load_rig
    from acquisition.store import RunStore

    effect_run(tmp_path / "run", 0.0)
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    axes = {a.role: a for a in rig.axes}
    tick_rad = 2 * math.pi / 4096
    with RunStore.open(tmp_path / "run") as store:
        records = list(store.captures())
    assert records
    for rec in records:
        for role, measured in rec.axes_measured.items():
            ax = axes[role]
            k = (measured - math.radians(ax.zero_offset_deg)) * ax.direction * ax.gear_ratio
            k /= tick_rad
            assert abs(k - round(k)) < 1e-6, (role, k)
            error = abs(measured - rec.axes_commanded[role]) * ax.gear_ratio
            assert error <= tick_rad / 2 + 1e-9, (role, math.degrees(error))
