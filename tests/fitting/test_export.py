"""Mitsuba export of a fit: the material Mitsuba loads (its own BSDF code, or the registered
Python BSDF) evaluates to the fitted model's f_r.

Ground truth on one side is Mitsuba's eval (float32, its own implementation of diffuse,
roughconductor and blendbsdf); on the other, fitting.models.evaluate (float64). Tolerance
1e-4 relative: float32 carries ~6e-8 relative rounding per operation and these BSDFs chain
a few dozen operations (exp, sqrt, division), so agreement is expected near 1e-6; 1e-4 leaves
room without hiding a wrong factor (the smallest real mistake — e.g. a missing Fresnel or
a wrong blend weight — changes f_r by percents).
"""

from __future__ import annotations

import json

import mitsuba as mi
import numpy as np
import pytest

from fitting import models
from fitting.export import material_dict, material_xml, write_material_xml


@pytest.fixture(scope="module", autouse=True)
def variant() -> str:
    from simulator.materials import register_model_bsdf
    from simulator.variant import ensure_variant

    name = ensure_variant()
    register_model_bsdf()
    return name


def _fit(model: str, options: dict, params: dict, channels=("R", "G", "B")) -> dict:
    """A fit JSON dict: list values are per channel (kd_R…), scalars shared (m)."""
    out = {}
    for k, v in params.items():
        if isinstance(v, list):
            for c, x in zip(channels, v, strict=True):
                out[f"{k}_{c}"] = {"median": x, "map": x, "unit": "1"}
        else:
            out[k] = {"median": v, "map": v, "unit": "1"}
    out["discrepancy"] = {"median": 0.01, "map": 0.01, "unit": "1"}
    return {"model": model, "options": options, "channels": list(channels), "parameters": out}


def _directions(rng, n):
    # cos θ ≥ 0.15: away from grazing, where float32 cos θ_o in Mitsuba's division loses digits.
    ct = rng.uniform(0.15, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct**2)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=1)


def _mitsuba_f(bsdf, wi, wo) -> np.ndarray:
    """f_r(ω_i to light, ω_o to camera) per channel (N, 3): Mitsuba eval / cos θ_i."""
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2]))
    return np.stack([np.asarray(v[c], dtype=np.float64) for c in range(3)], 1) / wi[:, 2:3]


def _model_f(model, options, params, wi, wo, channels=("R", "G", "B")) -> np.ndarray:
    m = models.get(model, **options)
    cols = []
    for c in range(3):
        p = {}
        for k, v in params.items():
            if isinstance(v, list):
                p[k] = v[c] if len(channels) == 3 else float(np.mean(v))
            else:
                p[k] = v
        cols.append(m.evaluate(p, wi, wo))
    return np.stack(cols, 1)


CASES = [
    ("lambert", {}, {"kd": [0.2, 0.5, 0.7]}, "diffuse"),
    (
        "torrance-sparrow",
        {"shadowing": "smith-rational", "fresnel": "none"},
        {"kd": [0.1, 0.2, 0.3], "ks": [0.3, 0.5, 0.6], "m": 0.2},
        "blendbsdf",
    ),
    (
        "torrance-sparrow",
        {"shadowing": "smith-rational", "fresnel": "conductor", "distribution": "ggx"},
        {"kd": [0.0, 0.0, 0.0], "ks": [0.9, 1.0, 0.8], "m": 0.3, "eta": 0.2, "k": 3.0},
        "roughconductor",
    ),
    (
        "torrance-sparrow",
        {"shadowing": "smith-rational", "fresnel": "conductor"},
        {"kd": [0.05, 0.1, 0.2], "ks": [0.5, 0.6, 0.7], "m": 0.05, "eta": 0.3, "k": 2.5},
        "blendbsdf",
    ),
    (  # dielectric Fresnel exported as a conductor with k = 0
        "torrance-sparrow",
        {"shadowing": "smith-rational", "fresnel": "dielectric"},
        {"kd": [0.3, 0.4, 0.5], "ks": [0.4, 0.3, 0.2], "m": 0.15, "ior": 1.6},
        "blendbsdf",
    ),
    (  # kd + ks > 1: no valid blend weight → Python BSDF
        "torrance-sparrow",
        {"shadowing": "smith-rational", "fresnel": "none"},
        {"kd": [0.5, 0.6, 0.7], "ks": [0.8, 0.9, 1.2], "m": 0.1},
        "gonio_model",
    ),
    ("blinn-phong", {}, {"kd": [0.1, 0.2, 0.3], "ks": [0.3, 0.5, 0.6], "n": 50.0}, "gonio_model"),
    ("phong", {}, {"kd": [0.1, 0.2, 0.3], "ks": [3.0, 5.0, 6.0], "n": 20.0}, "gonio_model"),
    (  # the seed form (v-cavity G): no Mitsuba built-in
        "torrance-sparrow",
        {},
        {"kd": [0.1, 0.2, 0.3], "ks": [0.3, 0.5, 0.6], "m": 0.2, "ior": 1.6},
        "gonio_model",
    ),
]


