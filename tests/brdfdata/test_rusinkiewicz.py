"""Rusinkiewicz half/difference angles: definitions, round trips, the pole and grazing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brdfdata.directions import spherical_to_vector, uniform_hemisphere
from brdfdata.rusinkiewicz import from_half_diff, to_half_diff


def _angle(a, b):
    # angle between unit vectors via atan2(|a×b|, a·b): accurate near 0 and π
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def test_definitions_on_random_pairs():
    rng = np.random.default_rng(0)
    wi, wo = uniform_hemisphere(2000, rng), uniform_hemisphere(2000, rng)
    th, td, pd = to_half_diff(wi, wo)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    # θ_h is the angle between h and n̂; θ_d the angle between ω_i (or ω_o) and h
    np.testing.assert_allclose(th, _angle(h, np.array([0, 0, 1.0])), atol=1e-12)
    np.testing.assert_allclose(td, _angle(wi, h), atol=1e-12)
    np.testing.assert_allclose(td, _angle(wo, h), atol=1e-12)
    assert np.all((pd >= 0) & (pd < 2 * np.pi))


def test_round_trip_from_angles():
    rng = np.random.default_rng(1)
    th = rng.uniform(0, np.pi / 2, 1000)
    td = rng.uniform(0, np.pi / 2, 1000)
    pd = rng.uniform(0, 2 * np.pi, 1000)
    ph = rng.uniform(0, 2 * np.pi, 1000)
    wi, wo = from_half_diff(th, td, pd, ph)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1, atol=1e-14)
    th2, td2, pd2 = to_half_diff(wi, wo)
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-12)
    ok = (td > 1e-6) & (th > 1e-6)  # φ_d is undefined at θ_d = 0
    dphi = np.angle(np.exp(1j * (pd2 - pd)))
    np.testing.assert_allclose(dphi[ok], 0, atol=1e-10)


def test_round_trip_from_vectors_and_phi_h():
    rng = np.random.default_rng(2)
    wi, wo = uniform_hemisphere(1000, rng), uniform_hemisphere(1000, rng)
    th, td, pd = to_half_diff(wi, wo)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    ph = np.arctan2(h[:, 1], h[:, 0])
    wi2, wo2 = from_half_diff(th, td, pd, ph)
    np.testing.assert_allclose(wi2, wi, atol=1e-12)
    np.testing.assert_allclose(wo2, wo, atol=1e-12)


def test_pole_and_special_configurations():
    z = np.array([0.0, 0.0, 1.0])
    # normal incidence and viewing: everything zero, no NaN from the undefined azimuths
    th, td, pd = to_half_diff(z, z)
    assert (th, td, pd) == (0.0, 0.0, 0.0)
    # a mirror pair: h = n̂ exactly → θ_h = 0, θ_d = θ_i
    wi = spherical_to_vector(0.7, 0.3)
    wo = spherical_to_vector(0.7, 0.3 + np.pi)
    th, td, _ = to_half_diff(wi, wo)
    assert th == pytest.approx(0, abs=1e-15) and td == pytest.approx(0.7, abs=1e-14)
    # retro-reflection: θ_d = 0, θ_h = θ
    th, td, _ = to_half_diff(wi, wi)
    assert th == pytest.approx(0.7, abs=1e-14) and td == pytest.approx(0, abs=1e-15)
    # both grazing at opposite azimuths: θ_h = 0, θ_d → 90°
    g = spherical_to_vector(np.pi / 2 - 1e-9, 0.0)
    th, td, _ = to_half_diff(g, g * np.array([-1, -1, 1]))
    assert th == pytest.approx(0, abs=1e-15) and td == pytest.approx(np.pi / 2 - 1e-9, abs=1e-14)
    # inverse at the pole θ_h = 0: ω_o is the mirror of ω_i
    wi, wo = from_half_diff(0.0, 0.4, 1.0)
    np.testing.assert_allclose(wo, wi * np.array([-1, -1, 1]), atol=1e-15)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    st.floats(0, np.pi / 2),
    st.floats(0, 2 * np.pi),
    st.floats(0, np.pi / 2),
    st.floats(0, 2 * np.pi),
)
def test_round_trip_hypothesis(ti, pi, to, po):
    wi, wo = spherical_to_vector(ti, pi), spherical_to_vector(to, po)
    th, td, pd = to_half_diff(wi, wo)
    assert np.isfinite([th, td, pd]).all()
    h = wi + wo
    n = np.linalg.norm(h)
    if n < 1e-6:  # ω_i ≈ −ω_o (both on the horizon): h undefined
        return
    ph = np.arctan2(h[1], h[0])
    wi2, wo2 = from_half_diff(th, td, pd, ph)
    # the conditioning of h = (ω_i + ω_o)/|…| limits the round trip to ~1e-16/|ω_i + ω_o|
    np.testing.assert_allclose(wi2, wi, atol=1e-13 / n)
    np.testing.assert_allclose(wo2, wo, atol=1e-13 / n)
