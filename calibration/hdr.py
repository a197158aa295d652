"""HDR merge of linear exposure brackets with noise-optimal weights.

Hasinoff, Durand & Freeman (2010), "Noise-optimal capture for high dynamic range photography";
Granados et al. (2010), "Optimal HDR reconstruction with linear digital cameras". For bracket i
with exposure t_i and signal s_i (electrons), the flux estimate is

    Φ̂ = Σ w_i s_i/t_i / Σ w_i,   w_i = t_i² / (g Φ̂ t_i + σ_read²),   Var(Φ̂) = 1 / Σ w_i,

with w_i = 0 where saturated. The weights depend on Φ̂, so we start from the longest unsaturated
exposure and iterate twice. Here signals are in electrons, so the gain g = 1. σ_read² may differ
per bracket (a dark frame's temporal variance grows with exposure through dark-current shot
noise): pass one value per bracket.

`merge_brackets_local` is the merge a reduction uses on images: the weights, the variance and
the choice of brackets come from each pixel's neighbours (a 3×3 same-colour mean without the
pixel itself), never from the pixel's own noisy value. Anything computed from the pixel's own
value and then used to weight or select that value is correlated with its noise, and the merged
flux (or a fit weighted by its σ) is biased by O(1/N_electrons), most of all next to the clip
level, where the long exposure survives only when it fluctuated low.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["merge_brackets", "merge_brackets_local", "merge_frames_local", "local_mean"]


def merge_brackets(
    electrons: list[np.ndarray],
    exposures_s: list[float],
    saturated: list[np.ndarray],
    read_noise_e: float | list[float] | np.ndarray,
    iterations: int = 2,
    flux_for_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge brackets → (flux e/s, variance (e/s)², all_saturated mask).

    ``read_noise_e``: signal-independent noise σ (electrons), a scalar or one per bracket.
    ``flux_for_weights``: an estimate of the flux that does not depend on this pixel's own
    noise (e.g. a local mean over neighbours). When given, the weights and the variance use it.
    Why: weights and a variance computed from the pixel's own noisy value are correlated with
    its noise — an upward fluctuation claims a larger variance and gets less weight — which
    biases any weighted fit by O(1/N_electrons). Invisible per pixel, that bias is several
    posterior σ once ~10⁴ samples of ~10⁴ e⁻ each are fitted together.
    """
    t = np.asarray(exposures_s, dtype=np.float64)
    s = np.stack([np.asarray(e, dtype=np.float64) for e in electrons])
    sat = np.stack([np.asarray(m, dtype=bool) for m in saturated])
    ok = ~sat
    shape = (-1,) + (1,) * (s.ndim - 1)
    tt = t.reshape(shape)
    # Initial estimate: the longest unsaturated exposure (best SNR under shot noise).
    order = np.argsort(t)[::-1]
    phi = np.full(s.shape[1:], np.nan)
    for i in order:
        fill = np.isnan(phi) & ok[i]
        phi[fill] = s[i][fill] / t[i]
    all_sat = np.isnan(phi)
    phi = np.where(all_sat, s[np.argmin(t)] / t.min(), phi)
    var_read = np.maximum(
        np.broadcast_to(np.asarray(read_noise_e, dtype=np.float64) ** 2, t.shape), 1e-12
    ).reshape(shape)
    for _ in range(iterations):
        w = np.where(ok, tt**2 / (np.maximum(phi, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
        est = np.divide((w * s / tt).sum(axis=0), wsum, out=np.zeros_like(phi), where=wsum > 0)
        phi = np.where(all_sat, phi, est)
    if flux_for_weights is not None:
        ref = np.where(np.isfinite(flux_for_weights), flux_for_weights, phi)
        w = np.where(ok, tt**2 / (np.maximum(ref, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
        est = np.divide((w * s / tt).sum(axis=0), wsum, out=np.zeros_like(phi), where=wsum > 0)
        phi = np.where(all_sat, phi, est)
    else:
        w = np.where(ok, tt**2 / (np.maximum(phi, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
    var = np.divide(1.0, wsum, out=np.full_like(phi, np.inf), where=wsum > 0)
    return phi, var, all_sat


def merge_brackets_local(
    electrons: list[np.ndarray],
    exposures_s: list[float],
    saturated: list[np.ndarray],
    read_noise_e: float | list[float] | np.ndarray,
    clip_e: float | list[float | np.ndarray],
    *,
    valid: np.ndarray | None = None,
    cfa: bool = False,
    margin_sigma: float = 5.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge an image's brackets with weights, variance and bracket choice from the neighbours.

    → (flux e/s, variance (e/s)², all_saturated mask), like `merge_brackets`.

    ``saturated``: per bracket, the pixels at the camera's clip level (their value is unknown).
    ``clip_e``: that clip level in the same electrons as ``electrons`` (after black or dark
    subtraction): a scalar, or one value or per-pixel map per bracket (a master dark's level
    varies per pixel and exposure, and the clip sits at white − dark). ``valid``: pixels whose
    flux may enter their neighbours' local estimate (e.g. the ones on the sample: holder or
    background neighbours would pull an edge pixel's estimate down and understate its
    variance); None = all. ``cfa``: the frames are a 2×2 colour mosaic (neighbours are the
    same-colour photosites).

    Steps: (1) a first merge (`merge_brackets`, own-value weights) gives every pixel a flux;
    (2) each pixel's reference flux is the mean of its neighbours' (`local_mean`), independent
    of its own noise; (3) a bracket whose expected signal Φ_ref·t_i is within ``margin_sigma``
    σ of the clip, Φ_ref t_i + k √(Φ_ref t_i + σ_read,i²) ≥ clip, is dropped whatever the
    pixel's own value (values at the clip are always dropped): dropping it only when the
    pixel's own value crossed the clip keeps it exactly when it fluctuated low; (4) the final
    merge weights the kept brackets by w_i = t_i²/(Φ_ref t_i + σ_read,i²) and reports
    Var = 1/Σ w_i at Φ_ref (Hasinoff et al. 2010). Given the neighbours, the weights are
    constants, so the merged flux is an unbiased mean of unbiased bracket estimates.
    """
    t = np.asarray(exposures_s, dtype=np.float64)
    read_e = np.broadcast_to(np.asarray(read_noise_e, dtype=np.float64), t.shape)
    flux, _var, all_sat = merge_brackets(electrons, exposures_s, saturated, read_e)
    ok = ~all_sat
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.ndim < flux.ndim:  # a (H, W) mask for (H, W, C) frames
            valid = np.broadcast_to(valid[..., None], flux.shape)
        ok = ok & valid
    local = local_mean(flux, ok, cfa=cfa)
    ref = np.maximum(np.where(np.isfinite(local), local, flux), 0.0)
    clips = clip_e if isinstance(clip_e, list | tuple) else [clip_e] * t.size
    if len(clips) != t.size:
        raise ValueError(f"clip_e: {len(clips)} values for {t.size} brackets")
    sats = []
    for i, ti in enumerate(t):
        expected = ref * ti
        near = expected + margin_sigma * np.sqrt(expected + read_e[i] ** 2) >= clips[i]
        sats.append(np.asarray(saturated[i], dtype=bool) | near)
    return merge_brackets(electrons, exposures_s, sats, read_e, flux_for_weights=local)


def local_mean(flux: np.ndarray, valid: np.ndarray, *, cfa: bool) -> np.ndarray:
    """Mean flux of each pixel's same-colour 3×3 neighbourhood, the pixel itself excluded
    (so the estimate is independent of its own noise); NaN where no valid neighbour exists.
    ``flux`` is (H, W) or (H, W, C); with ``cfa`` the four 2×2 mosaic phases are separate."""
    from scipy.ndimage import uniform_filter

    out = np.full(flux.shape, np.nan)
    planes = (
        [(slice(i, None, 2), slice(j, None, 2)) for i in (0, 1) for j in (0, 1)]
        if cfa
        else [(slice(None), slice(None))]
    )
    for sl in planes:
        f = np.where(valid[sl], flux[sl], 0.0)
        v = valid[sl].astype(np.float64)
        size = (3, 3) + (1,) * (f.ndim - 2)
        tot = uniform_filter(f, size=size, mode="constant") * 9.0 - f
        cnt = uniform_filter(v, size=size, mode="constant") * 9.0 - v
        with np.errstate(invalid="ignore", divide="ignore"):
            out[sl] = np.where(cnt > 0.5, tot / np.maximum(cnt, 1e-12), np.nan)
    return out


def merge_frames_local(
    dn: np.ndarray,
    offset_dn: np.ndarray,
    gain_e_per_dn: float,
    white_dn: float,
    exposures_s: list[float],
    read_noise_e: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    cfa: bool = False,
    margin_sigma: float = 5.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`merge_brackets_local` from the raw frames in one compiled pass per step (the same
    maths, without its whole-image float64 temporaries: about 20 of them per bracket).

    ``dn``: the brackets' raw values (B, H, W) or (B, H, W, C); ``offset_dn``: the value each
    one reads at zero signal (the master dark of its exposure, or the black level broadcast),
    same shape. Electrons are (DN − offset)·gain, a bracket is saturated at DN ≥ white − ½
    and clips at (white − offset)·gain electrons, as calibration.planes.merge_pose forms them
    for `merge_brackets_local`. Returns (flux e/s, variance (e/s)², all_saturated mask).
    """
    b = dn.shape[0]
    if offset_dn.shape != dn.shape:
        raise ValueError(f"offset_dn shape {offset_dn.shape} ≠ dn shape {dn.shape}")
    four = dn.ndim == 4
    dn4 = dn if four else dn[..., None]
    off4 = offset_dn if four else offset_dn[..., None]
    shape = dn4.shape[1:]
    ok_valid = np.ones(shape, bool) if valid is None else np.asarray(valid, bool)
    if ok_valid.ndim == 2:
        ok_valid = np.broadcast_to(ok_valid[..., None], shape)
    t = np.asarray(exposures_s, dtype=np.float64)
    read_e = np.broadcast_to(np.asarray(read_noise_e, dtype=np.float64), t.shape).copy()
    if t.size != b:
        raise ValueError(f"{t.size} exposures for {b} brackets")
    flux = np.empty(shape)
    var = np.empty(shape)
    all_sat = np.empty(shape, bool)
    _merge_local_kernel(
        dn4,
        off4,
        float(gain_e_per_dn),
        float(white_dn),
        t,
        read_e,
        ok_valid,
        2 if cfa else 1,
        float(margin_sigma),
        (flux, var, all_sat),
    )
    if not four:
        flux, var, all_sat = flux[..., 0], var[..., 0], all_sat[..., 0]
    return flux, var, all_sat


@numba.njit(cache=True)
def _own_merge(s, ok, t, var_read, order, shortest):  # noqa: ANN001, ANN202
    """`merge_brackets` for one pixel with own-value weights, 2 iterations → (Φ, all_sat)."""
    phi = np.nan
    for i in order:
        if ok[i]:
            phi = s[i] / t[i]
            break
    if np.isnan(phi):
        return s[shortest] / t[shortest], True
    for _ in range(2):
        phi = _weighted(s, ok, t, var_read, phi)[0]
    return phi, False


@numba.njit(cache=True)
def _weighted(s, ok, t, var_read, ref):  # noqa: ANN001, ANN202
    """(Σ wᵢ sᵢ/tᵢ / Σ wᵢ, Σ wᵢ) with wᵢ = tᵢ²/(max(ref, 0)·tᵢ + σ²ᵢ) on kept brackets, summed
    in bracket order as numpy's axis-0 sums are (0 where no bracket is kept)."""
    ref = max(ref, 0.0)
    wsum = 0.0
    acc = 0.0
    for i in range(s.shape[0]):
        w = t[i] ** 2 / (ref * t[i] + var_read[i]) if ok[i] else 0.0
        wsum += w
        acc += w * s[i] / t[i]
    return (acc / wsum if wsum > 0 else 0.0), wsum


@numba.njit(cache=True)
def _electrons(dn, off, gain, white, y, x, c, s, ok):  # noqa: ANN001
    """One pixel's brackets in electrons into `s`, and `ok` = not saturated (DN ≥ white − ½)."""
    for i in range(dn.shape[0]):
        v = np.float64(dn[i, y, x, c])
        s[i] = (v - off[i, y, x, c]) * gain
        ok[i] = not (v >= white - 0.5)


@numba.njit(cache=True, parallel=True)
def _merge_local_kernel(dn, off, gain, white, t, read_e, valid, stride, margin, out):  # noqa: ANN001
    """Both steps of merge_frames_local: (1) the own-value merge of every pixel that may serve
    as a neighbour (valid ones); (2) per pixel, the neighbours' mean flux (same colour: `stride`
    2 in a mosaic), the brackets near the clip dropped by it, and the merge weighted by it
    (`merge_brackets_local`'s steps 2–4). Rows run in parallel; every pixel's arithmetic is
    its own, so the result does not depend on the number of threads."""
    flux, var, all_sat = out
    nb, h, w, nc = dn.shape
    var_read = np.maximum(read_e**2, 1e-12)
    order = np.argsort(t)[::-1]
    shortest = np.argmin(t)
    first = np.empty((h, w, nc))
    usable = np.zeros((h, w, nc), np.bool_)
    for y in numba.prange(h):
        s = np.empty(nb)
        ok = np.empty(nb, np.bool_)
        for x in range(w):
            for c in range(nc):
                if valid[y, x, c]:
                    _electrons(dn, off, gain, white, y, x, c, s, ok)
                    phi, sat = _own_merge(s, ok, t, var_read, order, shortest)
                    first[y, x, c] = phi
                    usable[y, x, c] = not sat
    for y in numba.prange(h):
        s = np.empty(nb)
        ok = np.empty(nb, np.bool_)
        for x in range(w):
            for c in range(nc):
                tot = 0.0
                cnt = 0
                for dy in (-stride, 0, stride):
                    for dx in (-stride, 0, stride):
                        yy, xx = y + dy, x + dx
                        if (dy or dx) and 0 <= yy < h and 0 <= xx < w and usable[yy, xx, c]:
                            tot += first[yy, xx, c]
                            cnt += 1
                _electrons(dn, off, gain, white, y, x, c, s, ok)
                if cnt:
                    local = tot / cnt
                    ref = max(local, 0.0)
                else:  # no neighbour: the pixel's own merge (merge_brackets_local's fallback)
                    local = _own_merge(s, ok, t, var_read, order, shortest)[0]
                    ref = max(local, 0.0)
                for i in range(nb):
                    clip = (white - off[i, y, x, c]) * gain
                    expected = ref * t[i]
                    near = expected + margin * np.sqrt(expected + read_e[i] ** 2) >= clip
                    ok[i] = ok[i] and not near
                if not ok.any():  # every bracket dropped: the shortest's value, unknown
                    flux[y, x, c] = s[shortest] / t[shortest]
                    var[y, x, c], all_sat[y, x, c] = np.inf, True
                    continue
                # Without neighbours the weights come from the pixel's own merge with the kept
                # brackets, as merge_brackets(flux_for_weights=local) falls back where NaN.
                ref_w = local if cnt else _own_merge(s, ok, t, var_read, order, shortest)[0]
                est, wsum = _weighted(s, ok, t, var_read, ref_w)
                flux[y, x, c] = est
                var[y, x, c] = 1.0 / wsum if wsum > 0 else np.inf
                all_sat[y, x, c] = False
