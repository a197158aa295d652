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

from dataclasses import dataclass

import numba
import numpy as np

from plumbing.numba_policy import dispatch

__all__ = [
    "merge_brackets",
    "merge_brackets_local",
    "merge_frames_local",
    "RawBrackets",
    "local_mean",
]


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


@dataclass(frozen=True)
class RawBrackets:
    """One pose's brackets as the camera recorded them, for `merge_frames_local`.

    ``dn``: raw values (B, H, W) or (B, H, W, C); ``offset_dn``: what each reads at zero
    signal (the master dark of its exposure, or the black level broadcast), same shape;
    ``exposures_s`` (B,); ``read_noise_e``: signal-independent noise σ per bracket (e⁻);
    ``gain_e_per_dn``; ``white_dn``: the clip level (a bracket is saturated at DN ≥ white − ½
    and clips at (white − offset)·gain electrons)."""

    dn: np.ndarray
    offset_dn: np.ndarray
    exposures_s: list[float]
    read_noise_e: np.ndarray
    gain_e_per_dn: float
    white_dn: float


def merge_frames_local(
    brackets: RawBrackets,
    *,
    valid: np.ndarray | None = None,
    cfa: bool = False,
    margin_sigma: float = 5.0,
    flat: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`merge_brackets_local` from the raw frames in one compiled pass over the rows, its two
    steps interleaved (the same maths, without its whole-image float64 temporaries: about 20
    of them per bracket).

    Electrons are (DN − offset)·gain, as calibration.planes.merge_pose forms them for
    `merge_brackets_local`; ``valid``, ``cfa`` and ``margin_sigma`` are its arguments.
    ``flat``: a flat field's (gain, relative variance), frame-shaped, applied to the merged
    flux in the same pass as calibration.flatfield.FlatField.apply does (Φ/g, Var/g² + Φ'²·v).
    Returns (flux e/s, variance (e/s)², all_saturated mask).
    """
    dn, offset_dn = brackets.dn, brackets.offset_dn
    exposures_s, read_noise_e = brackets.exposures_s, brackets.read_noise_e
    gain_e_per_dn, white_dn = brackets.gain_e_per_dn, brackets.white_dn
    b = dn.shape[0]
    if offset_dn.shape != dn.shape:
        raise ValueError(f"offset_dn shape {offset_dn.shape} ≠ dn shape {dn.shape}")
    four = dn.ndim == 4
    shape = dn.shape[1:]
    h, w, nc = shape[0], shape[1], (shape[2] if four else 1)
    ok_valid = np.ones((h, w), bool) if valid is None else np.asarray(valid, bool)
    if ok_valid.ndim == 2 and four:  # a (H, W) mask for (H, W, C) frames
        ok_valid = np.broadcast_to(ok_valid[..., None], shape)
    t = np.asarray(exposures_s, dtype=np.float64)
    read_e = np.broadcast_to(np.asarray(read_noise_e, dtype=np.float64), t.shape).copy()
    if t.size != b:
        raise ValueError(f"{t.size} exposures for {b} brackets")
    flux = np.empty((h, w * nc))
    var = np.empty((h, w * nc))
    all_sat = np.empty((h, w * nc), bool)
    step = 2 if cfa else 1  # a mosaic's same-colour neighbours are 2 photosites away
    frames = (
        np.ascontiguousarray(dn).reshape(b, h, w * nc),
        # A view where the strides allow (a window of the darks' stack, a broadcast level),
        # read-only whatever it was: numba compiles a kernel per argument type, and a writable
        # window, a read-only broadcast and a stack were three compiles of the merge (~10 CPU-s
        # each on a fresh checkout) where two now serve (the windows and the stacks).
        _read_only(np.asarray(offset_dn, dtype=np.float64).reshape(b, h, w * nc)),
        float(gain_e_per_dn),
        float(white_dn),
        t,
        read_e,
        np.ascontiguousarray(ok_valid).reshape(h, w * nc),
        step,
        step * nc,
        float(margin_sigma),
    )
    if flat is None:
        field = (np.ones((1, 1)), np.zeros((1, 1)), False)
    else:
        field = tuple(np.asarray(a, dtype=np.float64).reshape(h, w * nc) for a in flat)
        field = (*field, True)
    out = (flux, var, all_sat)
    # Threads for large frames when they pay (the fitting kernels' policy: plumbing.numba_policy).
    dispatch("hdr_merge", _merge_par, _merge_ser, h * w * nc, frames, field, out)
    return flux.reshape(shape), var.reshape(shape), all_sat.reshape(shape)


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of `a` (no copy)."""
    view = a.view()
    view.flags.writeable = False
    return view


# The kernel works a row at a time in branch-free loops over the row's values (masks as 0/1
# floats, selects instead of branches) so that LLVM vectorises them: per pixel the merge is a
# short chain of dependent divisions, which scalar code waits on (≈ 110 ns a photosite).


@numba.njit(cache=True, nogil=True)
def _row_electrons(dn, off, gain, white, y, s, ok):
    """Row y of every bracket in electrons into s[i], and ok[i] = 1.0 where not saturated
    (DN < white − ½), 0.0 where saturated."""
    for i in range(dn.shape[0]):
        d, o, si, oki = dn[i, y], off[i, y], s[i], ok[i]
        for x in range(si.shape[0]):
            v = np.float64(d[x])
            si[x] = (v - o[x]) * gain
            oki[x] = 1.0 if v < white - 0.5 else 0.0


@numba.njit(cache=True, nogil=True)
def _row_weighted(s, ok, t, var_read, ref, scratch, est, var):
    """Per value x of a row: est = Σ wᵢ sᵢ/tᵢ / Σ wᵢ and var = 1/Σ wᵢ over kept brackets
    (ok = 1), wᵢ = tᵢ²/Dᵢ, Dᵢ = max(ref, 0)·tᵢ + σ²ᵢ — as one fraction: with P = Πⱼ Dⱼ and
    Pᵢ = P/Dᵢ (products over kept j ≠ i), est = Σ tᵢ sᵢ Pᵢ / Σ tᵢ² Pᵢ, var = P / Σ tᵢ² Pᵢ: one
    division instead of 2B + 1. Dᵢ ≤ ~10⁶ and B ≤ ~10 keep the products far inside float64's
    range. (NaN, ∞) where no bracket is kept."""
    if s.shape[0] in (2, 3):
        _row_weighted_fused(s, ok, t, var_read, ref, est, var)
    else:
        _row_weighted_general(s, ok, t, var_read, ref, scratch, est, var)


@numba.njit(cache=True, nogil=True)
def _row_weighted_general(s, ok, t, var_read, ref, scratch, est, var):
    """`_row_weighted` for any number of brackets, one operation per pass over the row."""
    nb, n = s.shape
    big_d, others, num, den, prod = scratch
    for i in range(nb):
        di, oki = big_d[i], ok[i]
        for x in range(n):
            di[x] = max(ref[x], 0.0) * t[i] + var_read[i] if oki[x] != 0.0 else 1.0
    for x in range(n):
        num[x] = 0.0
        den[x] = 0.0
        prod[x] = 1.0
    for i in range(nb):
        oki, di, si = ok[i], big_d[i], s[i]
        for x in range(n):
            others[x] = oki[x]  # a dropped bracket's terms vanish, its D is 1 in the others'
            prod[x] *= di[x]
        for j in range(nb):
            if j != i:
                dj = big_d[j]
                for x in range(n):
                    others[x] *= dj[x]
        for x in range(n):
            num[x] += t[i] * si[x] * others[x]
            den[x] += t[i] * t[i] * others[x]
    for x in range(n):
        inv = 1.0 / den[x] if den[x] > 0 else np.nan
        est[x] = num[x] * inv
        var[x] = prod[x] * inv if den[x] > 0 else np.inf


@numba.njit(cache=True, nogil=True)
def _row_weighted_fused(s, ok, t, var_read, ref, est, var):
    """`_row_weighted` for 2 or 3 brackets in one pass over the row (the general form makes
    ~17 passes of one operation each; this one keeps a value's terms in registers), with the
    same operations in the same order, so bit for bit the same."""
    n = s.shape[1]
    s0, s1, ok0, ok1 = s[0], s[1], ok[0], ok[1]
    t0, t1, v0, v1 = t[0], t[1], var_read[0], var_read[1]
    if s.shape[0] == 2:
        for x in range(n):
            r = max(ref[x], 0.0)
            d0 = r * t0 + v0 if ok0[x] != 0.0 else 1.0
            d1 = r * t1 + v1 if ok1[x] != 0.0 else 1.0
            o0 = ok0[x] * d1
            o1 = ok1[x] * d0
            num = (0.0 + t0 * s0[x] * o0) + t1 * s1[x] * o1
            den = (0.0 + t0 * t0 * o0) + t1 * t1 * o1
            prod = 1.0 * d0 * d1
            inv = 1.0 / den if den > 0 else np.nan
            est[x] = num * inv
            var[x] = prod * inv if den > 0 else np.inf
        return
    s2, ok2, t2, v2 = s[2], ok[2], t[2], var_read[2]
    for x in range(n):
        r = max(ref[x], 0.0)
        d0 = r * t0 + v0 if ok0[x] != 0.0 else 1.0
        d1 = r * t1 + v1 if ok1[x] != 0.0 else 1.0
        d2 = r * t2 + v2 if ok2[x] != 0.0 else 1.0
        o0 = ok0[x] * d1 * d2
        o1 = ok1[x] * d0 * d2
        o2 = ok2[x] * d0 * d1
        num = ((0.0 + t0 * s0[x] * o0) + t1 * s1[x] * o1) + t2 * s2[x] * o2
        den = ((0.0 + t0 * t0 * o0) + t1 * t1 * o1) + t2 * t2 * o2
        prod = 1.0 * d0 * d1 * d2
        inv = 1.0 / den if den > 0 else np.nan
        est[x] = num * inv
        var[x] = prod * inv if den > 0 else np.inf


@numba.njit(cache=True, nogil=True)
def _row_own_merge(s, ok, t, var_read, shortest, scratch, phi, sat, tmp):
    """`merge_brackets` with own-value weights along a row: Φ starts at the longest kept
    bracket's sᵢ/tᵢ, then two weighted iterations; where no bracket is kept (sat = 1) Φ is the
    shortest bracket's sᵢ/tᵢ (its value is unknown)."""
    nb, n = s.shape
    for x in range(n):
        phi[x] = np.nan
    for i in np.argsort(t):  # the longest kept bracket is written last
        si, oki = s[i], ok[i]
        for x in range(n):
            phi[x] = si[x] / t[i] if oki[x] != 0.0 else phi[x]
    for x in range(n):
        sat[x] = 1.0 if np.isnan(phi[x]) else 0.0
        phi[x] = s[shortest, x] / t[shortest] if sat[x] != 0.0 else phi[x]
    est, var = tmp
    for _ in range(2):
        _row_weighted(s, ok, t, var_read, phi, scratch, est, var)
        for x in range(n):
            phi[x] = phi[x] if sat[x] != 0.0 else est[x]


@numba.njit(cache=True, nogil=True)
def _row_scratch(nb, n):
    """The general weighted mean's buffers (empty for the fused one's 2 or 3 brackets)."""
    m = 0 if nb in (2, 3) else n
    return (np.empty((nb, m)), np.empty(m), np.empty(m), np.empty(m), np.empty(m))


@numba.njit(cache=True, nogil=True)
def _own_merge_where(s, ok, t, var_read, shortest, cnt, dropped, n_own, ref):
    """ref[x] = the own-value merge of the kept brackets for the `n_own` values x with no
    usable neighbour (cnt = 0) and a bracket dropped (dropped ≠ 0), gathered into rows of their
    own: every value's merge is its own arithmetic, so it is the whole row's bit for bit."""
    nb, n = s.shape
    at = np.empty(n_own, np.int64)
    k = 0
    for x in range(n):
        if cnt[x] == 0.0 and dropped[x] != 0.0:
            at[k] = x
            k += 1
    s_own, ok_own = np.empty((nb, n_own)), np.empty((nb, n_own))
    for i in range(nb):
        for k in range(n_own):
            s_own[i, k] = s[i, at[k]]
            ok_own[i, k] = ok[i, at[k]]
    phi, sat = np.empty(n_own), np.empty(n_own)
    scratch, tmp = _row_scratch(nb, n_own), (np.empty(n_own), np.empty(n_own))
    _row_own_merge(s_own, ok_own, t, var_read, shortest, scratch, phi, sat, tmp)
    for k in range(n_own):
        ref[at[k]] = phi[k]


@numba.njit(cache=True, nogil=True)
def _first_row(y, frames, noise, s, ok, first, fu, us):
    """Step 1 for row y, whose electrons are `s`, `ok`: every value's own-value merge into
    `first`, and whether it may serve as a neighbour (valid and not all saturated) into the
    padded rows `us` (1/0) and `fu` (its merge where usable, 0 elsewhere). `noise` = (read
    variances, index of the shortest bracket), from `_merge_band`."""
    _dn, _off, _gain, _white, t, _read_e, valid, _sy, sx, _margin = frames
    var_read, shortest = noise
    nb, n = s.shape
    phi, sat = np.empty(n), np.empty(n)
    scratch, tmp = _row_scratch(nb, n), (np.empty(n), np.empty(n))
    _row_own_merge(s, ok, t, var_read, shortest, scratch, phi, sat, tmp)
    v = valid[y]
    for x in range(n):
        first[x] = phi[x]
        u = 1.0 if v[x] and sat[x] == 0.0 else 0.0
        us[x + sx] = u
        fu[x + sx] = phi[x] if u != 0.0 else 0.0


@numba.njit(cache=True, nogil=True)
def _final_row(y, frames, field, noise, s, ok, first, near_rows, out):
    """Step 2 for row y, whose electrons are `s`, `ok` (its clip test drops brackets from
    `ok`): the neighbours' mean, the brackets near the clip dropped by it, and the merge
    weighted by it (or by the value's own merge `first` where it has no usable neighbour),
    divided by the flat `field` = (gain, relative variance, applied?). `near_rows` are step
    1's padded (fu, us) rows of y − sy, y and y + sy."""
    _dn, off, gain, white, t, read_e, _valid, _sy, sx, margin = frames
    flat_gain, flat_rel_var, apply_flat = field
    flux, var, all_sat = out
    var_read, shortest = noise
    nb, n = s.shape
    tot, cnt, ref = np.empty(n), np.empty(n), np.empty(n)
    dropped, kept = np.zeros(n), np.zeros(n)
    # The 8 neighbours (rows y ∓ sy, y; columns x ∓ sx, x) in one pass, added in the order
    # row by row, column by column; column x + sx of a padded row is column x.
    fu0, fu1, fu2, us0, us1, us2 = near_rows
    for x in range(n):
        a, b, c = x, x + sx, x + 2 * sx
        tot_x = ((((((0.0 + fu0[a]) + fu0[b]) + fu0[c]) + fu1[a]) + fu1[c]) + fu2[a]) + fu2[b]
        tot_x += fu2[c]
        cnt_x = ((((((0.0 + us0[a]) + us0[b]) + us0[c]) + us1[a]) + us1[c]) + us2[a]) + us2[b]
        cnt_x += us2[c]
        cnt[x] = cnt_x
        tot[x] = tot_x / cnt_x if cnt_x > 0 else np.nan  # the neighbours' mean
        ref[x] = max(tot[x] if cnt_x > 0 else first[x], 0.0)
    for i in range(nb):
        oki, offi = ok[i], off[i, y]
        for x in range(n):
            expected = ref[x] * t[i]
            near = expected + margin * np.sqrt(expected + read_e[i] ** 2)
            keep = near < (white - offi[x]) * gain
            dropped[x] += 0.0 if keep else oki[x]
            oki[x] = oki[x] if keep else 0.0
            kept[x] += oki[x]
    # Where no neighbour is usable the weights come from the value's own merge of the kept
    # brackets. Step 1 stored that merge (`first`) for the brackets kept then; it is recomputed
    # only for the few values the clip test above dropped a bracket of (the off-sample border
    # is most of a row's values and seldom near the clip: recomputing it all was 2 of the
    # step's 3 weighted passes).
    n_own = 0
    for x in range(n):
        ref[x] = tot[x] if cnt[x] > 0 else first[x]
        n_own += 1 if cnt[x] == 0.0 and dropped[x] != 0.0 else 0
    if n_own:
        _own_merge_where(s, ok, t, var_read, shortest, cnt, dropped, n_own, ref)
    scratch, tmp = _row_scratch(nb, n), (np.empty(n), np.empty(n))
    est, v = tmp
    _row_weighted(s, ok, t, var_read, ref, scratch, est, v)
    for x in range(n):
        none = kept[x] == 0.0
        phi_x = s[shortest, x] / t[shortest] if none else est[x]
        var_x = np.inf if none else v[x]
        if apply_flat:  # as FlatField.apply: Φ' = Φ/g, Var Φ' = Var Φ/g² + Φ'²·Var g/g²
            g = flat_gain[y, x]
            phi_x = phi_x / g
            var_x = var_x / (g * g) + (phi_x * phi_x) * flat_rel_var[y, x]
        flux[y, x] = phi_x
        var[y, x] = var_x
        all_sat[y, x] = none


#: Rows per work item of the threaded merge: each item recomputes step 1 for the 2·sy rows
#: beyond its ends (its neighbours' halo), 2·2/64 ≈ 6 % of step 1 for a mosaic.
_BAND_ROWS = 64


@numba.njit(cache=True, nogil=True)
def _merge_band(frames, field, out, y0, y1):
    """Both steps for rows y0 ≤ y < y1, interleaved: step 1 runs sy rows ahead of step 2 (its
    own rows y0 − sy … y1 + sy − 1, within the frame), so a row's electrons are computed once,
    for both steps, and the steps' state is a band of rows, not whole-frame arrays. Zero rows
    and columns pad the band's state: outside the frame no value is usable."""
    dn, off, gain, white, sy, sx = frames[0], frames[1], frames[2], frames[3], frames[7], frames[8]
    nb, h, n = dn.shape
    lo, hi = max(y0 - sy, 0), min(y1 + sy, h)
    base = y0 - sy  # the state's row 0
    rows = y1 - y0 + 2 * sy
    first = np.empty((rows, n))
    fu, us = np.zeros((rows, n + 2 * sx)), np.zeros((rows, n + 2 * sx))
    ring = sy + 1  # electrons of rows y − sy … y: step 2 of row y − sy needs them
    noise = (np.maximum(frames[5] ** 2, 1e-12), np.argmin(frames[4]))  # once, not per row
    s_ring, ok_ring = np.empty((ring, nb, n)), np.empty((ring, nb, n))
    for y in range(lo, y1 + sy):
        if y < hi:
            k, r = y % ring, y - base
            _row_electrons(dn, off, gain, white, y, s_ring[k], ok_ring[k])
            _first_row(y, frames, noise, s_ring[k], ok_ring[k], first[r], fu[r], us[r])
        yf = y - sy  # every step-1 row around it is done
        if y0 <= yf < y1:
            k, r = yf % ring, yf - base
            near = (fu[r - sy], fu[r], fu[r + sy], us[r - sy], us[r], us[r + sy])
            _final_row(yf, frames, field, noise, s_ring[k], ok_ring[k], first[r], near, out)


@numba.njit(cache=True, parallel=True, nogil=True)
def _merge_par(frames, field, out):
    """merge_frames_local's two steps on rows of values (B, H, W·C), bands of rows in parallel:
    each value's arithmetic is its own, so the result is the serial twin's bit for bit.
    `frames` = (dn, offset, gain, white, t, read σ, valid, the neighbours' strides in rows and
    in values, margin σ)."""
    h = frames[0].shape[1]
    n_bands = (h + _BAND_ROWS - 1) // _BAND_ROWS
    for b in numba.prange(n_bands):
        # int64 rows, as the serial twin passes them (prange's index is unsigned): one compiled
        # _merge_band for both, not a second ~15 CPU-s compile of its whole call tree
        y0 = np.int64(b * _BAND_ROWS)
        _merge_band(frames, field, out, y0, np.int64(min(y0 + _BAND_ROWS, h)))


@numba.njit(cache=True, nogil=True)
def _merge_ser(frames, field, out):
    """`_merge_par` on one thread (small frames, or cores busy: plumbing.numba_policy.dispatch), as
    one band: no halo to recompute."""
    _merge_band(frames, field, out, 0, frames[0].shape[1])
