"""Rigs drawn from an instrument budget: the shared errors a lab states in its rig file (k = 1)
and, for the simulated world, one draw of each — the error a real rig carries for its life.

Coverage and the accuracy-vs-time study's realistic rig are statements about rigs: each repeat
is another rig, so each gets a fresh draw of every shared error (`InstrumentBudget.world`) while
the rig file keeps stating the same distribution (`InstrumentBudget.rig`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.special import ndtri

from simulator.scene import StrayLightSpec

__all__ = ["InstrumentBudget", "sobol_normal"]

_ZERO_AXES = ("light_theta", "camera_theta", "camera_phi")
_PLAY_AXES = ("light_theta", "camera_theta", "light_phi", "camera_phi")
_SAG_AXES = ("light_theta", "camera_theta")


@dataclass(frozen=True)
class InstrumentBudget:
    """The sizes (k = 1) of a typical Dynamixel X-series lab rig's shared errors, each with
    where that size comes from."""

    #: The lamp certificate's relative σ (NIST SP 250-89, FEL lamp standards: 1–2 % at k = 2,
    #: lamp-to-lamp and ageing more).
    cert_rel_sigma: float = 0.015
    #: A tape measure to a filament inside its envelope: a few mm on a 0.5 m arm.
    distance_sigma_m: float = 0.003
    #: Each arm's encoder zero against the geometric zero after mounting.
    zero_sigma_deg: float = 0.2
    #: The sample on its holder (a burr, tape under an edge), about x and about y.
    tilt_sigma_deg: float = 0.2
    #: The gears' play per axis (XM430-W350: 0.25°, plus horn and arm); the world draws it
    #: ± `play_spread` (relative σ) around this value, as the rig file states it.
    play_deg: float = 0.3
    play_spread: float = 0.5
    #: A 0.5 m arm's sag when horizontal.
    sag_sigma_deg: float = 0.15
    #: The sample's bow (the sagitta of a dome over its half side): a painted card or coated
    #: panel ~0.1 mm over 50 mm; sheet samples curl by 0.1–1 mm, a lapped tile ~10 µm.
    bow_sigma_m: float = 0.0001
    #: The camera's entrance pupil along its line of sight: inside the lens, known to ~5–10 mm
    #: without a pupil measurement.
    camera_distance_sigma_m: float = 0.005
    #: The flat-field source's fall-off from the optical axis to the frame's corner: LED flat
    #: panels' uniformity specs 2–5 % (an integrating sphere's port ≤ 1 %); either sign (an
    #: edge-lit panel is brighter at its edges).
    flat_falloff_sigma: float = 0.02
    #: Light the lamp does not cause (the room, a monitor, a controller's LED), as the radiance
    #: it gives a white surface: a dark lab with black curtains ~5e-4 W m⁻² sr⁻¹ (~0.1 % of a
    #: diffuse f at 0.5 m from a 1 W/sr lamp). Never negative: the world draws σ·|z|.
    ambient_sigma_W_m2_sr: float = 5e-4

    #: How many standard-normal numbers one world draws (`world`'s `z`).
    N_DRAWS = 1 + 1 + len(_ZERO_AXES) + 2 + len(_PLAY_AXES) + len(_SAG_AXES) + 4

    def stated(self) -> dict[str, float]:
        return asdict(self)

    def rig(self, rig: Any, lamp_radius_m: float = 0.0) -> Any:
        """`rig` (acquisition.config.RigConfig) stating this budget: the lamp's certificate and
        the geometry's σ and the sample's flatness, which calibration writes into the samples'
        budget and the fit carries as nuisance parameters; and the lamp's exit aperture
        (`lamp_radius_m`, a lab measures it with a ruler), which the fit averages over."""
        return rig.model_copy(
            update={
                "sample": rig.sample.model_copy(update={"bow_sigma_m": self.bow_sigma_m}),
                "calibration": rig.calibration.model_copy(
                    update={"flat_source_falloff_sigma": self.flat_falloff_sigma}
                ),
                "light": rig.light.model_copy(
                    update={
                        "intensity_rel_sigma": self.cert_rel_sigma,
                        "radius_m": lamp_radius_m,
                        "ambient_sigma_W_m2_sr": self.ambient_sigma_W_m2_sr,
                    }
                ),
                "geometry": rig.geometry.model_copy(
                    update={
                        "light_distance_sigma_m": self.distance_sigma_m,
                        "axis_zero_sigma_deg": dict.fromkeys(_ZERO_AXES, self.zero_sigma_deg),
                        "sample_tilt_sigma_deg": self.tilt_sigma_deg,
                        "backlash_deg": self.play_deg,
                        "arm_sag_deg": self.sag_sigma_deg,
                        "camera_distance_sigma_m": self.camera_distance_sigma_m,
                    }
                ),
            }
        )

    def world(self, scene: Any, z: np.ndarray, seed: int) -> Any:
        """`scene` (simulator.scene.Scene) as one rig of this budget: its lamp, distance, arm
        zeros, sample tilt, gears' play and arms' sag set from the `N_DRAWS` standard-normal
        numbers `z`, and sensor noise from `seed`: its lamp, distance, arm zeros, sample tilt,
        gears' play, arms' sag, sample bow, camera distance, flat-source fall-off and room
        light. The rest stays as `scene` has it: the lamp's size and drift and the camera's
        non-linearity (calibration measures it from the brackets)."""
        z = np.asarray(z, float)
        if z.shape != (self.N_DRAWS,):
            raise ValueError(f"one world takes {self.N_DRAWS} draws, got shape {z.shape}")
        zeros, tilt = z[2:5], z[5:7]
        plays, sags, bow, cam_r, falloff = z[7:11], z[11:13], z[13], z[14], z[15]
        room = self.ambient_sigma_W_m2_sr * abs(float(z[16]))
        cert = 1.0 + self.cert_rel_sigma * z[0]
        geometry = scene.geometry.model_copy(
            update={
                "light_distance_error_m": self.distance_sigma_m * z[1],
                "axis_zero_error_deg": {
                    a: self.zero_sigma_deg * float(v)
                    for a, v in zip(_ZERO_AXES, zeros, strict=True)
                },
                "sample_tilt_deg": {
                    "x": self.tilt_sigma_deg * float(tilt[0]),
                    "y": self.tilt_sigma_deg * float(tilt[1]),
                },
                "backlash_deg": {
                    a: max(0.0, self.play_deg * (1 + self.play_spread * float(v)))
                    for a, v in zip(_PLAY_AXES, plays, strict=True)
                },
                "compliance_deg": {
                    a: self.sag_sigma_deg * float(v) for a, v in zip(_SAG_AXES, sags, strict=True)
                },
                "sample_bow_m": self.bow_sigma_m * float(bow),
                "camera_distance_error_m": self.camera_distance_sigma_m * float(cam_r),
            }
        )
        return scene.model_copy(
            update={
                "light": scene.light.model_copy(update={"intensity_W_sr": (cert, cert, cert)}),
                "geometry": geometry,
                "flat_source_falloff": self.flat_falloff_sigma * float(falloff),
                "stray_light": StrayLightSpec(radiance_W_m2_sr=(room, room, room)),
                "seed": seed,
            }
        )


def sobol_normal(n: int, dims: int, seed: int) -> np.ndarray:
    """(n, dims) standard-normal draws from a scrambled Sobol' sequence (randomised quasi-Monte
    Carlo, Owen 1997). The net's balance holds for a power of 2 points; another n takes the
    first n of the next power of 2 (a prefix of the sequence: still spread over the whole
    budget, its balance only near that of the power below). A Latin hypercube stratifies each
    draw alone, but a parameter's error often sums several (kd's: the lamp's certificate and its
    distance), and the sum of two stratified columns is not stratified: over 30 realistic rigs
    kd's 68 % coverage was 0.53 with one hypercube and 0.87 with another, the intervals being
    the same.
    Sobol' points are also stratified in every pair of the leading dimensions (a (t, m, 2)-net
    in base 2), so sums of them are too; estimates stay unbiased (the scrambling)."""
    from scipy.stats import qmc

    if n < 1:
        raise ValueError(f"a Sobol' sample takes at least 1 point, not {n}")
    u = qmc.Sobol(d=dims, scramble=True, seed=seed).random(1 << (n - 1).bit_length())[:n]
    return ndtri(np.clip(u, 1e-12, 1 - 1e-12))
