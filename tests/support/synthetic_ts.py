"""A Torrance-Sparrow samples table made by an independent plain-numpy reference (not
fitting.models): the truth for the fitting tests that recover known parameters."""

from __future__ import annotations

import numpy as np

from brdfdata.directions import spherical_to_vector
from brdfdata.samples import SampleTable

__all__ = ["TRUTH", "ts_reference", "synthetic"]


def ts_reference(kd, ks, m, wi, wo):
    """Lambert + Beckmann lobe, V-cavity G, F = 1, written from docs/design.md §5 independently of
    fitting.models: f = kd/π + ks · D_norm G / (4 cos θ_i cos θ_o),
    D_norm = exp(−tan²θ_h/m²) / (π m² cos⁴θ_h)."""
    ci, co = wi[:, 2], wo[:, 2]
    h = wi + wo
    h = h / np.linalg.norm(h, axis=1)[:, None]
    ch = h[:, 2]
    vh = np.sum(wo * h, axis=1)
    tan2 = (1.0 - ch**2) / ch**2
    d = np.exp(-tan2 / m**2) / (np.pi * m**2 * ch**4)
    g = np.minimum(1.0, np.minimum(2 * ch * co / vh, 2 * ch * ci / vh))
    return kd / np.pi + ks * d * g / (4 * ci * co)


TRUTH = {"kd": {"R": 0.5, "G": 0.3, "B": 0.2}, "ks": {"R": 0.8, "G": 0.6, "B": 0.4}}


def synthetic(m: float, n: int, rng: np.random.Generator, rel_noise=0.03) -> SampleTable:
    cols = {k: [] for k in ("ti", "pi", "to", "po", "ch", "f", "s")}
    for c in "RGB":
        ti = rng.uniform(0.05, 1.3, n)
        to = rng.uniform(0.05, 1.3, n)
        # Half the samples near the specular plane so the lobe is well sampled.
        po = np.where(
            np.arange(n) % 2 == 0, np.pi + rng.uniform(-0.3, 0.3, n), rng.uniform(0, 2 * np.pi, n)
        )
        wi = spherical_to_vector(ti, np.zeros(n))
        wo = spherical_to_vector(to, po)
        f = ts_reference(TRUTH["kd"][c], TRUTH["ks"][c], m, wi, wo)
        sig = rel_noise * f + 1e-3
        for k, v in zip(
            cols,
            (ti, np.zeros(n), to, po, np.full(n, c), f + sig * rng.standard_normal(n), sig),
            strict=True,
        ):
            cols[k].append(v)
    c = {k: np.concatenate(v) for k, v in cols.items()}
    return SampleTable(
        c["ti"], c["pi"], c["to"], c["po"], c["ch"], c["f"], c["s"], np.zeros(c["f"].size, np.int32)
    )
