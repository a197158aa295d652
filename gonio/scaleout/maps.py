"""Parameter maps of a per-texel fit (issue 20): PNG previews, EXR textures and a Mitsuba scene.

From the result rows (fitting.texels) of a `gonio fit-texels` job, into ``OUT/maps/``:

* ``NAME.png`` — the median of every parameter, and ``NAME-sigma.png`` its 1-σ half-width
  (p84 − p16)/2, in a perceptual colour map with the value range in the file name's sidecar
  ``maps.json``; the verdicts ``rhat_max.png`` and ``chi2_red.png`` likewise. Row 0 of an image
  is the texel row iy = n_y − 1 (+y up, as the sample is seen from above).
* For a model Mitsuba renders with built-ins per texel — Lambert + Beckmann or GGX lobe with
  F ≡ 1 and Smith shadowing (fitting.export's ``roughconductor`` case) — the textures
  ``rho.exr``, ``spec.exr``, ``weight.exr``, ``alpha.exr`` (float32, exact values) and
  ``material-texels.xml``, a scene of the sample (a rectangle of the sample's size; 2 × 2 units
  when the samples do not say it) with the material blendbsdf(diffuse ρ, roughconductor α;
  weight w) of bitmap textures (nearest lookup, raw), so f = (1 − w)ρ/π + w·s·lobe =
  kd/π + ks·lobe per texel, with w = max_c ks_c, ρ = kd/(1 − w), s = ks/w (fitting.export's
  identity). Bitmap row iy holds texel row iy (Mitsuba's rectangle: v grows with +y). Texels
  without a fit are 0 (black).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["write_maps", "scene_xml"]


def _png(path: Path, image: np.ndarray) -> tuple[float, float]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finite = image[np.isfinite(image)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if hi <= lo:
        hi = lo + 1e-12
    # Flipped so that +y is up in the picture (row 0 of the array is the texel row iy = 0).
    plt.imsave(path, np.ma.masked_invalid(image[::-1]), cmap="viridis", vmin=lo, vmax=hi)
    return lo, hi


def _exr(path: Path, image: np.ndarray) -> None:
    import OpenEXR

    from plumbing.atomic import atomic_write_bytes

    arr = np.ascontiguousarray(np.nan_to_num(image, nan=0.0).astype(np.float32))
    key = "RGB" if arr.ndim == 3 else "Y"
    tmp = path.with_name(f".{path.name}.build")
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {key: arr}) as f:
        f.write(str(tmp))
    atomic_write_bytes(path, tmp.read_bytes(), overwrite=True)
    tmp.unlink()


def write_maps(
    rows, n_x: int, n_y: int, out_dir: Path, options, size_m: float | None = None
) -> list[Path]:
    """Write the PNG previews (and, where Mitsuba can render the model, EXR textures and the
    scene XML) into ``out_dir/maps``; returns the files written."""
    from fitting.texels import parameter_maps
    from plumbing.atomic import atomic_write_bytes

    maps = parameter_maps(rows, n_x, n_y)
    dest = Path(out_dir) / "maps"
    dest.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    ranges: dict[str, list[float]] = {}
    names = sorted({k[: -len(".median")] for k in maps if k.endswith(".median")})
    for name in names:
        for suffix, image in (
            ("", maps[f"{name}.median"]),
            ("-sigma", (maps[f"{name}.p84"] - maps[f"{name}.p16"]) / 2.0),
        ):
            path = dest / f"{name}{suffix}.png"
            ranges[path.name] = list(_png(path, image))
            written.append(path)
    for verdict in ("rhat_max", "chi2_red", "n_samples"):
        if verdict in maps:
            path = dest / f"{verdict}.png"
            ranges[path.name] = list(_png(path, maps[verdict]))
            written.append(path)
    text = json.dumps({"value_range": ranges, "n_x": n_x, "n_y": n_y}, indent=1)
    written.append(atomic_write_bytes(dest / "maps.json", text.encode(), overwrite=True))
    written.extend(_scene(maps, dest, options, size_m or 2.0))
    return written


def _channel_maps(maps: dict, base: str, channels: list[str]) -> np.ndarray | None:
    """(n_y, n_x, C) medians of a per-channel parameter (or its shared bare name)."""
    if f"{base}.median" in maps:
        return np.repeat(maps[f"{base}.median"][..., None], len(channels), axis=-1)
    per = [maps.get(f"{base}_{c}.median") for c in channels]
    return None if any(p is None for p in per) else np.stack(per, axis=-1)


def _scene(maps: dict, dest: Path, options, size_m: float) -> list[Path]:
    """EXR textures and material-texels.xml for a Lambert + lobe with F ≡ 1 (module doc)."""
    from fitting.export import builtin_reason
    from plumbing.atomic import atomic_write_bytes

    model_options = dict(getattr(options, "model_options", {}) or {})
    if getattr(options, "model", None) != "torrance-sparrow":
        return []
    if model_options.get("fresnel") != "none" or builtin_reason(options.model, model_options):
        return []
    channels = [c for c in ("R", "G", "B") if f"kd_{c}.median" in maps] or ["R", "G", "B"]
    kd, ks = _channel_maps(maps, "kd", channels), _channel_maps(maps, "ks", channels)
    if kd is None or ks is None or "m.median" not in maps:
        return []
    if kd.shape[-1] != 3:
        kd, ks = (np.repeat(a.mean(axis=-1, keepdims=True), 3, axis=-1) for a in (kd, ks))
    w = np.nanmax(ks, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.clip(kd / (1.0 - w[..., None]), 0.0, 1.0)
        spec = np.clip(ks / w[..., None], 0.0, 1.0)
    files = {
        "rho.exr": rho,
        "spec.exr": spec,
        "weight.exr": w,
        "alpha.exr": maps["m.median"],
    }
    out = []
    for name, image in files.items():
        _exr(dest / name, image)
        out.append(dest / name)
    xml = scene_xml(model_options.get("distribution", "beckmann"), size_m / 2.0)
    out.append(atomic_write_bytes(dest / "material-texels.xml", xml.encode(), overwrite=True))
    return out


def _bitmap(name: str, filename: str) -> str:
    return (
        f'    <texture type="bitmap" name="{name}">\n'
        f'        <string name="filename" value="{filename}"/>\n'
        '        <boolean name="raw" value="true"/>\n'
        '        <string name="filter_type" value="nearest"/>\n'
        '        <string name="wrap_mode" value="clamp"/>\n'
        "    </texture>\n"
    )


def scene_xml(distribution: str = "beckmann", half_m: float = 1.0) -> str:
    """The Mitsuba 3 material of the maps (textures beside the XML; see the module doc)."""
    inner = _bitmap("reflectance", "rho.exr").replace("\n    ", "\n        ")
    lobe_alpha = _bitmap("alpha", "alpha.exr").replace("\n    ", "\n        ")
    lobe_spec = _bitmap("specular_reflectance", "spec.exr").replace("\n    ", "\n        ")
    return (
        '<scene version="3.0.0">\n'
        "<!-- gonio fit-texels: per-texel kd/pi + ks*lobe as blendbsdf of bitmaps "
        "(gonio/scaleout/maps.py) -->\n"
        '<bsdf type="blendbsdf" id="texels">\n'
        + _bitmap("weight", "weight.exr")
        + '    <bsdf type="diffuse">\n    '
        + inner
        + "    </bsdf>\n"
        + f'    <bsdf type="roughconductor">\n'
        f'        <string name="distribution" value="{distribution}"/>\n'
        '        <string name="material" value="none"/>\n    '
        + lobe_alpha
        + "    "
        + lobe_spec
        + "    </bsdf>\n</bsdf>\n"
        + "<!-- the sample: Mitsuba's rectangle spans [-1, 1]^2, scaled to the sample's half side "
        "(m) -->\n"
        + '<shape type="rectangle" id="sample">\n'
        + f'    <transform name="to_world"><scale x="{half_m:g}" y="{half_m:g}"/></transform>\n'
        + '    <ref id="texels"/>\n</shape>\n</scene>\n'
    )
