"""EMVA 1288 camera sensor model: radiance image → digital numbers (DN).

Reference: EMVA Standard 1288 Release 4.0 (2021), §2 "Sensitivity, linearity and noise" (linear
camera model) and the camera irradiance equation (Horn, *Robot Vision*, eq. 10.2). Per pixel and
colour channel:

1. irradiance on the sensor     E = L · π / (4 N²)            [W m⁻²]  (N = f-number, on axis;
   the exact on-axis value is π L / (1 + 4N²); we use the paraxial form the calibration inverts)
   × cos⁴α off axis only if ``spec.vignetting`` (α = angle of the pixel's chief ray)
2. photons                      Φ = E · pitch² · t / (h c / λ)
3. mean electrons               μ_e = QE · Φ · (1 + PRNU_map) + dark · t
4. shot noise                   e ~ Poisson(μ_e)              (only if ``spec.noise``)
   dark offset                  e + DSNU_map                  (EMVA 1288's dark signal
   non-uniformity: an offset, either sign, the same in a dark frame as in a lit one. As a
   Poisson mean it had to be clipped at 0, so a dark frame read ~0.4 DN high of a lit frame's
   dark part on a 2 e⁻ DSNU, a bias only the simulator had, which the linearity measurement
   from the brackets read as a bend of −0.3 %.)
5. full well                    e = min(e, full_well)
   non-linearity                e · (1 + β e/full_well)      (only if ``spec.nonlinearity``)
6. read noise                   e + N(0, σ_read²)             (only if ``spec.noise``)
7. ADC                          DN = clip(round(black + e / K⁻¹), 0, 2^bits − 1)
   with K⁻¹ = ``gain_e_per_dn`` (electrons per DN)

With ``spec.bayer == "RGGB"`` the R/G/B channel of each CFA site is taken *before* the noise stages
(a real sensor measures one band per site), and the output is a single (H, W) mosaic.

Every stage runs only when the spec enables it, and each executed stage is recorded in
``Sensor.executed_stages`` (last capture) and ``Sensor.stage_counts`` (all captures), so a test can
prove a disabled effect never ran.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from simulator.scene import SensorSpec

__all__ = [
    "Sensor",
    "expected_dn",
    "expected_electrons",
    "cos4_vignetting",
    "bayer_select",
    "enabled_stages",
    "PLANCK_J_S",
    "LIGHT_SPEED_M_S",
    "STAGES",
]

PLANCK_J_S = 6.62607015e-34  # exact (SI 2019)
LIGHT_SPEED_M_S = 299_792_458.0  # exact

STAGES = (
    "irradiance",
    "vignetting",
    "photons",
    "bayer",
    "prnu",
    "dark_current",
    "shot_noise",
    "dsnu",
    "full_well",
    "nonlinearity",
    "read_noise",
    "adc",
)

# CFA site → RGB channel index for the 2×2 RGGB tile, [row % 2][col % 2].
_RGGB = np.array([[0, 1], [1, 2]])


def cos4_vignetting(shape: tuple[int, int], intrinsics: dict) -> np.ndarray:
    """cos⁴α per pixel (H, W) for a pinhole with OpenCV intrinsics (fx, fy, cx, cy)."""
    h, w = shape
    u = (np.arange(w) - intrinsics["cx"]) / intrinsics["fx"]
    v = (np.arange(h) - intrinsics["cy"]) / intrinsics["fy"]
    tan2 = u[None, :] ** 2 + v[:, None] ** 2
    return 1.0 / (1.0 + tan2) ** 2  # cos²α = 1/(1 + tan²α)


def bayer_select(planes: np.ndarray, pattern: str = "RGGB") -> np.ndarray:
    """(H, W, 3) → (H, W) mosaic taking the channel of each CFA site."""
    if pattern != "RGGB":
        raise ValueError(f"unsupported CFA pattern {pattern!r}")
    h, w = planes.shape[:2]
    idx = _RGGB[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    return np.take_along_axis(planes, idx[..., None], axis=-1)[..., 0]


def _photons_per_radiance(spec: SensorSpec, f_number: float, exposure_s: float) -> float:
    """Photons per pixel per unit radiance on axis: π/(4N²) · pitch² · t · λ/(h c)."""
    photon_energy_j = PLANCK_J_S * LIGHT_SPEED_M_S / spec.wavelength_m
    return np.pi / (4.0 * f_number**2) * spec.pixel_pitch_m**2 * exposure_s / photon_energy_j


def expected_electrons(
    radiance, exposure_s: float, spec: SensorSpec, f_number: float, intrinsics: dict | None = None
) -> np.ndarray:
    """Noise-free mean electrons (PRNU/DSNU averaged out, before full-well clipping)."""
    L = np.asarray(radiance, dtype=np.float64)
    phot = L * _photons_per_radiance(spec, f_number, exposure_s)
    if spec.vignetting:
        if not intrinsics:
            raise ValueError("vignetting is enabled: pass the camera intrinsics")
        v = cos4_vignetting(L.shape[:2], intrinsics)
        phot = phot * (v[..., None] if L.ndim == 3 else v)
    if spec.bayer and L.ndim == 3:
        phot = bayer_select(phot, spec.bayer)
    return spec.quantum_efficiency * phot + spec.dark_current_e_s * exposure_s


def expected_dn(
    radiance, exposure_s: float, spec: SensorSpec, f_number: float, intrinsics: dict | None = None
) -> np.ndarray:
    """Noise-free mean DN (float64), same layout as ``Sensor.capture`` (mosaic if Bayer).

    μ_DN = black + min(μ_e, full_well) / gain_e_per_dn, clipped to [0, 2^bits − 1]. (Rounding is
    unbiased on average once the noise exceeds ~0.5 DN; without noise it adds ≤ 0.5 DN.)
    """
    e = np.minimum(
        expected_electrons(radiance, exposure_s, spec, f_number, intrinsics), spec.full_well_e
    )
    dn = spec.black_level_dn + e / spec.gain_e_per_dn
    return np.clip(dn, 0.0, 2.0**spec.adc_bits - 1.0)


def enabled_stages(spec: SensorSpec) -> list[str]:
    """Stages a sensor with this spec runs, in order (what the effect planner reports)."""
    on = {
        "irradiance": True,
        "vignetting": spec.vignetting,
        "photons": True,
        "bayer": spec.bayer is not None,
        "prnu": spec.prnu > 0,
        "dark_current": spec.dark_current_e_s > 0,
        "dsnu": spec.dsnu_e > 0,
        "shot_noise": spec.noise,
        "full_well": True,
        "nonlinearity": spec.nonlinearity > 0,
        "read_noise": spec.noise and spec.read_noise_e > 0,
        "adc": True,
    }
    return [k for k in STAGES if on[k]]


class Sensor:
    """Seeded EMVA 1288 sensor. ``capture(radiance, exposure_s) -> uint16 DN``.

    The PRNU and DSNU maps are fixed-pattern: drawn once (from ``rng``) on the first capture of a
    given image shape and reused, as on a real sensor. ``rng`` may be a Generator or a seed.
    """

    def __init__(
        self,
        spec: SensorSpec,
        f_number: float,
        rng: np.random.Generator | int | None = 0,
        intrinsics: dict | None = None,
    ):
        if spec.vignetting and not intrinsics:
            raise ValueError("vignetting is enabled: pass the camera intrinsics")
        self.spec = spec
        self.f_number = float(f_number)
        # Anything with Generator's poisson/normal methods is accepted (tests pass a spy).
        self.rng = rng if hasattr(rng, "poisson") else np.random.default_rng(rng)
        self.intrinsics = intrinsics
        self.executed_stages: list[str] = []
        self.stage_counts: Counter[str] = Counter()
        self._fixed: dict[tuple, tuple[np.ndarray | None, np.ndarray | None]] = {}
        self._vig: dict[tuple, np.ndarray] = {}

    @property
    def white_level(self) -> int:
        return 2**self.spec.adc_bits - 1

    def enabled_stages(self) -> list[str]:
        """Stages this sensor runs, in order."""
        return enabled_stages(self.spec)

    def _ran(self, stage: str) -> None:
        self.executed_stages.append(stage)
        self.stage_counts[stage] += 1

    def _fixed_pattern(self, shape):
        if shape not in self._fixed:
            s = self.spec
            # Gaussian fixed-pattern maps: PRNU relative gain σ, DSNU offset σ in electrons.
            prnu = self.rng.normal(0.0, s.prnu, shape) if s.prnu > 0 else None
            dsnu = self.rng.normal(0.0, s.dsnu_e, shape) if s.dsnu_e > 0 else None
            self._fixed[shape] = (prnu, dsnu)
        return self._fixed[shape]

    def capture(self, radiance: np.ndarray, exposure_s: float) -> np.ndarray:
        """Radiance (H, W, 3) in W m⁻² sr⁻¹ → DN, uint16, (H, W, 3) or (H, W) mosaic."""
        s = self.spec
        self.executed_stages = []
        L = np.asarray(radiance, dtype=np.float64)
        if L.ndim != 3 or L.shape[-1] != 3:
            raise ValueError(f"radiance must be (H, W, 3), got {L.shape}")

        self._ran("irradiance")
        E = L * (np.pi / (4.0 * self.f_number**2))  # camera irradiance equation, W m⁻²
        if s.vignetting:
            self._ran("vignetting")
            key = L.shape[:2]
            if key not in self._vig:
                self._vig[key] = cos4_vignetting(key, self.intrinsics)
            E = E * self._vig[key][..., None]

        self._ran("photons")
        photon_energy_j = PLANCK_J_S * LIGHT_SPEED_M_S / s.wavelength_m
        photons = E * (s.pixel_pitch_m**2 * exposure_s / photon_energy_j)

        if s.bayer is not None:
            self._ran("bayer")
            photons = bayer_select(photons, s.bayer)

        mu = s.quantum_efficiency * photons
        prnu, dsnu = self._fixed_pattern(mu.shape)
        if prnu is not None:
            self._ran("prnu")
            mu = mu * (1.0 + prnu)
        if s.dark_current_e_s > 0:
            self._ran("dark_current")
            mu = mu + s.dark_current_e_s * exposure_s
        mu = np.maximum(mu, 0.0)

        if s.noise:
            self._ran("shot_noise")
            e = self.rng.poisson(mu).astype(np.float64)
        else:
            e = mu
        if dsnu is not None:
            self._ran("dsnu")
            e = e + dsnu
        self._ran("full_well")
        e = np.minimum(e, s.full_well_e)
        if s.nonlinearity > 0:
            self._ran("nonlinearity")
            e = e * (1.0 + s.nonlinearity * e / s.full_well_e)
        if s.noise and s.read_noise_e > 0:
            self._ran("read_noise")
            e = e + self.rng.normal(0.0, s.read_noise_e, e.shape)

        self._ran("adc")
        dn = np.rint(s.black_level_dn + e / s.gain_e_per_dn)
        return np.clip(dn, 0, self.white_level).astype(np.uint16)
