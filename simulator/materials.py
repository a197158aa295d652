"""Scene materials as Mitsuba 3 BSDFs: built-in plugins, RGL measured tensors, and any
`fitting.models` model wrapped as a Python BSDF.

Conventions (docs/design.md §3, §7): Mitsuba's ``bsdf.eval(ctx, si, w)`` returns f_r(si.wi, w)·cos
θ_w, with ``si.wi`` towards the camera and ``w`` towards the light when the direct integrator shades
a point. `fitting.models` take ``wi`` towards the light and ``wo`` towards the camera and return f_r
alone. So the wrapper evaluates ``model.evaluate(params, wi=w, wo=si.wi)·cos θ_w``.

The Python BSDF (``ModelBSDF``) moves the lanes to numpy, calls the model's numba kernel and moves
the result back. That needs concrete arrays, so the renderer runs such scenes with drjit's
*wavefront* mode (``JitFlag.SymbolicCalls`` / ``SymbolicLoops`` off, see ``needs_wavefront``);
each BSDF call then sees the evaluated lanes of its own shape. Importance sampling is
cosine-weighted (pdf = cos θ/π), which is exact for the diffuse part and unbiased for any lobe.
"""

from __future__ import annotations

import json
import weakref

import numpy as np

from simulator.scene import (
    BlendMaterial,
    ConductorMaterial,
    DiffuseMaterial,
    MeasuredMaterial,
    ModelMaterial,
    PlasticMaterial,
    RoughConductorMaterial,
    RoughDielectricMaterial,
    RoughPlasticMaterial,
    TexturedMaterial,
)
from simulator.texture import textured_dict

__all__ = [
    "material_dict",
    "needs_wavefront",
    "model_bsdfs_alive",
    "iter_materials",
    "register_model_bsdf",
    "model_channel_parameters",
    "MODEL_PLUGIN",
]

MODEL_PLUGIN = "gonio_model"


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def iter_materials(material):
    """The material and every nested one (blend children), depth first."""
    yield material
    if isinstance(material, BlendMaterial):
        yield from iter_materials(material.first)
        yield from iter_materials(material.second)


def needs_wavefront(material) -> bool:
    """True if any (nested) material is a Python-wrapped model (see module docstring).

    Other scenes need wavefront mode too while such a BSDF is alive: `model_bsdfs_alive`."""
    return any(isinstance(m, ModelMaterial) for m in iter_materials(material))


def _conductor(material, d: dict) -> dict:
    if material.eta is not None or material.k is not None:
        if material.eta is None or material.k is None:
            raise ValueError(f"{material.type}: give both eta and k, or a conductor preset")
        d["eta"] = _rgb(material.eta)
        d["k"] = _rgb(material.k)
    else:
        d["material"] = material.conductor or "none"
    d["specular_reflectance"] = _rgb(material.specular_reflectance)
    return d


def material_dict(material) -> dict:
    """Mitsuba ``load_dict`` description of a scene material (simulator.scene types)."""
    if isinstance(material, DiffuseMaterial):
        return {"type": "diffuse", "reflectance": _rgb(material.reflectance)}
    if isinstance(material, RoughConductorMaterial):
        d = {
            "type": "roughconductor",
            "distribution": material.distribution,
            "alpha": float(material.alpha),
        }
        return _conductor(material, d)
    if isinstance(material, ConductorMaterial):
        return _conductor(material, {"type": "conductor"})
    if isinstance(material, RoughPlasticMaterial):
        return {
            "type": "roughplastic",
            "distribution": material.distribution,
            "alpha": float(material.alpha),
            "diffuse_reflectance": _rgb(material.diffuse_reflectance),
            "int_ior": float(material.int_ior),
            "ext_ior": float(material.ext_ior),
        }
    if isinstance(material, PlasticMaterial):
        return {
            "type": "plastic",
            "diffuse_reflectance": _rgb(material.diffuse_reflectance),
            "int_ior": float(material.int_ior),
            "ext_ior": float(material.ext_ior),
        }
    if isinstance(material, RoughDielectricMaterial):
        return {
            "type": "roughdielectric",
            "distribution": material.distribution,
            "alpha": float(material.alpha),
            "int_ior": float(material.int_ior),
            "ext_ior": float(material.ext_ior),
        }
    if isinstance(material, MeasuredMaterial):
        return {"type": "measured", "filename": str(material.filename)}
    if isinstance(material, ModelMaterial):
        register_model_bsdf()
        return {"type": MODEL_PLUGIN, "spec": material.model_dump_json()}
    if isinstance(material, TexturedMaterial):
        return textured_dict(material)
    if isinstance(material, BlendMaterial):
        # Mitsuba blendbsdf: weight 0 selects the first nested BSDF, 1 the second, i.e.
        # f = (1 − w)·first + w·second. Nested BSDFs are taken in declaration order.
        return {
            "type": "blendbsdf",
            "weight": float(material.weight),
            "bsdf_0_first": material_dict(material.first),
            "bsdf_1_second": material_dict(material.second),
        }
    raise TypeError(f"unsupported material type {type(material).__name__}")


