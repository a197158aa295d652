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

__all__ = ["InstrumentBudget", "latin_hypercube_normal"]

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

    #: How many standard-normal numbers one world draws (`world`'s `z`).
    N_DRAWS = 1 + 1 + len(_ZERO_AXES) + 2 + len(_PLAY_AXES) + len(_SAG_AXES)

    def stated(self) -> dict[str, float]:
        return asdict(self)

    def rig(self, rig: Any) -> Any:
        """`rig` (acquisition.config.RigConfig) stating this budget: the lamp's certificate and
        the geometry's σ, which calibration writes into the samples' budget and the fit carries
        as nuisance parameters."""
        return rig.model_copy(
            update={
                "light": rig.light.model_copy(update={"intensity_rel_sigma": self.cert_rel_sigma}),
                "geometry": rig.geometry.model_copy(
                    update={
                        "light_distance_sigma_m": self.distance_sigma_m,
                        "axis_zero_sigma_deg": dict.fromkeys(_ZERO_AXES, self.zero_sigma_deg),
                        "sample_tilt_sigma_deg": self.tilt_sigma_deg,
                        "backlash_deg": self.play_deg,
                        "arm_sag_deg": self.sag_sigma_deg,
                    }
                ),
            }
        )

    def world(self, scene: Any, z: np.ndarray, seed: int) -> Any:
        """`scene` (simulator.scene.Scene) as one rig of this budget: its lamp, distance, arm
        zeros, sample tilt, gears' play and arms' sag set from the `N_DRAWS` standard-normal
        numbers `z`, and sensor noise from `seed`. The lamp's size and drift stay as `scene`
        has them. Effects no budget component sizes yet are switched off, because the fit could
        only be wrong about them: the camera's non-linearity (the budget names it, the fit does
        not carry it), the flat source's fall-off, stray light, the camera's distance and the
        sample's bow."""
        z = np.asarray(z, float)
        if z.shape != (self.N_DRAWS,):
            raise ValueError(f"one world takes {self.N_DRAWS} draws, got shape {z.shape}")
        zeros, tilt = z[2:5], z[5:7]
        plays, sags = z[7:11], z[11:13]
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
                "camera_distance_error_m": 0.0,
                "sample_bow_m": 0.0,
            }
        )
        return scene.model_copy(
            update={
                "light": scene.light.model_copy(update={"intensity_W_sr": (cert, cert, cert)}),
                "geometry": geometry,
                "sensor": scene.sensor.model_copy(update={"nonlinearity": 0.0}),
                "flat_source_falloff": 0.0,
                "stray_light": None,
                "seed": seed,
            }
        )


def latin_hypercube_normal(n: int, dims: int, seed: int) -> np.ndarray:
    """(n, dims) standard-normal draws, a Latin hypercube: each column's draws fall one in each
    1/n band of the distribution, in random order. Plain draws would make a coverage measure how
    lucky n rigs were as much as the intervals (of 30 plain draws, the share inside ±1σ is
    0.68 ± 0.085); stratified, each band is represented once and estimates stay unbiased
    (McKay, Beckman & Conover 1979)."""
    rng = np.random.default_rng(seed)
    u = np.stack([(rng.permutation(n) + rng.uniform(size=n)) / n for _ in range(dims)], axis=1)
    return ndtri(u)