@pytest.mark.parametrize(("model", "options", "params", "plugin"), CASES)
def test_exported_material_matches_the_model(model, options, params, plugin) -> None:
    fit = _fit(model, options, params)
    d = material_dict(fit)
    assert d["type"] == plugin
    rng = np.random.default_rng(7)
    wi, wo = _directions(rng, 400), _directions(rng, 400)
    got = _mitsuba_f(mi.load_dict(d), wi, wo)
    want = _model_f(model, options, params, wi, wo)
    assert np.all(want > 0)
    rel = np.abs(got - want) / want
    assert rel.max() < 1e-4, rel.max()
    # The XML is the same material.
    got_xml = _mitsuba_f(mi.load_string(material_xml(fit)), wi, wo)
    np.testing.assert_array_equal(got_xml, got)


def test_single_channel_fit_exports_grey() -> None:
    params = {"kd": [0.25], "ks": [0.4], "m": 0.3}
    fit = _fit(
        "torrance-sparrow", {"shadowing": "smith-rational", "fresnel": "none"}, params, ("Y",)
    )
    d = material_dict(fit)
    assert d["bsdf_0_diffuse"]["reflectance"]["value"] == pytest.approx([0.25 / 0.6] * 3)
    rng = np.random.default_rng(1)
    wi, wo = _directions(rng, 100), _directions(rng, 100)
    got = _mitsuba_f(mi.load_dict(d), wi, wo)
    m = models.get("torrance-sparrow", shadowing="smith-rational", fresnel="none")
    want = m.evaluate({"kd": 0.25, "ks": 0.4, "m": 0.3}, wi, wo)
    assert np.max(np.abs(got - want[:, None]) / want[:, None]) < 1e-4


def test_python_bsdf_spec_names_the_model(tmp_path) -> None:
    fit = _fit("blinn-phong", {}, {"kd": [0.1, 0.1, 0.1], "ks": [0.3, 0.5, 0.6], "n": 50.0})
    spec = json.loads(material_dict(fit)["spec"])
    assert spec["model"] == "blinn-phong"
    assert spec["parameters"]["kd"] == 0.1  # equal channels collapse to a scalar
    assert spec["parameters"]["ks"] == [0.3, 0.5, 0.6]
    assert "discrepancy" not in spec["parameters"]
    assert "register_model_bsdf" in material_xml(fit)  # the in-process XML needs the plugin
    # On disk the export is for plain Mitsuba: a tabulated fallback
    # (tests/fitting/test_export_builtin.py).
    path = write_material_xml(fit, tmp_path / "m.xml")
    assert 'type="measured"' in path.read_text() and (tmp_path / "m.bsdf").is_file()


def test_preview_colour_follows_the_material() -> None:
    """A reddish Lambertian sphere renders red-dominant at its centre."""
    import io

    from PIL import Image

    from simulator.preview import preview_png

    png = preview_png(_fit("lambert", {}, {"kd": [0.8, 0.2, 0.1]}), size_px=64, spp=16)
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    r, g, b = a[28:36, 28:36].reshape(-1, 3).mean(axis=0)
    assert r > g > b
