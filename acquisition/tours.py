"""Travel-optimal pose order: which pose to visit next so the arms spend the least time moving.

The metric is the move time of `acquisition.motion` (all axes move together; a leg lasts as long
as its slowest axis). Small plans get nearest neighbour then 2-opt on the full n × n cost matrix
(exactly as before, so existing plans keep their order, and with it the demo's noise
realisation). A plan too large for that matrix (n² doubles, times the axis count while it is
built: 10⁴ poses would need ~4 GB) gets the same two steps in O(n) memory: nearest neighbour
through a k-d tree, then 2-opt inside overlapping windows along the tour.
"""

from __future__ import annotations

import numpy as np

from acquisition.config import AxisConfig
from acquisition.motion import axis_speed_rad_s, move_time_s

__all__ = ["order_poses", "DENSE_MAX_POSES"]

# Above this many poses the dense cost matrix is not built. It is built in blocks of rows
# (`_dense_cost`), so at 1500 poses the ordering holds the matrix and its padded copy, 2 × 1500² ×
# 8 B ≈ 36 MB, plus one block's temporaries: the most a plan may cost before its first capture
# on a small lab PC. (Evaluated in one piece, move_time_s's temporaries over n² × n_axes made a
# 1250-pose plan peak at 350 MiB: the soak's 741 MiB "peak RSS" of issue 23 item 6, in part.)
DENSE_MAX_POSES = 1500
# Elements (legs × axes) per block of `_dense_cost`: about 6 temporaries of 8 B each, ≈ 50 MB.
BLOCK_ELEMENTS = 1 << 20
# 2-opt window (poses) for large plans: each window's cost matrix is WINDOW² doubles (~0.5 MB)
# and consecutive windows overlap by half, so an improving exchange near a window's edge is
# seen whole by the next one.
WINDOW = 256
# Candidate neighbours per pose for the large-plan nearest-neighbour walk (see there).
CANDIDATES = 12
# Sweeps of the windows over the whole tour: on a 10⁵-pose hemisphere plan one sweep gains
# 1.8 % of the move time for 18 s; a second gains far less for as long again.
SWEEPS = 1


def order_poses(axes: dict[str, AxisConfig], vectors: np.ndarray, start: np.ndarray) -> list[int]:
    """Visit order of `vectors` (n, n_axes) starting from `start` (n_axes,), axes ordered like
    `axes`; the tour is an open path (it ends wherever is cheapest)."""
    n = len(vectors)
    if n <= 2:
        return list(range(n))
    if n > DENSE_MAX_POSES:
        tour = _nearest_neighbour_kdtree(axes, vectors, start)
        return _windowed_two_opt(axes, vectors, start, tour).tolist()
    cost = _dense_cost(axes, vectors)
    start_cost = move_time_s(axes, start[None, :], vectors)
    # Nearest neighbour.
    tour = [int(np.argmin(start_cost))]
    left = np.ones(n, dtype=bool)
    left[tour[0]] = False
    for _ in range(n - 1):
        c = np.where(left, cost[tour[-1]], np.inf)
        nxt = int(np.argmin(c))
        tour.append(nxt)
        left[nxt] = False
    # Local search on the open path start → tour → (free end). Two dummy nodes make it a
    # fixed-ends path: n = the start pose, n + 1 = the end (every edge into it costs 0), so
    # both moves below are plain edge exchanges on one cost matrix `C`.
    c_full = np.zeros((n + 2, n + 2))
    c_full[:n, :n] = cost
    c_full[n, :n] = c_full[:n, n] = start_cost
    path = np.array([n, *tour, n + 1])
    # Or-opt (moving runs of 1–3 poses) was tried on top: it gained 0.1 % on isotropic.toml,
    # and changing the demo's order changes its noise realisation, so it is not used.
    while _two_opt(c_full, path):
        pass
    return path[1:-1].tolist()


