"""Numerical second derivatives for the estimator: one stencil, shared by the mismatch study's
observed information (fitting.mismatch) and the multi-start search's mode covariances
(fitting.tempering)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["stencil_hessian"]


def stencil_hessian(
    fn: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    step: np.ndarray,
    cols: np.ndarray | None = None,
) -> np.ndarray:
    """∂²fn/∂x² at ``x`` over the coordinates ``cols`` (default all) by central second
    differences with steps ``step`` (one per column), every stencil point in one call of the
    batched ``fn`` ((M, D) points → (M,) values: a likelihood takes walkers in batch)."""
    x = np.asarray(x, dtype=np.float64)
    cols = np.arange(x.size) if cols is None else np.asarray(cols)
    step = np.asarray(step, dtype=np.float64)
    d = cols.size
    pts = [x]
    for a in range(d):
        for sign in (1, -1):
            y = x.copy()
            y[cols[a]] += sign * step[a]
            pts.append(y)
    for a in range(d):
        for b in range(a + 1, d):
            for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                y = x.copy()
                y[cols[a]] += sa * step[a]
                y[cols[b]] += sb * step[b]
                pts.append(y)
    v = np.asarray(fn(np.array(pts)), dtype=np.float64)
    hess = np.empty((d, d))
    k = 1 + 2 * d
    for a in range(d):
        hess[a, a] = (v[1 + 2 * a] - 2 * v[0] + v[2 + 2 * a]) / step[a] ** 2
        for b in range(a + 1, d):
            pp, pm, mp, mm = v[k : k + 4]
            hess[a, b] = hess[b, a] = (pp - pm - mp + mm) / (4 * step[a] * step[b])
            k += 4
    return hess
