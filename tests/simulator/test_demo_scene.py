"""`gonio demo --scene S` fits the model the scene's material is, or says it cannot (issue 18
item 4). The choice is unit-tested on scene files; one CLI-level check runs `gonio demo` in
process up to the spine (acquisition is replaced by a stop), so it takes seconds, not the
minutes of a full demo (tests/gonio/test_demo_e2e.py runs that once for the default scene).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from fitting import models
from gonio.backends import load_scene
from gonio.pipeline import demo_fit_choice
from simulator.scene import RoughPlasticMaterial
from tests.support.paths import REPO

GGX = REPO / "tests" / "scenes" / "ggx_blend.toml"


def test_ggx_scene_fits_ggx() -> None:
    opts, line = demo_fit_choice(load_scene(GGX), quick=True)
    assert opts.model == "torrance-sparrow"
    # Mitsuba's GGX roughconductor: the exact separable Smith G1 and, with conductor "none",
    # F ≡ 1 (simulator.materials, docs/design.md §7).
    assert dict(opts.model_options) == {
        "distribution": "ggx",
        "shadowing": "smith",
        "fresnel": "none",
    }
    models.get(opts.model, **opts.model_options)  # a valid registered option set
    assert "ggx" in line and "no parameter truth" not in line


def test_default_demo_scene_keeps_the_beckmann_model() -> None:
    opts, _ = demo_fit_choice(load_scene(REPO / "configs" / "scenes" / "demo.toml"), quick=True)
    assert opts.model_options["distribution"] == "beckmann"
    assert opts.model_options["shadowing"] == "smith-rational"
    assert opts.model_options["fresnel"] == "none"


def test_model_scene_fits_its_own_model() -> None:
    scene = load_scene(REPO / "configs" / "scenes" / "model_ts.toml")
    opts, _ = demo_fit_choice(scene, quick=True)
    assert opts.model == "torrance-sparrow"
    assert dict(opts.model_options) == dict(scene.material.options)


def test_a_material_without_a_model_says_so() -> None:
    base = load_scene(GGX)
    scene = base.model_copy(update={"material": RoughPlasticMaterial()})
    opts, line = demo_fit_choice(scene, quick=True)
    assert opts.model == "torrance-sparrow"  # the demo's own model, named in the line
    assert "roughplastic" in line and "no parameter truth exists" in line


class _Stop(Exception):
    pass


def test_cli_demo_prints_the_choice(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import gonio.pipeline as pipeline
    from gonio.cli import app

    seen = {}

    def stop(run_dir, spec):
        seen["fit"] = spec.fit
        raise _Stop

    monkeypatch.setattr(pipeline, "run_spine", stop)
    res = CliRunner().invoke(
        app, ["demo", "--quick", "--scene", str(GGX), "--out", str(tmp_path / "r")]
    )
    assert isinstance(res.exception, _Stop), res.output
    assert "fitting torrance-sparrow (distribution=ggx" in res.output
    assert seen["fit"].model_options["distribution"] == "ggx"
