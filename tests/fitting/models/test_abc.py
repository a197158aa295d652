"""The ABC lobe (fitting.models.abc_lobe) against its published form, written here from the paper's
quantities (Löw et al. 2012, §4: S(f) = A / (1 + B f²)^C, f the distance in the projected disk
between the mirror direction ω_r of ω_i and ω_o) rather than from the module's expressions."""

from __future__ import annotations

import numpy as np
import pytest

from brdfdata.directions import spherical_to_vector
from fitting import models

RNG = np.random.default_rng(11)
N = 5000
# up to 89°: grazing pairs included
WI = spherical_to_vector(RNG.uniform(0, np.radians(89), N), RNG.uniform(0, 2 * np.pi, N))
WO = spherical_to_vector(RNG.uniform(0, np.radians(89), N), RNG.uniform(0, 2 * np.pi, N))


def _low_abc(wi, wo, a, b, c, p=2.0):
    """Löw et al.'s smooth-surface lobe from its definition: reflect ω_i about the normal,
    project both directions on the surface plane, A / (1 + B ‖ω_r,p − ω_o,p‖^p)^C."""
    wr = wi * np.array([-1.0, -1.0, 1.0])
    f = np.linalg.norm(wr[:, :2] - wo[:, :2], axis=1)
    return a / (1.0 + b * f**p) ** c


@pytest.mark.parametrize("exponent", ["2", "3"])
def test_lobe_is_the_published_abc_form(exponent: str) -> None:
    # k = 0 (no obliquity) and q = 1e-3 at its lower bound times (1 − ω·h)⁵ ≤ 1: F̂ − 1 ≤ 1e-3;
    # with q = 0 exactly the lobe must be Löw's ABC form with B = (2^(1/C) − 1)/w^p to
    # rounding (1e-12 relative: a few operations in double precision).
    p = float(exponent)
    model = models.get("abc", exponent=exponent)
    for w, c in ((0.05, 0.7), (0.3, 2.5), (1.2, 15.0)):
        params = {"kd": 0.0, "ks": 2.0, "w": w, "C": c, "q": 0.0, "k": 0.0}
        b = (2.0 ** (1.0 / c) - 1.0) / w**p
        ref = _low_abc(WI, WO, 2.0, b, c, p)
        for backend in ("numba", "numpy"):
            got = model.evaluate(params, WI, WO, backend=backend)
            assert np.max(np.abs(got / ref - 1.0)) < 1e-12, (backend, w, c)


def test_half_width_fresnel_and_obliquity() -> None:
    model = models.get("abc")
    # at d = w the lobe is ks/2 whatever C (the parametrisation's definition)
    ti = np.radians(40.0)
    wi = spherical_to_vector(ti, 0.0)[None]
    for c in (0.1, 1.0, 10.0):
        w = 0.2
        # ω_o in the plane of incidence with ‖ω_r,p − ω_o,p‖ = w: sin θ_o = sin θ_i − w
        wo = spherical_to_vector(np.arcsin(np.sin(ti) - w), np.pi)[None]
        f = model.evaluate({"kd": 0.0, "ks": 1.0, "w": w, "C": c, "q": 0.0, "k": 0.0}, wi, wo)
        assert f[0] == pytest.approx(0.5, rel=1e-12)
    # F̂ = 1 + q (1 − ω_i·h)⁵ and the obliquity (cos θ_i cos θ_o)^k multiply the lobe
    params = {"kd": 0.0, "ks": 1.0, "w": 0.4, "C": 1.0, "q": 7.0, "k": 1.3}
    base = dict(params, q=0.0, k=0.0)
    h = (WI + WO) / np.linalg.norm(WI + WO, axis=1)[:, None]
    cos_d = np.sum(WI * h, axis=1)
    expect = (1 + 7.0 * (1 - cos_d) ** 5) * (WI[:, 2] * WO[:, 2]) ** 1.3
    ratio = model.evaluate(params, WI, WO) / model.evaluate(base, WI, WO)
    assert np.max(np.abs(ratio / expect - 1.0)) < 1e-10  # (1 − cos)⁵ near 0 loses ~1e-11
    # log f in log space, and the diffuse term adds kd/π
    p = dict(params, kd=0.3)
    assert np.allclose(model.log_evaluate(p, WI, WO), np.log(model.evaluate(p, WI, WO)), 0, 1e-12)
    diff = model.evaluate(p, WI, WO) - model.evaluate(params, WI, WO)
    assert np.allclose(diff, 0.3 / np.pi, rtol=0, atol=1e-12)
