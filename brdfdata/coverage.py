"""Which parts of the hemisphere a model needs, and which a set of direction pairs left empty.

Each registered model names the regions its parameters are determined by
(``ModelEntry.needs`` of fitting.models, whose ``model_coverage`` calls this module);
:func:`coverage_report` counts the pairs of a plan (or of measured samples) in each region and
says which are empty or too sparse. Regions
(angles in degrees at the edges, radians inside):

specular      θ_h ≤ 5°: the mirror lobe's peak (h the half vector, θ_h from the normal)
off-specular  5° < θ_h ≤ 35°: a lobe's flanks and tail (width, tail exponent γ, a 2nd lobe)
grazing       max(θ_i, θ_o) ≥ 70°: Fresnel's rise and rough-diffuse flattening
retro         angle(ω_i, ω_o) ≤ 15°: the retro-reflection peak (the reported *gap* is the
              smallest light–camera angle the pairs reach, set by the rig's occlusion)
orientations  the half vector's azimuth φ_h mod 180° among lobe pairs (1° ≤ θ_h ≤ 15°, inside
              a glossy lobe of α ≲ 0.25), in 8 bins of 22.5° centred on multiples of 22.5°,
              a bin counting when it holds ≥ 3 pairs: an anisotropic lobe (α_x, α_y, φ₀)
              needs ≥ 4 bins, i.e. the sample measured in ≥ 4 orientations
out-of-plane  |Δφ| not within 2° of 0° or 180°
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "REGIONS",
    "MIN_PAIRS",
    "MIN_ORIENTATION_BINS",
    "RegionCoverage",
    "CoverageReport",
    "coverage_report",
]

REGIONS = ("specular", "off-specular", "grazing", "retro", "orientations", "out-of-plane")
#: Fewer pairs than this in a needed region is "sparse" (0 is "empty").
MIN_PAIRS = 8
#: Distinct 22.5° bins of φ_h mod 180° an anisotropic model needs.
MIN_ORIENTATION_BINS = 4
_ORIENTATION_BINS = 8


@dataclass(frozen=True)
class RegionCoverage:
    """One region: how many pairs fall in it (bins for "orientations") and the verdict."""

    region: str
    count: int
    needed: int
    status: str  # "ok", "sparse" or "empty"


@dataclass(frozen=True)
class CoverageReport:
    """Per-region coverage of a set of pairs; ``retro_gap_deg`` is the smallest angle between
    ω_i and ω_o among the pairs (how close to the light the camera got)."""

    regions: tuple[RegionCoverage, ...]
    retro_gap_deg: float
    n_pairs: int

    @property
    def missing(self) -> list[str]:
        """Needed regions that are empty or sparse."""
        return [r.region for r in self.regions if r.status != "ok"]

    def lines(self) -> list[str]:
        """One line per region, for `gonio plan` and the report."""
        out = []
        for r in self.regions:
            unit = "orientation bins" if r.region == "orientations" else "pairs"
            extra = f", gap {self.retro_gap_deg:.2f} deg" if r.region == "retro" else ""
            out.append(f"{r.region}: {r.count} {unit} (need ≥ {r.needed}{extra}): {r.status}")
        return out


def _pair_angles(wi: np.ndarray, wo: np.ndarray) -> dict[str, np.ndarray]:
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    s = wi + wo
    rho = np.hypot(s[:, 0], s[:, 1])
    theta_h = np.arctan2(rho, s[:, 2])
    phi_h = np.mod(np.arctan2(s[:, 1], s[:, 0]), np.pi)
    sep = np.arctan2(np.linalg.norm(np.cross(wi, wo), axis=1), np.sum(wi * wo, axis=1))
    theta_i = np.arctan2(np.hypot(wi[:, 0], wi[:, 1]), wi[:, 2])
    theta_o = np.arctan2(np.hypot(wo[:, 0], wo[:, 1]), wo[:, 2])
    dphi = np.mod(np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0]), 2 * np.pi)
    defined = (np.hypot(wi[:, 0], wi[:, 1]) > 1e-9) & (np.hypot(wo[:, 0], wo[:, 1]) > 1e-9)
    return {
        "theta_h": theta_h,
        "phi_h": phi_h,
        "sep": sep,
        "theta_max": np.maximum(theta_i, theta_o),
        "dphi": dphi,
        "azimuth_defined": defined,
    }


def _count(region: str, a: dict[str, np.ndarray]) -> int:
    d = np.radians
    if region == "specular":
        return int(np.sum(a["theta_h"] <= d(5.0)))
    if region == "off-specular":
        return int(np.sum((a["theta_h"] > d(5.0)) & (a["theta_h"] <= d(35.0))))
    if region == "grazing":
        return int(np.sum(a["theta_max"] >= d(70.0)))
    if region == "retro":
        return int(np.sum(a["sep"] <= d(15.0)))
    if region == "orientations":
        lobe = (a["theta_h"] >= d(1.0)) & (a["theta_h"] <= d(15.0))
        # centred bins: φ_h = 0 and φ_h → 180° (the same slope direction) share bin 0
        bins = np.rint(a["phi_h"][lobe] / (np.pi / _ORIENTATION_BINS)).astype(int)
        counts = np.bincount(bins % _ORIENTATION_BINS, minlength=_ORIENTATION_BINS)
        return int(np.sum(counts >= 3))
    if region == "out-of-plane":
        dp = np.degrees(a["dphi"])
        near = (np.minimum(dp, 360.0 - dp) <= 2.0) | (np.abs(dp - 180.0) <= 2.0)
        return int(np.sum(a["azimuth_defined"] & ~near))
    raise ValueError(f"unknown coverage region {region!r}; regions: {', '.join(REGIONS)}")


def coverage_report(needs: Iterable[str], wi, wo) -> CoverageReport:
    """Coverage of the pairs (ω_i, ω_o) (each (N, 3), sample frame) in each region of
    ``needs`` (see the module docstring for the regions and thresholds)."""
    a = _pair_angles(wi, wo)
    rows = []
    for region in needs:
        count = _count(region, a)
        needed = MIN_ORIENTATION_BINS if region == "orientations" else MIN_PAIRS
        status = "empty" if count == 0 else ("sparse" if count < needed else "ok")
        rows.append(RegionCoverage(region, count, needed, status))
    gap = float(np.degrees(a["sep"].min())) if a["sep"].size else float("nan")
    return CoverageReport(tuple(rows), gap, int(a["sep"].size))