def _dense_cost(axes: dict[str, AxisConfig], vectors: np.ndarray) -> np.ndarray:
    """The n × n move-time matrix, a block of rows at a time (the same arithmetic as one call, so
    the same values and the same tour; memory: the matrix plus one block's temporaries)."""
    n, n_axes = vectors.shape
    rows = max(1, BLOCK_ELEMENTS // (n * n_axes))
    cost = np.empty((n, n))
    for lo in range(0, n, rows):
        cost[lo : lo + rows] = move_time_s(axes, vectors[lo : lo + rows, None, :], vectors[None])
    return cost


def _two_opt(c: np.ndarray, p: np.ndarray) -> bool:
    """2-opt: reverse p[i..j] when that shortens the path (moves are symmetric in time, so a
    reversed segment costs what it did). Changes edges (i−1, i) and (j, j+1). In place."""
    m = len(p) - 1  # p[0] and p[m] are fixed
    improved = False
    for i in range(1, m - 1):
        js = np.arange(i + 1, m)
        gain = c[p[i - 1], p[i]] + c[p[js], p[js + 1]] - c[p[i - 1], p[js]] - c[p[i], p[js + 1]]
        k = int(np.argmax(gain))
        if gain[k] > 1e-9:
            j = js[k]
            p[i : j + 1] = p[i : j + 1][::-1].copy()
            improved = True
    return improved


def _nearest_neighbour_kdtree(
    axes: dict[str, AxisConfig], vectors: np.ndarray, start: np.ndarray
) -> np.ndarray:
    """Nearest-neighbour tour without the n × n matrix.

    Every pose gets a candidate list: its CANDIDATES nearest poses in cruise-time coordinates
    (angle / axis speed) under the Chebyshev norm — the move time of long moves exactly
    (slowest axis, constant speed), and nearly the trapezoid's ranking of short ones — found in
    one batched k-d tree query and then ranked by the exact move time. The walk takes the first
    unvisited pose of the current pose's list; when all are visited it asks a k-d tree of the
    unvisited poses (rebuilt whenever half of it has been visited, so such a query finds a free
    pose among few candidates). Work O(n log n), memory O(n · CANDIDATES).
    """
    # Imported for the large plans only: scipy.spatial is 0.8 CPU-s of every `gonio acquire`
    # (and of one that stops at a bad rig file), and the plans that reach here are rare.
    from scipy.spatial import cKDTree

    pts = vectors / np.array([axis_speed_rad_s(a) for a in axes.values()])
    n = len(vectors)
    k = min(CANDIDATES + 1, n)
    _, near = cKDTree(pts).query(pts, k=k, p=np.inf, workers=-1)
    near = near[:, 1:]  # drop the pose itself
    legs = move_time_s(axes, vectors[:, None, :], vectors[near])
    near = np.take_along_axis(near, np.argsort(legs, axis=1, kind="stable"), axis=1)

    visited = np.zeros(n, dtype=bool)
    tour = np.empty(n, dtype=np.int64)
    tour[0] = int(np.argmin(move_time_s(axes, start, vectors)))
    visited[tour[0]] = True
    alive = np.flatnonzero(~visited)
    tree = None  # a cKDTree of the unvisited poses
    used = 0  # visited poses still in `tree`
    for t in range(1, n):
        here = tour[t - 1]
        free = near[here][~visited[near[here]]]
        if len(free):
            nxt = int(free[0])
        else:
            if tree is None or 2 * used > len(alive):
                alive = np.flatnonzero(~visited)
                tree, used = cKDTree(pts[alive]), 0
            q = 8
            while True:
                q = min(q, len(alive))
                _, idx = tree.query(pts[here], k=q, p=np.inf)
                cand = alive[np.atleast_1d(idx)]
                cand = cand[~visited[cand]]
                if len(cand) or q == len(alive):
                    break
                q *= 4
            nxt = int(cand[int(np.argmin(move_time_s(axes, vectors[here], vectors[cand])))])
        tour[t] = nxt
        visited[nxt] = True
        used += 1
    return tour


def _windowed_two_opt(
    axes: dict[str, AxisConfig], vectors: np.ndarray, start: np.ndarray, tour: np.ndarray
) -> np.ndarray:
    """2-opt restricted to windows of WINDOW consecutive tour positions (ends fixed; the last
    window's end is free, through a zero-cost dummy node as in the dense case)."""
    pts = np.vstack([start[None, :], vectors])  # row 0 = the start pose
    path = np.concatenate([[0], tour + 1])
    n = len(path)
    step = WINDOW // 2
    for _ in range(SWEEPS):
        improved = False
        for s in range(0, max(n - 2, 1), step):
            e = min(s + WINDOW, n)
            nodes = path[s:e]
            local = move_time_s(axes, pts[nodes][:, None, :], pts[nodes][None, :, :])
            order = np.arange(len(nodes))
            if e == n:  # free end: a dummy node every pose reaches at no cost
                local = np.pad(local, ((0, 1), (0, 1)))
                order = np.append(order, len(nodes))
            before = order.copy()
            while _two_opt(local, order):
                improved = True
            if e == n:
                order = order[:-1]
            if not np.array_equal(order, before[: len(order)]):
                path[s:e] = nodes[order]
        if not improved:
            break
    return path[1:] - 1
