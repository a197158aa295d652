"""The model registry (issue 21 item 5): one dispatcher, aliases, named variants, options with
allowed values, one-line errors naming what is allowed, what `--model all` fits."""

from __future__ import annotations

import numpy as np
import pytest

from brdfdata.directions import uniform_hemisphere
from fitting import compare, models
from fitting.models import seed
from fitting.ngan import COOK_TORRANCE_OPTIONS


def test_every_entry_builds_with_its_defaults_and_declares_its_parts():
    assert models.names() == models.names()
    for name in models.names():
        e = models.entry(name)
        m = models.get(name)
        assert m.name == name  # variants report their own name
        assert e.summary and e.reference
        assert {"reciprocal", "energy_conserving", "isotropic"} <= set(m.flags)
        for o in e.options:
            assert o.default in o.allowed
        # a model's options rebuild it (what a fit JSON stores is enough to reload it)
        if e.base is None:
            assert models.get(name, **m.options).options == m.options
        d = models.describe(name)
        assert d["parameters"] == m.parameters and d["options"] == e.options


def test_aliases_and_variants():
    assert models.resolve("ts") == "torrance-sparrow"
    assert models.resolve("ts-anisotropic") == "torrance-sparrow-anisotropic"
    assert models.get("on").name == "oren-nayar"
    assert set(models.aliases().values()) <= set(models.names())
    # a variant is its base with options fixed — numerically identical
    rng = np.random.default_rng(0)
    wi, wo = uniform_hemisphere(200, rng), uniform_hemisphere(200, rng)
    p = {"kd": 0.2, "ks": 0.7, "m": 0.2, "f0": 0.05}
    ct = models.get("cook-torrance")
    assert ct.options == COOK_TORRANCE_OPTIONS
    np.testing.assert_array_equal(
        ct.evaluate(p, wi, wo),
        models.get("torrance-sparrow", **COOK_TORRANCE_OPTIONS).evaluate(p, wi, wo),
    )
    # a variant's free options stay choosable; its fixed ones cannot be changed
    assert models.get("heavy-tail", shadowing="v-cavity").options["shadowing"] == "v-cavity"
    with pytest.raises(ValueError, match="fixes distribution"):
        models.get("ts-ggx-smith", distribution="beckmann")
    models.get("ts-ggx-smith", distribution="ggx")  # restating a fixed value is fine


def test_errors_name_what_is_allowed():
    with pytest.raises(KeyError, match="unknown model 'cook'"):
        models.get("cook")
    with pytest.raises(ValueError, match="known: lambert"):
        models.resolve("nope")
    assert str(models.UnknownModelError("x y")) == "x y"  # no KeyError quotes
    with pytest.raises(ValueError) as exc:
        models.get("torrance-sparrow", anisotropy="0.5")
    msg = str(exc.value)
    assert "unknown option 'anisotropy'" in msg and "distribution: beckmann* | ggx" in msg
    assert "\n" not in msg
    with pytest.raises(ValueError, match="choose one of beckmann, ggx"):
        models.get("torrance-sparrow", distribution="phong")
    with pytest.raises(ValueError, match="takes no options"):
        models.get("lambert", fresnel="none")
    with pytest.raises(ValueError, match="already registered"):
        models.register(models.ModelEntry("ward", seed.Lambert))


def _in_plane(n: int = 200):
    """Directions of an in-plane (isotropic) measurement: one sample orientation."""
    rng = np.random.default_rng(3)
    ti, to = rng.uniform(0.05, 1.3, n), rng.uniform(0.05, 1.3, n)
    wi = np.stack([np.sin(ti), np.zeros(n), np.cos(ti)], 1)
    wo = np.stack([-np.sin(to), np.zeros(n), np.cos(to)], 1)
    return wi, wo


def test_model_all_fits_every_registered_model_or_says_why_not():
    opts = {"shadowing": "smith-rational", "fresnel": "none"}
    for directions, anisotropic_skipped in ((_in_plane(), True), (None, False)):
        cands, skipped = compare.candidates("all", opts, directions=directions)
        # every registered model and variant is either fitted or listed with its reason
        assert sorted([c.model for c in cands] + [s.model for s in skipped]) == sorted(
            models.names()
        )
        why = {s.model: s.reason for s in skipped}
        # these options make torrance-sparrow the named variant ts-beckmann-smith: fitted once
        assert why["ts-beckmann-smith"] == "the same model as torrance-sparrow with these options"
        aniso = {n for n in models.names() if "orientations" in models.entry(n).needs}
        assert aniso and (aniso <= set(why)) == anisotropic_skipped
        for n in aniso & set(why):
            assert "of the 4 sample orientations" in why[n]
    # several names by comma (aliases resolve), each taking the options that apply to it
    cands, _ = compare.candidates("lambert, ts", {"fresnel": "none"})
    assert [(c.model, c.options) for c in cands] == [
        ("lambert", {}),
        ("torrance-sparrow", {"fresnel": "none"}),
    ]
    assert models.applicable_options("lambert", {"fresnel": "none"}) == {}
    assert models.applicable_options("torrance-sparrow", {"fresnel": "none", "x": "1"}) == {
        "fresnel": "none"
    }
    cands, _ = compare.candidates("all", {"fresnel": "none"})
    assert [c.model for c in cands] == models.names()
    assert {c.label: c.options for c in cands}["torrance-sparrow"] == {"fresnel": "none"}
    # a single model by variant or alias; unknown options fail with the allowed ones
    assert compare.candidates("ts-ggx-smith")[0][0].model == "ts-ggx-smith"
    with pytest.raises(ValueError, match="unknown option 'anisotropy'"):
        compare.candidates("torrance-sparrow", {"anisotropy": "0.5"})
    c, _ = compare.candidates("torrance-sparrow-anisotropic", shared=("alpha_x", "alpha_y", "phi0"))
    assert c[0].shared == ("alpha_x", "alpha_y", "phi0")
