"""Export a fit as a Mitsuba 3 material: a ``load_dict`` dict and the equivalent XML (issues 7, 16).

Built-in plugins are used where they reproduce the fitted f_r exactly:

* ``lambert`` → ``diffuse`` with reflectance kd (f = kd/π).
* ``torrance-sparrow`` whose shadowing is Mitsuba's Smith G₁ — ``smith-rational`` (Walter's
  rational fit for Beckmann; for GGX the exact G₁) or, for GGX, ``smith`` (exact Λ, the same
  G₁) — with the lobe ks·D G F/(4 cos θ_i cos θ_o):

  - fresnel ``conductor`` (η, k) or ``none`` (F ≡ 1) → ``roughconductor`` (alpha = m),
    specular_reflectance ks;
  - fresnel ``dielectric`` with one ior for all channels → ``roughplastic`` with
    int_ior = ior, ext_ior = 1, diffuse_reflectance 0 (its coated-diffuse term vanishes, leaving
    exactly F_dielectric·D·G/(4 cos θ_i cos θ_o)) and specular_reflectance ks; a per-channel
    ior becomes a ``roughconductor`` with k = 0 (the conductor Fresnel equations with k = 0
    are the dielectric ones for external reflection).

  With kd > 0 the material is ``blendbsdf`` of ``diffuse`` (ρ) and that lobe (specular
  reflectance s) with weight w: Mitsuba gives (1 − w) ρ/π + w s·lobe, which equals
  kd/π + ks·lobe for ρ = kd/(1 − w) and s = ks/w. We take w = max_c ks_c (the channel with
  the largest ks gets s = 1). Mitsuba rejects RGB reflectances outside [0, 1], so this needs
  max ks + max kd ≤ 1; otherwise, and for ks > 1, no built-in applies.

Anything else (Phong family, v-cavity or exact-Λ Beckmann Smith shadowing, Schlick Fresnel):

* in-process (:func:`material_dict`, used by the preview and the simulator) the registered
  Python BSDF ``gonio_model`` of :mod:`simulator.materials`, with one string parameter
  ``spec`` = the JSON of a ``simulator.scene.ModelMaterial``; it must be registered in the
  active variant before loading (``simulator.materials.register_model_bsdf()``);
* on disk (:func:`export_material`, what ``gonio fit`` writes) a *tabulated fallback* that
  plain Mitsuba loads: the model tabulated as an RGL tensor file beside the XML
  (:mod:`brdfdata.formats.rgl_tabulate`) and a ``measured`` BSDF referencing it, with one line
  saying how close the table is to the model.

Parameters held fixed in the fit (``--fix``, the fit JSON's ``fixed``) are exported with the
fitted ones. Channels: a fit with R, G and B gives RGB values; any other channel set (e.g. one
luminance channel Y) gives grey values equal to the mean over the fitted channels.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from plumbing.atomic import atomic_write_bytes

__all__ = [
    "MODEL_PLUGIN",
    "ExportResult",
    "material_dict",
    "material_xml",
    "export_material",
    "write_material_xml",
    "channel_values",
    "fit_evaluator",
    "export_fit",
    "is_builtin",
    "builtin_reason",
]

#: Name of the Python BSDF plugin registered by simulator.materials.register_model_bsdf.
MODEL_PLUGIN = "gonio_model"
_RGB = ("R", "G", "B")


def _fit_dict(fit) -> dict:
    return fit.to_dict() if hasattr(fit, "to_dict") else dict(fit)


def channel_values(fit, estimate: str = "median") -> dict[str, list[float]]:
    """Each model parameter as an (R, G, B) triple from a fit (FitResult or its JSON dict),
    fixed parameters (the JSON's ``fixed``) included.

    ``kd_R`` → kd[0]…; a shared (bare) name fills all three; the discrepancy term is dropped.
    """
    d = _fit_dict(fit)
    chans = list(d["channels"])
    entries = [(n, float(p[estimate])) for n, p in d["parameters"].items()]
    entries += [(n, float(v)) for n, v in (d.get("fixed") or {}).items()]
    per: dict[str, dict[str, float]] = {}
    for name, value in entries:
        if name == "discrepancy":
            continue
        base, _, ch = name.rpartition("_")
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
    return out


def fit_evaluator(fit, estimate: str = "median") -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``evaluate(wi, wo)`` → f_r (N, 3) in sr⁻¹ of the fitted model with the exported (R, G, B)
    parameter values (as :func:`material_dict` sees them)."""
    from fitting import models

    d = _fit_dict(fit)
    model = models.get(d["model"], **dict(d.get("options") or {}))
    vals = channel_values(d, estimate)

    def evaluate(wi, wo):
        cols = [model.evaluate({k: v[c] for k, v in vals.items()}, wi, wo) for c in range(3)]
        return np.stack(cols, axis=1)

    return evaluate


def builtin_reason(model: str, options: Mapping) -> str | None:
    """None when a Mitsuba built-in reproduces the model with these options exactly (given the
    reflectance limits of the module docstring), else why not, in a few words."""
    if model == "lambert":
        return None
    if model != "torrance-sparrow":
        return f"Mitsuba 3 has no {model} BSDF"
    dist = options.get("distribution", "beckmann")
    shadow = options.get("shadowing", "v-cavity")
    fres = options.get("fresnel", "dielectric")
    if not (shadow == "smith-rational" or (dist == "ggx" and shadow == "smith")):
        return f"Mitsuba's microfacet BSDFs use Smith G1, not {shadow} shadowing"
    if fres not in ("conductor", "dielectric", "none"):
        return f"Mitsuba's microfacet BSDFs have no {fres} Fresnel"
    return None


def is_builtin(model: str, options: Mapping) -> bool:
    """True when a Mitsuba built-in BSDF reproduces the model with these options exactly
    (given max ks + max kd ≤ 1, see the module docstring)."""
    return builtin_reason(model, options) is None


def _rgb(v) -> dict:
    return {"type": "rgb", "value": [float(x) for x in v]}


def _lobe(options: Mapping, vals: Mapping, spec: list[float]) -> dict:
    """The microfacet lobe alone: roughplastic (one dielectric ior) or roughconductor."""
    fres = options.get("fresnel", "dielectric")
    dist = options.get("distribution", "beckmann")
    alpha = float(vals["m"][0])
    ior = vals.get("ior", [1.5] * 3)
    if fres == "dielectric" and ior[0] == ior[1] == ior[2]:
        return {
            "type": "roughplastic",
            "distribution": dist,
            "alpha": alpha,
            "int_ior": float(ior[0]),
            "ext_ior": 1.0,
            "diffuse_reflectance": _rgb([0.0, 0.0, 0.0]),
            "specular_reflectance": _rgb(spec),
        }
    d = {
        "type": "roughconductor",
        "distribution": dist,
        "alpha": alpha,
        "specular_reflectance": _rgb(spec),
    }
    if fres == "conductor":
        d["eta"], d["k"] = _rgb(vals["eta"]), _rgb(vals["k"])
    elif fres == "dielectric":
        d["eta"], d["k"] = _rgb(ior), _rgb([0.0, 0.0, 0.0])
    else:
        d["material"] = "none"
    return d


def _builtin_dict(model: str, options: Mapping, vals: Mapping) -> dict | None:
    """The built-in material, or None when none reproduces the fit (module docstring)."""
    if model == "lambert":
        return {"type": "diffuse", "reflectance": _rgb(vals["kd"])}
    if not is_builtin(model, options):
        return None
    kd, ks = vals.get("kd", [0.0] * 3), vals.get("ks", [0.0] * 3)
    w = max(ks)
    if not (0 < w <= 1 and max(kd) <= 1 - w and min(kd) >= 0):
        return None
    if max(kd) <= 0:
        return _lobe(options, vals, ks)
    return {
        "type": "blendbsdf",
        # weight 0 selects the first nested BSDF, 1 the second (Mitsuba blendbsdf).
        "weight": float(w),
        "bsdf_0_diffuse": {"type": "diffuse", "reflectance": _rgb([x / (1 - w) for x in kd])},
        "bsdf_1_specular": _lobe(options, vals, [x / w for x in ks]),
    }


def material_dict(fit, estimate: str = "median") -> dict:
    """Mitsuba ``load_dict`` material for a fit (FitResult or fit JSON dict): a built-in where
    one is exact, else the registered Python BSDF (module docstring)."""
    d = _fit_dict(fit)
    model, options = d["model"], dict(d.get("options") or {})
    vals = channel_values(d, estimate)
    builtin = _builtin_dict(model, options, vals)
    if builtin is not None:
        return builtin
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


def _xml_text(d: Mapping, head: str, bsdf_id: str | None = None) -> str:
    lines = _xml(d, 0, bsdf_id)
    lines[0] = lines[0].replace("<bsdf ", '<bsdf version="3.0.0" ', 1)
    return f"<!-- {head.replace('--', '-')} -->\n" + "\n".join(lines) + "\n"


def material_xml(fit, estimate: str = "median", bsdf_id: str | None = None) -> str:
    """:func:`material_dict` as Mitsuba 3 XML (one ``<bsdf version="3.0.0">`` element, loadable
    with ``mi.load_string``; include it in a scene or reference it by ``bsdf_id``)."""
    d = material_dict(fit, estimate)
    head = "gonio fit export"
    if d["type"] == MODEL_PLUGIN:
        head += " — needs simulator.materials.register_model_bsdf() before loading"
    return _xml_text(d, head, bsdf_id)


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_material` wrote: the XML, the Mitsuba plugin it uses, the tabulated
    file of a fallback (else None), and one line describing the export."""

    xml_path: Path
    plugin: str
    table_path: Path | None
    note: str


def _hint(vals: Mapping) -> tuple[float, str]:
    """Roughness that shapes the fallback's parameterization: m, or the Phong lobe's width."""
    if "m" in vals:
        return float(np.clip(vals["m"][0], 0.01, 1.0)), "beckmann"
    if "n" in vals:  # cos^n α ≈ exp(−n α²/2): width √(2/n)
        return float(np.clip(math.sqrt(2.0 / (float(vals["n"][0]) + 2.0)), 0.01, 1.0)), "beckmann"
    return 0.5, "beckmann"


def export_material(fit, path: str | os.PathLike, estimate: str = "median") -> ExportResult:
    """Write the material for plain Mitsuba 3 at ``path`` (XML): the built-in where one is
    exact, else the tabulated fallback ``<path stem>.bsdf`` referenced by a ``measured`` BSDF
    (relative file name: keep the two files together)."""
    from brdfdata.formats.rgl_tabulate import TabulateOptions, closeness, write_tabulated

    path = Path(path)
    d = _fit_dict(fit)
    model, options = d["model"], dict(d.get("options") or {})
    vals = channel_values(d, estimate)
    builtin = _builtin_dict(model, options, vals)
    if builtin is not None:
        text = _xml_text(
            builtin, f"gonio fit export: {model} as Mitsuba's built-in {builtin['type']}"
        )
        atomic_write_bytes(path, text.encode(), overwrite=True)
        return ExportResult(path, builtin["type"], None, f"built-in {builtin['type']} (exact)")
    why = builtin_reason(model, options) or "reflectances outside what Mitsuba's built-ins accept"
    table = path.with_suffix(".bsdf")
    m, dist = _hint(vals)
    evaluate = fit_evaluator(d, estimate)
    desc = f"gonio tabulated {model} {json.dumps(options, sort_keys=True)}"
    write_tabulated(table, evaluate, TabulateOptions(m=m, distribution=dist, description=desc))
    close = closeness(table, evaluate)
    note = f"tabulated fallback {table.name} ({why}): {close.line()}"
    text = _xml_text({"type": "measured", "filename": table.name}, f"gonio fit export: {note}")
    atomic_write_bytes(path, text.encode(), overwrite=True)
    return ExportResult(path, "measured", table, note)


def write_material_xml(fit, path: str | os.PathLike, estimate: str = "median") -> Path:
    """Write the material for plain Mitsuba 3 (:func:`export_material`); returns the XML path."""
    return export_material(fit, path, estimate).xml_path


def export_fit(fmt: str, source: str | os.PathLike, out: str | os.PathLike, angles: str = "rad"):
    """``gonio export merl FIT.json``: the fitted model (medians) tabulated at every MERL bin
    centre. Returns (path, one line describing what was written); other formats are refused in
    one line, as :func:`brdfdata.formats.convert.export_file` refuses them."""
    from brdfdata.formats import merl
    from brdfdata.formats.common import FormatError
    from brdfdata.formats.convert import check_export
    from brdfdata.samples.guards import F_MAX_SR
    from fitting.result import read_fit

    source, out = Path(source), Path(out)
    check_export(fmt, angles)
    if fmt == "csv":
        raise FormatError(f"{source}: export csv writes a samples table; give SAMPLES.parquet")
    if angles != "rad":
        raise FormatError("--angles applies to csv only (MERL bins are angles by definition)")
    fit = read_fit(source)
    with np.errstate(over="ignore", invalid="ignore"):  # judged below, in one line
        table = merl.tabulate(fit_evaluator(fit))
    raw = table.raw[table.raw >= 0]
    if not np.all(np.isfinite(table.raw)) or (raw.size and raw.max() * max(merl.SCALES) > F_MAX_SR):
        # a fit read back with parameters no measurement gives (kd = 1e308 wrote inf)
        raise FormatError(
            f"{source}: its parameters give f beyond {F_MAX_SR:.0e} sr^-1 or not finite at some "
            "MERL bin; not a fit of a measured material — refit it"
        )
    merl.write_merl(out, table)
    n = int(np.sum(merl.read_merl(out).raw[0] >= 0))
    opts = json.dumps(fit.options, sort_keys=True)
    return out, f"{fit.model} {opts} tabulated at {n} bin centres (medians)"
