"""Radiometric calibration: sensor counts → radiance → BRDF.

The camera irradiance equation (seed lecture, "cameras see radiance"): the image-plane
irradiance is E_img = L · A_aperture / d_img² = L (π/4)(D/f)² cos⁴α = L π / (4 N²) on axis
(N = f-number; cos⁴α falls off across the field and is corrected by a flat field, not here).
A pixel of pitch p collecting for t seconds with quantum efficiency QE at wavelength λ counts
electrons e = QE · E_img p² t / (h c / λ), so

    L = e · (h c / λ) · 4 N² / (π · QE · p² · t).

The BRDF is f_r = L / E_surf with E_surf = I cos θ_i / r² (point source of intensity I W/sr at
distance r; seed: E = I (n̂·l̂)/r²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PLANCK_J_S", "LIGHT_SPEED_M_S", "CameraRadiometry", "surface_irradiance"]

PLANCK_J_S = 6.62607015e-34
LIGHT_SPEED_M_S = 299792458.0


@dataclass(frozen=True)
class CameraRadiometry:
    """The camera's stated radiometric description (run.toml [camera]). Without a stated
    quantum efficiency the conversion is nominal (QE = 1): fine for the reference-target method,
    where every common factor cancels; the certified method needs the stated value."""

    f_number: float
    pixel_pitch_m: float
    quantum_efficiency: float | None
    wavelength_m: float
    gain_e_per_dn: float
    black_level_dn: float
    white_level_dn: float
    read_noise_e: float

    @classmethod
    def from_description(cls, d: dict) -> CameraRadiometry:
        try:
            return cls(
                f_number=float(d["f_number"]),
                pixel_pitch_m=float(d["pixel_pitch_m"]),
                quantum_efficiency=(
                    float(d["quantum_efficiency"]) if "quantum_efficiency" in d else None
                ),
                wavelength_m=float(d["wavelength_m"]),
                gain_e_per_dn=float(d["gain_e_per_dn"]),
                black_level_dn=float(d["black_level_dn"]),
                white_level_dn=float(d["white_level_dn"]),
                read_noise_e=float(d.get("read_noise_e", 0.0)),
            )
        except KeyError as exc:
            raise ValueError(f"camera description lacks {exc.args[0]!r}") from None

    @property
    def radiance_per_electron_rate(self) -> float:
        """W m⁻² sr⁻¹ per (electron/s): the camera irradiance equation inverted."""
        photon_j = PLANCK_J_S * LIGHT_SPEED_M_S / self.wavelength_m
        qe = 1.0 if self.quantum_efficiency is None else self.quantum_efficiency
        return photon_j * 4.0 * self.f_number**2 / (math.pi * qe * self.pixel_pitch_m**2)

    def electrons(self, dn: np.ndarray) -> np.ndarray:
        return (np.asarray(dn, dtype=np.float64) - self.black_level_dn) * self.gain_e_per_dn

    def saturated(self, dn: np.ndarray) -> np.ndarray:
        # The ADC clips at white; treat the last code as clipped (its true value is unknown).
        return np.asarray(dn) >= self.white_level_dn - 0.5


def surface_irradiance(
    intensity_W_sr: np.ndarray | float, cos_theta_i: np.ndarray, distance_m: np.ndarray
) -> np.ndarray:
    """E = I cos θ_i / r² (W/m²)."""
    return np.asarray(intensity_W_sr) * np.maximum(cos_theta_i, 0.0) / np.square(distance_m)
