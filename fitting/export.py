"""Export a fit as a Mitsuba 3 material: a ``load_dict`` dict and the equivalent XML (issue 7).

Built-in plugins are used where they reproduce the fitted f_r exactly:

* ``lambert`` → ``diffuse`` with reflectance kd (f = kd/π).
* ``torrance-sparrow`` with shadowing ``smith-rational`` (Mitsuba's Smith G₁: Walter's rational
  fit for Beckmann, the exact G₁ for GGX) and fresnel ``conductor`` (η, k), ``dielectric``
  (η = ior, k = 0: the conductor Fresnel equations with k = 0 are the dielectric ones for
  external reflection) or ``none`` (F ≡ 1):
  ks·D G F/(4 cos θ_i cos θ_o) = ``roughconductor`` (alpha = m) with specular_reflectance ks.
  With kd > 0 the material is ``blendbsdf`` of ``diffuse`` (ρ) and that ``roughconductor``
  (specular_reflectance s) with weight w: Mitsuba gives (1 − w) ρ/π + w s·lobe, which equals
  kd/π + ks·lobe for ρ = kd/(1 − w) and s = ks/w. We take w = max_c ks_c (the channel with
  the largest ks gets s = 1). Mitsuba rejects RGB reflectances outside [0, 1], so this needs
  max ks + max kd ≤ 1 (some w with w ≥ ks_c and 1 − w ≥ kd_c exists only then); otherwise,
  and for ks > 1, the Python BSDF below is used instead.

Anything else (Phong family, v-cavity or exact-Λ Smith shadowing, Schlick Fresnel) becomes the
registered Python BSDF ``gonio_model`` of :mod:`simulator.materials`, with one string parameter
``spec`` = the JSON of a ``simulator.scene.ModelMaterial`` {"type": "model", "model",
"options", "parameters"}. It must be registered in the active Mitsuba variant *before* the
dict or XML is loaded: ``from simulator.materials import register_model_bsdf;
register_model_bsdf()`` (``simulator.render`` does this for scenes it builds).

Channels: a fit with R, G and B gives RGB values; any other channel set (e.g. one luminance
channel Y) gives grey values equal to the mean over the fitted channels.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

from fitting.atomic import atomic_write_bytes

__all__ = [
    "MODEL_PLUGIN",
    "material_dict",
    "material_xml",
    "write_material_xml",
    "channel_values",
    "is_builtin",
]

#: Name of the Python BSDF plugin registered by simulator.materials.register_model_bsdf.
MODEL_PLUGIN = "gonio_model"
_RGB = ("R", "G", "B")


def _fit_dict(fit) -> dict:
    return fit.to_dict() if hasattr(fit, "to_dict") else dict(fit)


def channel_values(fit, estimate: str = "median") -> dict[str, list[float]]:
    """Each model parameter as an (R, G, B) triple from a fit (FitResult or its JSON dict).

    ``kd_R`` → kd[0]…; a shared (bare) name fills all three; the discrepancy term is dropped.
    """
    d = _fit_dict(fit)
    chans = list(d["channels"])
    params = d["parameters"]
    per: dict[str, dict[str, float]] = {}
    for name, p in params.items():
        if name == "discrepancy":
            continue
        base, _, ch = name.rpartition("_")
        value = float(p[estimate])
        if base and ch in chans:
            per.setdefault(base, {})[ch] = value
        else:
            per[name] = {c: value for c in chans}
    out = {}
    for base, by_ch in per.items():
        if all(c in by_ch for c in _RGB):
            out[base] = [by_ch[c] for c in _RGB]
        else:
            mean = sum(by_ch.values()) / len(by_ch)
            out[base] = [mean] * 3
    # Parameters held fixed with --fix are not in the JSON; the model defaults cover them.
    return out


def is_builtin(model: str, options: Mapping) -> bool:
    """True when a Mitsuba built-in BSDF reproduces the model with these options exactly
    (given max ks + max kd ≤ 1, see the module docstring)."""
    if model == "lambert":
        return True
    return (
        model == "torrance-sparrow"
        and options.get("shadowing", "v-cavity") == "smith-rational"
        and options.get("fresnel", "dielectric") in ("conductor", "dielectric", "none")
    )


def _rgb(v) -> dict:
    return {"type": "rgb", "value": [float(x) for x in v]}


def _roughconductor(options: Mapping, vals: Mapping, spec: list[float]) -> dict:
    d = {
        "type": "roughconductor",
        "distribution": options.get("distribution", "beckmann"),
        "alpha": float(vals["m"][0]),
        "specular_reflectance": _rgb(spec),
    }
    fres = options.get("fresnel", "dielectric")
    if fres == "conductor":
        d["eta"], d["k"] = _rgb(vals["eta"]), _rgb(vals["k"])
    elif fres == "dielectric":
        d["eta"], d["k"] = _rgb(vals.get("ior", [1.5] * 3)), _rgb([0.0, 0.0, 0.0])
    else:
        d["material"] = "none"
    return d


def material_dict(fit, estimate: str = "median") -> dict:
    """Mitsuba ``load_dict`` material for a fit (FitResult or fit JSON dict); see module doc."""
    d = _fit_dict(fit)
    model, options = d["model"], dict(d.get("options") or {})
    vals = channel_values(d, estimate)
    if model == "lambert":
        return {"type": "diffuse", "reflectance": _rgb(vals["kd"])}
    kd, ks = vals.get("kd", [0.0] * 3), vals.get("ks", [0.0] * 3)
    w = max(ks)
    if is_builtin(model, options) and 0 < w <= 1 and max(kd) <= 1 - w:
        if max(kd) <= 0:
            return _roughconductor(options, vals, ks)
        return {
            "type": "blendbsdf",
            # weight 0 selects the first nested BSDF, 1 the second (Mitsuba blendbsdf).
            "weight": float(w),
            "bsdf_0_diffuse": {"type": "diffuse", "reflectance": _rgb([x / (1 - w) for x in kd])},
            "bsdf_1_specular": _roughconductor(options, vals, [x / w for x in ks]),
        }
    spec = {
        "type": "model",
        "model": model,
        "options": {k: str(v) for k, v in options.items()},
        "parameters": {k: (v[0] if v[0] == v[1] == v[2] else v) for k, v in vals.items()},
    }
    return {"type": MODEL_PLUGIN, "spec": json.dumps(spec, sort_keys=True)}


def _xml(d: Mapping, indent: int, name: str | None = None) -> list[str]:
    pad = "    " * indent
    attrs = f"type={quoteattr(d['type'])}" + (f" id={quoteattr(name)}" if name else "")
    lines = [f"{pad}<bsdf {attrs}>"]
    for key, v in d.items():
        if key == "type":
            continue
        if isinstance(v, Mapping) and v.get("type") == "rgb":
            value = ", ".join(repr(float(x)) for x in v["value"])
            lines.append(f'{pad}    <rgb name="{key}" value="{value}"/>')
        elif isinstance(v, Mapping):
            lines += _xml(v, indent + 1)
        elif isinstance(v, float | int) and not isinstance(v, bool):
            if not math.isfinite(v):
                raise ValueError(f"material parameter {key} = {v} is not finite")
            lines.append(f'{pad}    <float name="{key}" value="{float(v)!r}"/>')
        else:
            lines.append(f'{pad}    <string name="{key}" value={quoteattr(str(v))}/>')
    lines.append(f"{pad}</bsdf>")
    return lines


def material_xml(fit, estimate: str = "median", bsdf_id: str | None = None) -> str:
    """The same material as Mitsuba 3 XML (one ``<bsdf version="3.0.0">`` element, loadable
    with ``mi.load_string``; include it in a scene or reference it by ``bsdf_id``)."""
    d = material_dict(fit, estimate)
    lines = _xml(d, 0, bsdf_id)
    lines[0] = lines[0].replace("<bsdf ", '<bsdf version="3.0.0" ', 1)
    head = "<!-- gonio fit export"
    if d["type"] == MODEL_PLUGIN:
        head += " — needs simulator.materials.register_model_bsdf() before loading"
    return head + " -->\n" + "\n".join(lines) + "\n"


def write_material_xml(fit, path: str | os.PathLike, estimate: str = "median") -> Path:
    """Write :func:`material_xml` to ``path``."""
    return atomic_write_bytes(path, material_xml(fit, estimate).encode())