def model_channel_parameters(material: ModelMaterial) -> list[dict[str, float]]:
    """Per-channel (R, G, B) parameter dicts: a scalar applies to all three channels."""
    out: list[dict[str, float]] = [{}, {}, {}]
    for name, value in material.parameters.items():
        vals = (value, value, value) if isinstance(value, int | float) else value
        for c in range(3):
            out[c][name] = float(vals[c])
    return out


_REGISTERED: set[str] = set()
# Live ModelBSDF instances. drjit's *symbolic* virtual calls trace every registered instance of a
# class — so while any Python-model BSDF exists, *every* scene's BSDF call would trace it (and its
# numpy conversion fails). The renderer therefore switches to wavefront mode while one is alive.
_LIVE_MODEL_BSDFS: weakref.WeakSet = weakref.WeakSet()


def model_bsdfs_alive() -> bool:
    """True while any Python-model BSDF instance exists in this process."""
    return len(_LIVE_MODEL_BSDFS) > 0


def register_model_bsdf() -> None:
    """Register the ``gonio_model`` Python BSDF for the active Mitsuba variant (idempotent)."""
    import drjit as dr
    import mitsuba as mi

    from fitting import models

    variant = mi.variant()
    if variant in _REGISTERED:
        return

    def _np(x) -> np.ndarray:
        return np.atleast_1d(np.asarray(x, dtype=np.float64))

    def _dirs(v) -> np.ndarray:
        return np.stack(np.broadcast_arrays(_np(v.x), _np(v.y), _np(v.z)), axis=-1)

    class ModelBSDF(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            spec = ModelMaterial.model_validate(json.loads(props["spec"]))
            self.model = models.get(spec.model, **spec.options)
            missing = [
                p.name
                for p in self.model.parameters
                if p.name not in spec.parameters and p.default is None
            ]
            if missing:
                raise ValueError(
                    f"model material {spec.model!r}: set parameters {', '.join(missing)}"
                )
            self.channels = model_channel_parameters(spec)
            # Glossy + diffuse reflection on the front side only (a one-sided opaque sample).
            self.m_flags = (
                mi.BSDFFlags.DiffuseReflection
                | mi.BSDFFlags.GlossyReflection
                | mi.BSDFFlags.FrontSide
            )
            self.m_components = [self.m_flags]
            self.eval_calls = 0
            _LIVE_MODEL_BSDFS.add(self)

        def _f_cos(self, si, wo):
            """f_r(to light = wo, to camera = si.wi)·cos θ_wo per channel, numpy (N, 3)."""
            self.eval_calls += 1
            to_cam = _dirs(si.wi)
            to_light = _dirs(wo)
            to_cam, to_light = np.broadcast_arrays(to_cam, to_light)
            n = to_cam.shape[0]
            out = np.empty((n, 3))
            same = self.channels[0] == self.channels[1] == self.channels[2]
            for c in range(3):
                if c and same:
                    out[:, c] = out[:, 0]
                    continue
                out[:, c] = self.model.evaluate(self.channels[c], to_light, to_cam)
            out *= np.clip(to_light[:, 2], 0.0, None)[:, None]
            return out

        def _color(self, arr):
            if variant.startswith("scalar"):
                return mi.Color3f(*[float(arr[0, c]) for c in range(3)])
            return mi.Color3f(*[mi.Float(arr[:, c].astype(np.float32)) for c in range(3)])

        def eval(self, ctx, si, wo, active=True):
            return self._color(self._f_cos(si, wo))

        def pdf(self, ctx, si, wo, active=True):
            return mi.warp.square_to_cosine_hemisphere_pdf(wo)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.wo = wo
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = 0
            # weight = f·cos/pdf; the camera side must be above the surface as well.
            value = self.eval(ctx, si, wo, active) / dr.maximum(bs.pdf, 1e-12)
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (bs.pdf > 0)
            return bs, dr.select(ok, value, 0.0)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"ModelBSDF[{self.model.name}]"

    mi.register_bsdf(MODEL_PLUGIN, lambda props: ModelBSDF(props))
    _REGISTERED.add(variant)
