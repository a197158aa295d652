"""Fresnel reflectance against the published/independent numbers of docs/design.md §6."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize_scalar

from fitting.models import fresnel

COS = lambda deg: np.cos(np.radians(deg))  # noqa: E731


# docs/design.md §6 gives these to 4–5 decimals: the tolerance is half a unit in the last digit.
@pytest.mark.parametrize(
    ("deg", "expected", "tol"),
    [
        (0.0, 0.0400, 5e-5),
        (45.0, 0.05024, 5e-6),
        (60.0, 0.08919, 5e-6),
        (75.0, 0.25306, 5e-6),
        (85.0, 0.61280, 5e-6),
    ],
)
def test_dielectric_table_eta_1_5(deg, expected, tol):
    assert abs(fresnel.dielectric(COS(deg), 1.5) - expected) <= tol


def test_dielectric_s_and_p_at_45_deg():
    rs, rp = fresnel.dielectric_sp(COS(45.0), 1.5)
    assert abs(rs - 0.09201) <= 5e-6
    assert abs(rp - 0.00847) <= 5e-6


def test_brewster_angle():
    # R_p vanishes at Brewster's angle atan(1.5) = 56.310°: locate the minimum numerically.
    res = minimize_scalar(
        lambda deg: fresnel.dielectric_sp(COS(deg), 1.5)[1],
        bounds=(40, 70),
        method="bounded",
        options={"xatol": 1e-9},
    )
    assert abs(res.x - 56.310) <= 5e-4
    assert fresnel.dielectric_sp(COS(np.degrees(np.arctan(1.5))), 1.5)[1] < 1e-28


def test_cosine_weighted_hemispherical_average():
    # 2 ∫ F(θ) cos θ sin θ dθ = 0.09178 (docs/design.md §6), to its rounding.
    val = (
        2
        * quad(
            lambda t: fresnel.dielectric(np.cos(t), 1.5) * np.cos(t) * np.sin(t),
            0,
            np.pi / 2,
            epsabs=1e-12,
        )[0]
    )
    assert abs(val - 0.09178) <= 5e-6


def test_schlick_is_not_the_exact_value():
    assert abs(fresnel.schlick(COS(60.0), 0.04) - 0.0700) <= 5e-5
    assert abs(fresnel.schlick(COS(60.0), 0.04) - fresnel.dielectric(COS(60.0), 1.5)) > 0.015


@pytest.mark.parametrize(
    ("eta", "k", "f0"),
    [
        ((0.1431, 0.3750, 1.4425), (3.9832, 2.3857, 1.6032), (0.9667, 0.8022, 0.3240)),  # Au
        ((1.6575, 0.8804, 0.5212), (9.2239, 6.2695, 4.8370), (0.9280, 0.9178, 0.9189)),  # Al
        ((0.2004, 0.9240, 1.1022), (3.9129, 2.4528, 2.1422), (0.9521, 0.6197, 0.5106)),  # Cu
    ],
)
def test_conductor_f0_table(eta, k, f0):
    got = fresnel.conductor(1.0, np.array(eta), np.array(k))
    np.testing.assert_allclose(got, f0, atol=1e-4)


def test_conductor_with_k_zero_is_the_dielectric_including_tir():
    # Two different formulas (complex vs real arithmetic) must agree; η < 1 exercises TIR.
    c = np.linspace(0.0, 1.0, 401)
    for eta in (0.6, 1 / 1.5, 1.0, 1.5, 3.0):
        np.testing.assert_allclose(
            fresnel.conductor(c, eta, 0.0), fresnel.dielectric(c, eta), rtol=1e-12, atol=1e-15
        )


def test_total_internal_reflection_and_reciprocity_of_fresnel():
    eta = 1 / 1.5
    crit = np.arcsin(eta)
    theta = np.linspace(crit + 1e-9, np.pi / 2, 50)
    np.testing.assert_array_equal(fresnel.dielectric(np.cos(theta), eta), 1.0)
    # Below the critical angle F(θ_i; 1/η) = F(θ_t; η) (Stokes relations), θ_t from Snell.
    theta = np.linspace(0, crit - 1e-3, 50)
    theta_t = np.arcsin(np.sin(theta) / eta)
    np.testing.assert_allclose(
        fresnel.dielectric(np.cos(theta), eta), fresnel.dielectric(np.cos(theta_t), 1.5), rtol=1e-12
    )


def test_limits_eta_one_grazing_and_large_k():
    c = np.linspace(1e-6, 1.0, 100)
    np.testing.assert_array_equal(fresnel.dielectric(c, 1.0), 0.0)
    assert fresnel.dielectric(0.0, 1.5) == 1.0
    assert fresnel.conductor(0.0, 0.2, 3.0) == pytest.approx(1.0, abs=1e-15)
    big = fresnel.conductor(c, 1.0, 50.0)
    assert (
        np.all(np.isfinite(big)) and np.all(big <= 1.0) and np.all(big > 0.97)
    )  # pseudo-Brewster dip ≈ 0.98
    # F0 for k = 50, η = 1: (0 + 2500)/(4 + 2500)
    assert fresnel.conductor(1.0, 1.0, 50.0) == pytest.approx(2500 / 2504, rel=1e-13)


def test_broadcasting():
    c = np.linspace(0, 1, 7)
    eta = np.array([[1.2], [1.5], [2.0]])
    assert fresnel.dielectric(c, eta).shape == (3, 7)
    assert fresnel.conductor(c, eta, np.array([[1.0], [2.0], [3.0]])).shape == (3, 7)
    assert fresnel.schlick(c, eta * 0.01).shape == (3, 7)
    np.testing.assert_allclose(fresnel.dielectric(c, eta)[1], fresnel.dielectric(c, 1.5))
