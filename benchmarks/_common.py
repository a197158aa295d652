"""What several benchmarks share (benchmarks/ is on sys.path when one runs)."""

from __future__ import annotations

import numpy as np

__all__ = ["random_positions", "reachable_poses"]


def random_positions(n: int, rng: np.random.Generator, max_theta_deg: float):
    """`n` light positions at 0.5 m and camera positions at 0.7 m (m), directions uniform in
    θ ≤ `max_theta_deg` and φ: a spread of poses for render timings."""
    th_i = rng.uniform(0, np.radians(max_theta_deg), n)
    th_o = rng.uniform(0, np.radians(max_theta_deg), n)
    ph_i = rng.uniform(0, 2 * np.pi, n)
    ph_o = rng.uniform(0, 2 * np.pi, n)

    def sph(t, p, r):
        return r * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)

    return sph(th_i, ph_i, 0.5), sph(th_o, ph_o, 0.7)


def reachable_poses(rig, grid_deg, n: int) -> list[tuple[float, float, float, float]]:
    """The first `n` poses (θi, φi = 0, θo, Δφ in degrees) of `grid_deg` — an iterable of
    (θi, θo, Δφ) — that the rig's arms can reach; fewer when the grid runs out."""
    from acquisition.kinematics import Kinematics, Pose, Unreachable

    kin = Kinematics(rig)
    poses: list[tuple[float, float, float, float]] = []
    for ti, to, dp in grid_deg:
        try:
            kin.check(Pose.from_deg(ti, 0.0, to, dp))
        except Unreachable:
            continue
        poses.append((float(ti), 0.0, float(to), float(dp)))
        if len(poses) == n:
            break
    return poses
