"""Ground-truth f_r from a loaded Mitsuba BSDF — the one evaluation the renderer's truth and the
scene-material truth (simulator.truth) share.

Mitsuba's ``bsdf.eval(ctx, si, w)`` returns f_r(si.wi, w)·cos θ_w; the direct integrator calls
it with si.wi towards the camera and w towards the light, so we do the same and divide by
cos θ_i (docs/design.md §3). Below the horizon (either cosine ≤ 0) f_r = 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["eval_fr"]


def _frame(mi, si, uv=None):
    si.p = mi.Point3f(0.0, 0.0, 0.0)
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(
        mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0), mi.Vector3f(0.0, 0.0, 1.0)
    )
    si.uv = mi.Point2f(0.5, 0.5) if uv is None else uv
    return si


def eval_fr(bsdf, wi, wo, variant: str, *, wavefront: bool = False, uv=None) -> np.ndarray:
    """f_r (N, 3) in sr⁻¹ of `bsdf` (loaded in the active `variant`) for unit ``wi`` (to the
    light) and ``wo`` (to the camera), sample frame, (N, 3) each.

    ``wavefront``: evaluate with symbolic calls and loops off — a Python BSDF
    (simulator.materials) needs concrete arrays in the llvm variants. ``uv`` (N, 2): the
    surface point's texture coordinates (a textured BSDF, simulator.texture); default (½, ½).
    """
    import drjit as dr
    import mitsuba as mi

    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    n = wi.shape[0]
    ctx = mi.BSDFContext()
    if variant.startswith("scalar"):
        out = np.zeros((n, 3))
        si = _frame(mi, mi.SurfaceInteraction3f())
        for j in range(n):
            if uv is not None:
                si.uv = mi.Point2f(*(float(x) for x in uv[j]))
            si.wi = mi.Vector3f(*wo[j])
            v = bsdf.eval(ctx, si, mi.Vector3f(*wi[j]))
            out[j] = [v[0], v[1], v[2]]
    else:
        uv_mi = None if uv is None else mi.Point2f(np.asarray(uv)[:, 0], np.asarray(uv)[:, 1])
        si = _frame(mi, dr.zeros(mi.SurfaceInteraction3f, n), uv_mi)
        si.wi = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
        w = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
        if wavefront:
            with (
                dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False),
                dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False),
            ):
                v = bsdf.eval(ctx, si, w)
                dr.eval(v)
        else:
            v = bsdf.eval(ctx, si, w)
        out = np.stack([np.asarray(v[c], dtype=np.float64) for c in range(3)], axis=-1)
        out = np.broadcast_to(out, (n, 3)).copy()
    cos_i = wi[:, 2]
    valid = (cos_i > 0) & (wo[:, 2] > 0)
    f = np.zeros((n, 3))
    f[valid] = out[valid] / cos_i[valid, None]
    return f
