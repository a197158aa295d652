"""Sampling plans: which poses to measure, in which order, and what that costs in lab time."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from acquisition.config import PlanConfig, RigConfig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.motion import move_time_s

__all__ = ["PlannedPose", "Plan", "build_plan", "order_poses", "tour_time_s"]


@dataclass(frozen=True)
class PlannedPose:
    index: int  # stable identity within the plan (used by the run store for resume)
    pose: Pose
    targets: dict[str, float]  # axis role → rad


@dataclass
class Plan:
    config: PlanConfig
    poses: list[PlannedPose]  # in acquisition order
    skipped: list[tuple[tuple[float, float, float, float], str]]  # (pose deg, reason)
    move_time_s: float
    raster_move_time_s: float
    exposure_time_s: float

    def lab_time_s(self, readout_s: float, settle_s: float) -> float:
        n = len(self.poses)
        per_pose = settle_s + len(self.config.exposures_s) * readout_s
        return self.move_time_s + self.exposure_time_s + n * per_pose


def _grid(cfg: PlanConfig) -> list[tuple[float, float, float, float]]:
    if cfg.type == "explicit":
        return [tuple(p) for p in cfg.poses_deg]
    return [
        (ti, 0.0, to, dp % 360.0)
        for ti, to, dp in itertools.product(cfg.theta_i_deg, cfg.theta_o_deg, cfg.delta_phi_deg)
    ]


def _vector(targets: dict[str, float], roles: list[str]) -> np.ndarray:
    return np.array([targets[r] for r in roles])


def tour_time_s(rig: RigConfig, vectors: np.ndarray, start: np.ndarray | None = None) -> float:
    axes = {a.role: a for a in rig.axes if a.role in _ROLES}
    legs = move_time_s(axes, vectors[:-1], vectors[1:]).sum()
    if start is not None and len(vectors):
        legs += float(move_time_s(axes, start, vectors[0]))
    return float(legs)


_ROLES = ["light_theta", "light_phi", "camera_theta", "camera_phi"]


def order_poses(rig: RigConfig, vectors: np.ndarray, start: np.ndarray) -> list[int]:
    """Travel-optimal order: nearest neighbour from the start pose, then 2-opt on the
    move-time metric (moves are symmetric in time, so segment reversal is valid)."""
    n = len(vectors)
    if n <= 2:
        return list(range(n))
    axes = {a.role: a for a in rig.axes if a.role in _ROLES}
    cost = move_time_s(axes, vectors[:, None, :], vectors[None, :, :])
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
    # 2-opt (open path: reversing tour[i..j] changes edges (i-1,i) and (j,j+1)).
    t = np.array(tour)
    improved = True
    while improved:
        improved = False
        for i in range(0, n - 1):
            a_prev = start_cost[t[i]] if i == 0 else cost[t[i - 1], t[i]]
            prev_node = None if i == 0 else t[i - 1]
            js = np.arange(i + 1, n)
            old = a_prev + np.where(js < n - 1, cost[t[js], t[np.minimum(js + 1, n - 1)]], 0.0)
            new_first = start_cost[t[js]] if prev_node is None else cost[prev_node, t[js]]
            new = new_first + np.where(js < n - 1, cost[t[i], t[np.minimum(js + 1, n - 1)]], 0.0)
            gain = old - new
            k = int(np.argmax(gain))
            if gain[k] > 1e-9:
                j = js[k]
                t[i : j + 1] = t[i : j + 1][::-1].copy()
                improved = True
    return t.tolist()


def build_plan(rig: RigConfig, cfg: PlanConfig, start_rad: dict[str, float] | None = None) -> Plan:
    """Expand, check reachability, and order a plan.

    Grid poses the rig cannot take are skipped with their reason (when `skip_unreachable`);
    an unreachable explicit pose is an error, since the user asked for it by name.
    """
    kin = Kinematics(rig)
    poses: list[PlannedPose] = []
    skipped = []
    for deg in _grid(cfg):
        pose = Pose.from_deg(*deg)
        try:
            targets = kin.targets(pose)
        except Unreachable as exc:
            if cfg.type == "explicit" or not cfg.skip_unreachable:
                raise Unreachable(f"pose {list(deg)} deg: {exc}") from None
            skipped.append((deg, str(exc)))
            continue
        poses.append(PlannedPose(len(poses), pose, targets))
    if not poses:
        raise Unreachable("no pose of the plan is reachable by this rig")
    vectors = np.array([_vector(p.targets, _ROLES) for p in poses])
    if start_rad is None:
        start = np.array([_park(rig, r) for r in _ROLES])
    else:
        start = _vector(start_rad, _ROLES)
    raster = tour_time_s(rig, vectors, start)
    if cfg.order == "nearest":
        order = order_poses(rig, vectors, start)
        poses = [poses[i] for i in order]
        vectors = vectors[order]
    moves = tour_time_s(rig, vectors, start)
    exposure = len(poses) * float(sum(cfg.exposures_s))
    return Plan(cfg, poses, skipped, moves, raster, exposure)


def _park(rig: RigConfig, role: str) -> float:
    a = rig.axis(role)
    deg = a.park_deg if a.park_deg is not None else min(max(0.0, a.min_deg), a.max_deg)
    return math.radians(deg)


def park_targets(rig: RigConfig) -> dict[str, float]:
    return {a.role: _park(rig, a.role) for a in rig.axes}
