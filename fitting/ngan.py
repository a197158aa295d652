"""Published analytic fits of the MERL materials (Ngan, Durand & Matusik 2005).

Ngan, A., Durand, F., Matusik, W. "Experimental Analysis of BRDF Models", EGSR 2005. The fitted
parameters are read from the ``ngan_<model>.fit`` tables distributed with the BRDF benchmark
*bbm* (bsdfbenchmark/bbm, ``fits/``; see data/README.md for provenance). Each line is

    <material> = Aggregate(Lambertian(albedo = [r, g, b]), Ngan<Model>(key = value, ...))

with a value either a number or an ``[r, g, b]`` list. The parameter meaning is that of bbm's
``include/bsdfmodel/ngan.h`` (which the fits were exported from), not of our models, hence the
mapping below.

Cook-Torrance (bbm ``NganCookTorrance``): the Lambertian plus
    f_spec = albedo · D · G · F / (π cos θ_i cos θ_o)                      (bbm microfacet_n::Cook)
with D the π-normalised Beckmann NDF exp(−tan²θ_h/m²)/(π m² cos⁴θ_h), m = ``roughness``
(bbm ``ndf::beckmann`` with Normalize = true); G the V-groove min{1, 2 cos θ_h cos θ_i/(ω_i·h),
2 cos θ_h cos θ_o/(ω_o·h)} (Torrance & Sparrow 1967); and F Schlick's F₀ + (1 − F₀)(1 − ω·h)⁵
where F₀ = ``eta`` — bbm stores Ngan's Fresnel parameter as a *normal-incidence reflectance*
(``ior::reflectance``), not an index of refraction (docs/design.md §6: nickel F₀ = 0.733).

Our ``torrance-sparrow`` (fitting.models) is f = kd/π + ks · D · G · F / (4 cos θ_i cos θ_o)
with the same π-normalised D, the same V-cavity G and the same Schlick F, so with options
distribution = "beckmann", shadowing = "v-cavity", fresnel = "schlick" the two are identical for
    kd = Lambertian albedo,   ks = 4 · albedo / π,   m = roughness,   f0 = eta.
(Equating ks/4 = albedo/π.) The test suite checks this against an independent transcription of
bbm's formula.

Blinn-Phong (bbm ``NganBlinnPhong``, parameters ``albedo``, ``sharpness``) is read but not mapped
to a scene: bbm aliases it to its Lafortune "modified Phong", albedo·(n+2)/(2π)·cosⁿα with α
measured from the *mirror* direction, whereas a Blinn-Phong lobe uses the half vector (cosⁿθ_h),
and the two differ by roughly a factor 4 in n. Which one the published sharpness belongs to is
not settled here, so no exact mapping is claimed.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

from fitting.models.catalogue import COOK_TORRANCE_OPTIONS
from plumbing.inputs import MiB, read_input_text

__all__ = [
    "NGAN_MODELS",
    "read_ngan_fits",
    "ngan_fits_path",
    "ngan_cook_torrance_parameters",
    "ngan_scene_material",
    "COOK_TORRANCE_OPTIONS",
]

# The seven model tables of Ngan et al. 2005 as distributed by bbm (file ngan_<name>.fit).
NGAN_MODELS = (
    "ashikhminshirley",
    "blinnphong",
    "cooktorrance",
    "he",
    "lafortune",
    "ward",
    "wardduer",
)

_LINE = re.compile(
    r"^(?P<name>[^\s=]+)\s*=\s*Aggregate\(\s*Lambertian\((?P<diffuse>[^()]*)\)\s*,\s*"
    r"(?P<lobe>Ngan\w+)\((?P<params>[^()]*)\)\s*\)\s*$"
)
_PARAM = re.compile(r"(\w+)\s*=\s*(\[[^\]]*\]|[^,\s]+)")

Value = float | tuple[float, ...]


def _parse_params(text: str, where: str) -> dict[str, Value]:
    out: dict[str, Value] = {}
    for key, raw in _PARAM.findall(text):
        if raw.startswith("["):
            out[key] = tuple(float(v) for v in raw[1:-1].split(","))
        else:
            out[key] = float(raw)
    if not out and text.strip():
        raise ValueError(f"{where}: cannot parse parameters {text!r}")
    return out


def read_ngan_fits(path: str | os.PathLike) -> dict[str, dict[str, Value]]:
    """Parse a bbm ``ngan_<model>.fit`` table: {material: {parameter: value or (r, g, b)}}.

    Every entry has ``diffuse_albedo`` (the Lambertian albedo ρ_d, f_d = ρ_d/π, per channel) and
    the lobe's own parameters under the file's names (Cook-Torrance: ``albedo`` (r, g, b),
    ``eta`` = F₀, ``roughness`` = Beckmann m; Blinn-Phong: ``albedo``, ``sharpness``); the
    lobe class name (e.g. "NganCookTorrance") is under ``lobe``. Comment lines (#) are skipped;
    any other line that does not parse is an error naming the file and line.
    """
    path = Path(path)
    fits: dict[str, dict[str, Value]] = {}
    text = read_input_text(path, "fit table", 256 * MiB)
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        m = _LINE.match(line)
        if m is None:
            raise ValueError(
                f"{where}: not a 'name = Aggregate(Lambertian(...), Ngan...(...))' line"
            )
        diffuse = _parse_params(m["diffuse"], where)
        if "albedo" not in diffuse:
            raise ValueError(f"{where}: Lambertian without albedo")
        entry: dict[str, Value] = {"diffuse_albedo": diffuse["albedo"], "lobe": m["lobe"]}
        entry.update(_parse_params(m["params"], where))
        if m["name"] in fits:
            raise ValueError(f"{where}: material {m['name']!r} listed twice")
        fits[m["name"]] = entry
    if not fits:
        raise ValueError(f"{path}: no fits found")
    return fits


def ngan_fits_path(model: str = "cooktorrance", data_dir: str | os.PathLike | None = None) -> Path:
    """The ``ngan_<model>.fit`` file: in ``data_dir`` (a folder holding it or ``brdf_fits/``),
    else ``brdf_fits/`` found by the data resolver (brdfdata.data_paths: $GONIO_DATA, the
    repository's data/, an installed wheel's share/gonio/data)."""
    from brdfdata.data_paths import find_data

    if model not in NGAN_MODELS:
        raise ValueError(f"unknown Ngan model {model!r}; choose one of {', '.join(NGAN_MODELS)}")
    name = f"ngan_{model}.fit"
    if data_dir is None:
        return find_data(f"brdf_fits/{name}")
    tried = []
    for c in (Path(data_dir) / name, Path(data_dir) / "brdf_fits" / name):
        tried.append(str(c))
        if c.is_file():
            return c
    raise FileNotFoundError(f"{name} not found (looked in {', '.join(tried)})")


def _rgb(value: Value) -> tuple[float, float, float]:
    if isinstance(value, tuple):
        if len(value) != 3:
            raise ValueError(f"expected an (r, g, b) triple, got {value}")
        return (float(value[0]), float(value[1]), float(value[2]))
    v = float(value)
    return (v, v, v)


def ngan_cook_torrance_parameters(entry: dict[str, Value]) -> dict[str, Value]:
    """Our ``torrance-sparrow`` (beckmann, v-cavity, schlick) parameters of one Cook-Torrance fit.

    kd = ρ_d, ks = 4·albedo/π, m = roughness, f0 = eta (see the module docstring: bbm's
    albedo·D·G·F/(π cos θ_i cos θ_o) equals our ks·D·G·F/(4 cos θ_i cos θ_o) for ks/4 = albedo/π).
    """
    if entry.get("lobe") != "NganCookTorrance":
        raise ValueError(f"not a Cook-Torrance fit (lobe {entry.get('lobe')!r})")
    albedo = _rgb(entry["albedo"])
    return {
        "kd": _rgb(entry["diffuse_albedo"]),
        "ks": tuple(4.0 * a / math.pi for a in albedo),
        "m": float(entry["roughness"]),  # type: ignore[arg-type]
        "f0": float(entry["eta"]),  # type: ignore[arg-type]
    }


def ngan_scene_material(
    material_name: str,
    model: str = "cooktorrance",
    data_dir: str | os.PathLike | None = None,
) -> dict:
    """A scene ``[material]`` table (simulator.scene.ModelMaterial fields) for a MERL material's
    published fit, e.g. ``ngan_scene_material("nickel")``.

    Only ``model="cooktorrance"`` is mapped (to torrance-sparrow with beckmann / v-cavity /
    schlick, exact); the other tables can be read with `read_ngan_fits`.
    """
    if model != "cooktorrance":
        raise ValueError(
            f"ngan model {model!r} has no scene mapping; only 'cooktorrance' maps exactly to "
            "fitting.models (read the others with read_ngan_fits)"
        )
    fits = read_ngan_fits(ngan_fits_path(model, data_dir))
    if material_name not in fits:
        raise KeyError(f"{material_name!r} is not among the {len(fits)} MERL materials of the fit")
    return {
        "type": "model",
        "model": "torrance-sparrow",
        "options": dict(COOK_TORRANCE_OPTIONS),
        "parameters": ngan_cook_torrance_parameters(fits[material_name]),
    }
