"""Sample-region segmentation from the image itself, checked against the geometric footprint.

The geometric footprint (calibration.geometry: the sample square projected through the camera
model) is only as good as the calibrated sample pose, arm offsets and stated sample size. The
image shows where the sample really is: its edge against the holder or the background is a
*step* in radiance, while the sample's own radiance varies smoothly (a BRDF lobe changes by
≲ 1 % between adjacent pixels at this rig's ~0.1°/pixel). The sample's image is a convex
quadrilateral (a rectangle through a pinhole), so each of its four sides is found as a straight
edge near the predicted one:

1. ℓ = ln Φ of the (dark-subtracted, flat-corrected) flux summed over colours, floored at 3σ of
   the noise (a black background is then flat, not log-noise); σ_ℓ = σ_Φ/Φ (first-order error
   propagation), 0 on the floor.
2. Each predicted side is cut into segments of ~12 px. For every offset d ∈ [−band, +band]
   (0.25 px steps) along the side's outward normal n̂, the mean step across the side,
   s(d) = |⟨ℓ(x + (d+1)n̂) − ℓ(x + (d−1)n̂)⟩| (bilinear samples), is computed. An edge is a
   local maximum of s that stands out of s(d ± 2.5 px) by more than max(k·σ_s, τ) — k = 5
   noise σ and τ = 8 % (the smallest reflectance step called an edge; a lobe's smooth gradient
   has no such prominence) — and the sample's edge is the *innermost* one (the holder's own
   outer edge, often much stronger, lies beyond). The segments' edge offsets are fitted with a line
   d(t) = α + βt (a side may shift and tilt); a side with fewer than two detected segments
   keeps its predicted position (the image says nothing there: a dark sample on a black
   background, a holder as bright as the sample).
3. The four fitted lines bound the segmented quadrilateral; a pixel is in it when its centre is
   (so a pixel more than about half covered by the sample is in).

The caller intersects the result with the footprint: pixels the geometry puts on the sample but
the image does not (holder, background, a mis-estimated pose) are marked MASKED. A mis-estimated
pose larger than ``band_px`` cannot be corrected (the search window misses the edge) — the
quadrilateral then keeps the prediction on that side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

import plumbing.numba_policy  # noqa: F401 — the vector width, chosen before a kernel here compiles

__all__ = ["Segmentation", "segment_sample", "iou", "polygon_mask"]


@dataclass(frozen=True)
class Segmentation:
    mask: np.ndarray  # bool (H, W): pixel centres inside the segmented quadrilateral
    corners_px: np.ndarray  # (4, 2) its corners (u, v)
    sides_found: int  # sides located in the image (the others kept their predicted position)
    offsets_px: np.ndarray  # (4, 2) outward shift of each side at its two ends (0 = predicted)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def _ccw(corners: np.ndarray) -> np.ndarray:
    c = corners.mean(axis=0)
    ang = np.arctan2(corners[:, 1] - c[1], corners[:, 0] - c[0])
    return corners[np.argsort(ang)]


def polygon_mask(shape: tuple[int, int], corners_px: np.ndarray) -> np.ndarray:
    """Pixels (H, W) whose centre (integer u, v) lies inside the convex polygon ``corners_px``."""
    pts = _ccw(np.asarray(corners_px, dtype=np.float64))
    inside = np.empty(shape, bool)
    _inside_convex(pts, inside)
    return inside


@numba.njit(cache=True, nogil=True)
def _inside_convex(pts, inside):
    """inside[v, u] = (u, v) is on the inner side of every edge a→b of the counter-clockwise
    polygon `pts`: (b − a) × (p − a) ≥ 0, one pixel at a time (no (H, W) temporaries)."""
    n = pts.shape[0]
    for v in range(inside.shape[0]):
        fv = float(v)
        for u in range(inside.shape[1]):
            fu = float(u)
            ok = True
            for k in range(n):
                a0, a1 = pts[k, 0], pts[k, 1]
                b0, b1 = pts[(k + 1) % n, 0], pts[(k + 1) % n, 1]
                ok &= (b0 - a0) * (fv - a1) - (b1 - a1) * (fu - a0) >= 0
            inside[v, u] = ok


@numba.njit(cache=True, nogil=True)
def _bilinear(img, u, v):
    """`img` at (u, v) = (column, row), bilinear, the edge values beyond the image (as
    scipy.ndimage.map_coordinates(order=1, mode="nearest"): tests/calibration/test_segmentation.py).
    """
    h, w = img.shape
    u0, v0 = np.floor(u), np.floor(v)
    fu, fv = u - u0, v - v0
    iu, iv = int(u0), int(v0)
    c0, c1 = min(max(iu, 0), w - 1), min(max(iu + 1, 0), w - 1)
    r0, r1 = min(max(iv, 0), h - 1), min(max(iv + 1, 0), h - 1)
    top = img[r0, c0] * (1.0 - fu) + img[r0, c1] * fu
    bottom = img[r1, c0] * (1.0 - fu) + img[r1, c1] * fu
    return top * (1.0 - fv) + bottom * fv


@numba.njit(cache=True, nogil=True)
def _steps_across(ell, var_ell, p_out, p_in):
    """ℓ(p_out) − ℓ(p_in) and σ²_ℓ(p_out) + σ²_ℓ(p_in) at every (offset, position) of a side
    (p_* of shape (D, T, 2), (u, v) last): the four bilinear samples in one pass."""
    n_d, n_t = p_out.shape[0], p_out.shape[1]
    diff = np.empty((n_d, n_t))
    var = np.empty((n_d, n_t))
    for i in range(n_d):
        for j in range(n_t):
            uo, vo, ui, vi = p_out[i, j, 0], p_out[i, j, 1], p_in[i, j, 0], p_in[i, j, 1]
            diff[i, j] = _bilinear(ell, uo, vo) - _bilinear(ell, ui, vi)
            var[i, j] = _bilinear(var_ell, uo, vo) + _bilinear(var_ell, ui, vi)
    return diff, var


def _robust_line(
    t: np.ndarray, d: np.ndarray, w: np.ndarray, max_tilt_px: float, tol_px: float = 1.0
):
    """Line d(t) through the largest set of segment offsets that agree within ``tol_px``
    (every pair, and every single offset as a constant, proposes a line whose offset changes by
    at most ``max_tilt_px`` along the side; ties go to the innermost), refitted by weighted least
    squares; None with fewer than two agreeing segments. Segments that disagree see another
    edge (a holder's outer edge where the sample/holder step vanishes, a highlight)."""
    n = len(t)
    if n < 2:
        return None
    span = float(t.max() - t.min()) or 1.0
    proposals = [(d[i], 0.0, t[i]) for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            slope = (d[j] - d[i]) / (t[j] - t[i])
            if abs(slope) * span <= max_tilt_px:
                proposals.append((d[i], slope, t[i]))
    # Every proposal's inliers at once (proposals × segments); the best has the most inliers,
    # then the innermost mean offset, then comes first (as a scan keeping the first best would).
    d0, slope, t0 = np.array(proposals).T
    inliers = np.abs(d[None, :] - (d0[:, None] + slope[:, None] * (t[None, :] - t0[:, None])))
    inliers = inliers <= tol_px
    count = inliers.sum(axis=1)
    mean_d = (inliers * d[None, :]).sum(axis=1) / np.maximum(count, 1)
    first_best = np.lexsort((np.arange(len(count)), mean_d, -count))[0]
    best = inliers[first_best]
    if best.sum() < 2:
        return None
    coef = _weighted_line(t[best], d[best], w[best])
    if abs(coef[0]) * span > max_tilt_px:  # the refit may not tilt beyond the bound either
        return np.array([0.0, float(np.average(d[best], weights=w[best]))])
    return coef


def _weighted_line(t: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares line d = c₀·t + c₁ (closed form), as (c₀, c₁)."""
    sw = w.sum()
    tm, dm = (w * t).sum() / sw, (w * d).sum() / sw
    stt = (w * (t - tm) ** 2).sum()
    slope = (w * (t - tm) * (d - dm)).sum() / stt if stt > 0 else 0.0
    return np.array([slope, dm - slope * tm])


def segment_sample(
    flux: np.ndarray,
    corners_px: np.ndarray,
    *,
    noise_sd: float | np.ndarray = 0.0,
    band_px: float = 6.0,
    k_sigma: float = 5.0,
    min_step: float = 0.08,
    segment_px: float = 12.0,
) -> Segmentation:
    """Segment the sample in a flux image (H, W) around its predicted corners (4, 2) = (u, v).

    ``noise_sd`` (same units as ``flux``, scalar or per pixel) is each pixel's 1-σ noise;
    ``band_px`` the largest footprint error (pixels) that can be corrected; ``k_sigma`` and
    ``min_step`` the edge thresholds (noise σ and step in ln Φ, see the module docstring).
    """
    f = np.nan_to_num(np.asarray(flux, np.float64), nan=0.0, posinf=0.0)
    shape = f.shape
    pts = _ccw(np.asarray(corners_px, dtype=np.float64))
    if pts.shape != (4, 2) or not np.all(np.isfinite(pts)):
        raise ValueError("corners_px must be 4 finite (u, v) points")
    sd = np.nan_to_num(
        np.broadcast_to(np.asarray(noise_sd, np.float64), shape), nan=0.0, posinf=0.0
    )
    top = float(f.max()) if (f > 0).any() else 1.0
    floor = np.maximum(3.0 * np.abs(sd), 1e-9 * top)
    fc = np.maximum(f, floor)
    log_image = (np.log(fc), np.where(f > floor, (sd / fc) ** 2, 0.0))  # ℓ and σ_ℓ²
    centre = pts.mean(axis=0)
    offsets = np.zeros((4, 2))
    found = 0
    search = _EdgeSearch(np.arange(-band_px, band_px + 1e-9, 0.25), k_sigma, min_step, segment_px)
    for k in range(4):
        a, b = pts[k], pts[(k + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if length < 6.0:
            continue
        ts, ds, ws = _side_edges(log_image, a, b, _outward(a, b, centre), search)
        coef = _robust_line(
            np.array(ts), np.array(ds), np.array(ws, dtype=float), max_tilt_px=band_px / 2
        )
        if coef is not None:
            offsets[k] = [coef[1], coef[0] * length + coef[1]]
            found += 1
    new = _shifted_quadrilateral(pts, offsets, centre)
    return Segmentation(polygon_mask(shape, new), new, found, offsets)


@dataclass(frozen=True)
class _EdgeSearch:
    d_grid: np.ndarray  # offsets along the outward normal tried (px)
    k_sigma: float
    min_step: float
    segment_px: float


def _outward(a: np.ndarray, b: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit normal of side a→b pointing away from the quadrilateral's centre."""
    t_hat = (b - a) / np.hypot(*(b - a))
    n_hat = np.array([t_hat[1], -t_hat[0]])
    return -n_hat if np.dot(n_hat, (a + b) / 2 - centre) < 0 else n_hat


def _side_edges(log_image, a, b, n_hat, search: _EdgeSearch):
    """(t, edge offset, weight) of every segment of side a→b where an edge is found."""
    ell, var_ell = log_image
    length = float(np.hypot(*(b - a)))
    t_hat = (b - a) / length
    d_grid = search.d_grid
    # Stay 3 px clear of the corners, where the neighbouring side's edge crosses.
    n_seg = max(2, int((length - 6.0) // search.segment_px))
    t = np.arange(3.0, length - 3.0, 0.5)
    seg_id = np.minimum(((t - 3.0) / ((length - 6.0) / n_seg)).astype(int), n_seg - 1)
    base = a[None, None, :] + t[None, :, None] * t_hat  # (1, T, 2)
    # All offsets at once: (D, T) samples just outside and just inside each offset line.
    p_out = base + (d_grid[:, None, None] + 1.0) * n_hat
    p_in = base + (d_grid[:, None, None] - 1.0) * n_hat
    diff, var = _steps_across(ell, var_ell, p_out, p_in)
    ts, ds, ws = [], [], []
    # Per-segment means in one pass (seg_id is sorted along the side).
    starts = np.flatnonzero(np.r_[True, seg_id[1:] != seg_id[:-1]])
    counts = np.diff(np.r_[starts, len(t)])
    mean_diff = np.add.reduceat(diff, starts, axis=1) / counts
    mean_var = np.add.reduceat(var, starts, axis=1) / counts
    t_mid = np.add.reduceat(t, starts) / counts
    for g in range(len(starts)):
        n_t = int(counts[g])
        if n_t < 4:
            continue
        # Samples 0.5 px apart share pixels: count one independent sample per pixel.
        noise = np.sqrt(mean_var[:, g] / (n_t / 2.0))
        d_best = _innermost_edge(np.abs(mean_diff[:, g]), noise, search)
        if d_best is not None:
            ts.append(float(t_mid[g]))
            ds.append(d_best)
            ws.append(n_t)
    return ts, ds, ws


def _innermost_edge(steps: np.ndarray, noise: np.ndarray, search: _EdgeSearch) -> float | None:
    """The offset of the innermost significant step s(d), to a fraction of the grid step.

    The sample is the region around the core, so its edge is the *innermost* significant step
    (a holder's own outer edge, often much stronger, lies beyond). A step is an edge only if it
    stands out of its surroundings 2.5 px either side: a BRDF lobe's smooth gradient gives a
    similar step at every offset (no prominence), a sharp edge gives a peak (the ±1 px
    difference of a ≤ 1 px blurred step vanishes 2.5 px away)."""
    d_grid = search.d_grid
    m = 10  # 2.5 px in 0.25 px steps
    idx = np.arange(len(steps))
    around = 0.5 * (
        steps[np.clip(idx - m, 0, len(steps) - 1)] + steps[np.clip(idx + m, 0, len(steps) - 1)]
    )
    strong = steps - around > np.maximum(search.k_sigma * noise, search.min_step)
    peak = np.r_[
        steps[0] >= steps[1],
        (steps[1:-1] >= steps[:-2]) & (steps[1:-1] >= steps[2:]),
        steps[-1] >= steps[-2],
    ]
    cand = np.flatnonzero(strong & peak)
    if not cand.size:
        return None
    j = int(cand[0])
    # Sub-step position: the centroid of the peak above half its prominence. A sharp step
    # gives a flat-topped s(d) (the ±1 px difference spans it for 1 px of d), whose centre,
    # not its first point, is the edge.
    half = 0.5 * (steps[j] + around[j])
    lo = hi = j
    while lo > 0 and steps[lo - 1] > half:
        lo -= 1
    while hi < len(steps) - 1 and steps[hi + 1] > half:
        hi += 1
    wgt = steps[lo : hi + 1] - half
    return float(np.sum(wgt * d_grid[lo : hi + 1]) / np.sum(wgt))


def _shifted_quadrilateral(pts: np.ndarray, offsets: np.ndarray, centre: np.ndarray):
    """Corners of the quadrilateral bounded by the four sides shifted outward by `offsets`
    (px, at each side's two ends)."""
    lines = []
    for k in range(4):
        a, b = pts[k], pts[(k + 1) % 4]
        n_hat = _outward(a, b, centre)
        lines.append((a + offsets[k, 0] * n_hat, b + offsets[k, 1] * n_hat))
    new = np.empty((4, 2))
    for k in range(4):
        (p1, p2), (p3, p4) = lines[k - 1], lines[k]
        d1, d2 = p2 - p1, p4 - p3
        den = d1[0] * d2[1] - d1[1] * d2[0]
        if abs(den) < 1e-12:
            new[k] = pts[k]
            continue
        s = ((p3[0] - p1[0]) * d2[1] - (p3[1] - p1[1]) * d2[0]) / den
        new[k] = p1 + s * d1
    return new
