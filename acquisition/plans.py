"""Sampling plans: which poses to measure, in which order, and what that costs in lab time."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from acquisition.config import PlanConfig, RigConfig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.motion import move_time_s
from acquisition.tours import order_poses as _order
from plumbing.errors import UserError

__all__ = [
    "PlannedPose",
    "Plan",
    "LabTimeEstimate",
    "build_plan",
    "brackets_bound",
    "prescan_config",
    "refine_config",
    "build_refine_plan",
    "lab_time_estimate",
    "expand_grid",
    "retro_rig_poses",
    "order_poses",
    "park_targets",
    "refine_around_peak",
    "tour_time_s",
    "MIN_ORIENTATIONS",
    "anisotropic_poses",
    "anisotropic_plan_config",
    "retro_poses",
    "retro_plan_config",
    "plan_coverage",
]


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
    exposure_time_s: float  # all poses; an upper bound under auto-exposure
    # For an adaptive plan (phase 1 = this plan): the adaptive config, so the runner goes on to
    # phase 2 once the pre-scan is complete.
    adaptive: PlanConfig | None = None

    @property
    def retro_gap_deg(self) -> float | None:
        """The smallest light–camera angle among the poses (deg): how close to retro-reflection
        the plan gets (set by the rig's occlusion); None for a plan with no pose near retro."""
        gaps = [_separation_deg(p.pose.deg()) for p in self.poses]
        g = min(gaps, default=float("inf"))
        return g if g <= 15.0 else None  # brdfdata.coverage's retro region: angle ≤ 15°

    def lab_time_s(self, readout_s: float, settle_s: float) -> float:
        """Moves + exposures + settling + readout. Exact for fixed brackets (up to the motion
        model); an upper bound under auto-exposure (every pose takes `max_brackets` frames
        at the longest rungs)."""
        n = len(self.poses)
        per_pose = settle_s + brackets_bound(self.config)[0] * readout_s
        return self.move_time_s + self.exposure_time_s + n * per_pose


def brackets_bound(cfg: PlanConfig) -> tuple[int, float]:
    """(frames per pose, exposure seconds per pose): exact for fixed brackets; for auto-exposure
    the bound `max_brackets` frames at the longest rungs of the ladder."""
    if cfg.exposure_mode == "fixed":
        return len(cfg.exposures_s), float(sum(cfg.exposures_s))
    from acquisition.exposure import exposure_ladder

    ae = cfg.auto_exposure
    ladder = exposure_ladder(ae)
    return ae.max_brackets, float(sum(sorted(ladder)[-ae.max_brackets :]))


Deg4 = tuple[float, float, float, float]


def _steps(step: float, stop: float, inclusive: bool) -> tuple[float, ...]:
    n = int(math.floor(stop / step + 1e-9))
    vals = [round(k * step, 9) for k in range(n + 1)]
    return tuple(v for v in vals if v < stop - 1e-9 or (inclusive and v <= stop + 1e-9))


def _unique_directions(poses: list[Deg4]) -> list[Deg4]:
    """Drop poses that repeat an earlier one: at θ = 0 every φ is the same direction (pole),
    and φ is taken mod 360°. Order is kept, so pose indices stay stable."""
    seen: set[Deg4] = set()
    out = []
    for pose in poses:
        key = _direction_key(pose)
        if key not in seen:
            seen.add(key)
            out.append(pose)
    return out


def _direction_key(pose: Deg4) -> Deg4:
    ti, pi, to, po = pose
    return (
        round(ti, 9),
        0.0 if ti == 0 else round(pi % 360.0, 9),
        round(to, 9),
        0.0 if to == 0 else round(po % 360.0, 9),
    )


def _rusinkiewicz(cfg: PlanConfig) -> list[Deg4]:
    """(θ_h, θ_d, φ_d) grid, φ_h = 0 → (θ_i, φ_i, θ_o, φ_o) through Rusinkiewicz's change of
    variables (brdfdata.rusinkiewicz.from_half_diff, Rusinkiewicz 1998 §3). A direction below
    the horizon comes out with θ ≥ 90° and is later skipped as unreachable, with its reason."""
    from brdfdata.directions import vector_to_spherical
    from brdfdata.rusinkiewicz import from_half_diff

    grid = np.array(list(itertools.product(cfg.theta_h_deg, cfg.theta_d_deg, cfg.phi_d_deg)))
    wi, wo = from_half_diff(*np.radians(grid.T))
    ti, pi = vector_to_spherical(wi)
    to, po = vector_to_spherical(wo)
    deg = np.degrees(np.stack([ti, pi % (2 * np.pi), to, po % (2 * np.pi)], axis=-1))
    # Round off float noise (1e-9 deg) so a pole is exactly θ = 0 and duplicates are found.
    deg = np.round(deg, 9)
    return _unique_directions([tuple(float(a) for a in row) for row in deg])


def _separation_deg(deg: Deg4) -> float:
    """Angle between ω_i and ω_o of a pose (θ_i, φ_i, θ_o, φ_o in degrees)."""
    ti, pi, to, po = np.radians(deg)
    c = math.sin(ti) * math.sin(to) * math.cos(pi - po) + math.cos(ti) * math.cos(to)
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


#: The most poses a plan may ask for: twice the 10⁵ that are ordered in 25 s and 380 MB
#: (docs/performance.md); 1.3·10⁶ poses needed > 4 GB and smaller steps exhausted the machine
#: (24 GB) before a line was printed. Checked on the plan's own numbers, before any expansion.
MAX_PLAN_POSES = 200_000


class PlanTooLarge(UserError, ValueError):
    """A plan asks for more poses than gonio plans in bounded memory. One line."""


def pose_count_bound(cfg: PlanConfig) -> int:
    """An upper bound on the poses ``cfg`` expands to, from its lists and steps alone (the
    grids are products of them; de-duplication and reachability only remove poses)."""
    n = len
    if cfg.type == "hemisphere":
        n_theta = int(math.floor(cfg.theta_max_deg / (cfg.theta_step_deg or 90.0) + 1e-9)) + 1
        n_phi = int(math.ceil(360.0 / (cfg.phi_step_deg or 360.0) - 1e-9))
        return (
            (n(cfg.theta_i_deg) or n_theta)
            * (n(cfg.phi_i_deg) or n_phi)
            * (n(cfg.theta_o_deg) or n_theta)
            * (n(cfg.phi_o_deg) or n_phi)
        )
    if cfg.type == "anisotropic":
        return n(cfg.theta_i_deg) * n(cfg.theta_o_deg) * n(cfg.orientations_deg) * 2
    if cfg.type == "retro":
        return n(cfg.theta_i_deg) * max(n(cfg.retro_offsets_deg), 1) * 4
    if cfg.type == "explicit":
        return n(cfg.poses_deg)
    if cfg.type == "inplane":
        return n(cfg.theta_i_deg) * n(cfg.theta_o_deg) * 2
    if cfg.type == "rusinkiewicz":
        return n(cfg.theta_h_deg) * n(cfg.theta_d_deg) * n(cfg.phi_d_deg)
    return n(cfg.theta_i_deg) * n(cfg.theta_o_deg) * n(cfg.delta_phi_deg)


def _grid(cfg: PlanConfig, rig: RigConfig | None = None) -> list[Deg4]:
    bound = pose_count_bound(cfg)
    if bound > MAX_PLAN_POSES:
        raise PlanTooLarge(
            f"plan {cfg.name!r} asks for up to {bound:,} poses, more than the {MAX_PLAN_POSES:,} "
            "gonio orders in bounded memory; use larger steps or fewer angles (or split it "
            "into several plans)"
        )
    if cfg.type == "anisotropic":
        return anisotropic_poses(
            cfg.theta_i_deg, cfg.theta_o_deg, cfg.orientations_deg, retro_side=cfg.both_sides
        )
    if cfg.type == "retro":
        if rig is None:
            raise ValueError("a retro plan is laid out around the rig's min_separation_deg")
        return retro_rig_poses(rig, cfg.theta_i_deg, cfg.retro_offsets_deg)[0]
    if cfg.type == "explicit":
        return [tuple(p) for p in cfg.poses_deg]
    if cfg.type == "inplane":
        sides = (180.0, 0.0) if cfg.both_sides else (180.0,)
        return _unique_directions(
            [
                (ti, 0.0, to, side)
                for ti, side, to in itertools.product(cfg.theta_i_deg, sides, cfg.theta_o_deg)
            ]
        )
    if cfg.type == "hemisphere":
        thetas = _steps(cfg.theta_step_deg or 90.0, cfg.theta_max_deg, inclusive=True)
        phis = _steps(cfg.phi_step_deg or 360.0, 360.0, inclusive=False)
        return _unique_directions(
            list(
                itertools.product(
                    cfg.theta_i_deg or thetas,
                    cfg.phi_i_deg or phis,
                    cfg.theta_o_deg or thetas,
                    cfg.phi_o_deg or phis,
                )
            )
        )
    if cfg.type == "rusinkiewicz":
        return _rusinkiewicz(cfg)
    # isotropic: kept exactly as first defined (no de-duplication), so indices of existing
    # runs stay valid on resume.
    return [
        (ti, 0.0, to, dp % 360.0)
        for ti, to, dp in itertools.product(cfg.theta_i_deg, cfg.theta_o_deg, cfg.delta_phi_deg)
    ]


def expand_grid(cfg: PlanConfig, rig: RigConfig | None = None) -> list[Deg4]:
    """The plan's poses (θ_i, φ_i, θ_o, φ_o) in degrees, in expansion order (index = position),
    before reachability checks (a retro plan needs the rig it is laid out for)."""
    return _grid(cfg, rig)


def _vector(targets: dict[str, float], roles: list[str]) -> np.ndarray:
    return np.array([targets[r] for r in roles])


def tour_time_s(rig: RigConfig, vectors: np.ndarray, start: np.ndarray | None = None) -> float:
    axes = {r: rig.axis(r) for r in _roles(rig)}
    legs = move_time_s(axes, vectors[:-1], vectors[1:]).sum()
    if start is not None and len(vectors):
        legs += float(move_time_s(axes, start, vectors[0]))
    return float(legs)


def order_poses(rig: RigConfig, vectors: np.ndarray, start: np.ndarray) -> list[int]:
    """Travel-optimal order of a plan's axis vectors from `start` (see `acquisition.tours`)."""
    return _order({r: rig.axis(r) for r in _roles(rig)}, vectors, start)


_MOVED = {
    "two-arm": ("light_theta", "light_phi", "camera_theta", "camera_phi"),
    "inplane": ("light_theta", "camera_theta", "sample_azimuth"),
}


def _roles(rig: RigConfig) -> list[str]:
    """Axes a pose moves, in the rig's [[axes]] order (so vectors and `axes` dicts agree)."""
    moved = _MOVED[rig.geometry.preset]
    return [a.role for a in rig.axes if a.role in moved]


def build_plan(rig: RigConfig, cfg: PlanConfig, start_rad: dict[str, float] | None = None) -> Plan:
    """Expand, check reachability, and order a plan.

    Grid poses the rig cannot take are skipped with their reason (when `skip_unreachable`);
    an unreachable explicit pose is an error, since the user asked for it by name.
    An adaptive plan builds its phase 1 (`prescan_config`); phase 2 is `build_refine_plan`.
    """
    if cfg.type == "adaptive":
        plan = build_plan(rig, prescan_config(cfg), start_rad)
        plan.adaptive = cfg
        return plan
    kin = Kinematics(rig)
    poses: list[PlannedPose] = []
    skipped = []
    for deg in _grid(cfg, rig):
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
    roles = _roles(rig)
    vectors = np.array([_vector(p.targets, roles) for p in poses])
    if start_rad is None:
        start = np.array([_park(rig, r) for r in roles])
    else:
        start = _vector(start_rad, roles)
    raster = tour_time_s(rig, vectors, start)
    if cfg.order == "nearest":
        order = order_poses(rig, vectors, start)
        poses = [poses[i] for i in order]
        vectors = vectors[order]
    moves = tour_time_s(rig, vectors, start)
    exposure = len(poses) * brackets_bound(cfg)[1]
    return Plan(cfg, poses, skipped, moves, raster, exposure)


_PERIODIC = {"light_phi", "camera_phi", "sample_azimuth"}


def _park(rig: RigConfig, role: str) -> float:
    a = rig.axis(role)
    deg = a.park_deg if a.park_deg is not None else 0.0
    if role in _PERIODIC and not a.min_deg <= deg <= a.max_deg:
        # An azimuth is periodic: 180° parks at −180° on an axis limited to [−180, 179.9].
        for k in (-1, 1, -2, 2):
            if a.min_deg <= deg + 360.0 * k <= a.max_deg:
                deg += 360.0 * k
                break
    return math.radians(min(max(deg, a.min_deg), a.max_deg))


def park_targets(rig: RigConfig) -> dict[str, float]:
    return {a.role: _park(rig, a.role) for a in rig.axes}


def refine_around_peak(
    rig: RigConfig,
    prescan: dict[Deg4, float],
    *,
    span_deg: float,
    step_deg: float,
    exposures_s: tuple[float, ...] | None = None,
    name: str = "refine",
) -> PlanConfig:
    """Adaptive refinement: an explicit plan of fine poses around each incidence's peak.

    `prescan` maps the poses of a quick coarse scan (θ_i, φ_i, θ_o, φ_o in degrees) to a
    signal (e.g. the sample region's mean radiance per exposure time). For every incidence
    (θ_i, φ_i) the brightest outgoing direction marks the peak; around it a grid in θ_o
    (peak ± span, every `step_deg`) and in Δφ (± span, every step/ sin θ_o so the arc spacing on
    the sphere stays ≈ `step_deg`) is laid. Poses already in the pre-scan, repeats, and poses
    the rig cannot take are left out. `span_deg` should be about the pre-scan's spacing, so the
    true peak — somewhere between two coarse samples — lies inside the refined patch.
    """
    if not (0 < step_deg <= span_deg):
        raise ValueError(f"need 0 < step_deg ({step_deg}) <= span_deg ({span_deg})")
    kin = Kinematics(rig)
    incidences: dict[tuple[float, float], list[tuple[Deg4, float]]] = {}
    for pose, value in prescan.items():
        incidences.setdefault((pose[0], pose[1]), []).append((pose, float(value)))
    n = int(math.floor(span_deg / step_deg + 1e-9))
    offsets = [k * step_deg for k in range(-n, n + 1)]
    fine: list[Deg4] = []
    for (ti, pi), rows in incidences.items():
        (_, _, to_peak, po_peak), _ = max(rows, key=lambda r: r[1])
        for dto in offsets:
            to = to_peak + dto
            if not 0.0 <= to < 90.0:
                continue
            # Δφ step for an arc of ≈ step_deg at this θ_o (capped at the pole).
            dphi_step = min(step_deg / max(math.sin(math.radians(to)), 1e-9), 360.0)
            m = int(math.floor(span_deg / dphi_step + 1e-9)) if to > 0 else 0
            for k in range(-m, m + 1):
                fine.append((ti, pi, round(to, 9), round((po_peak + k * dphi_step) % 360.0, 9)))
    known = {_direction_key(p) for p in prescan}
    poses = []
    for deg in _unique_directions(fine):
        if _direction_key(deg) in known:
            continue
        try:
            kin.check(Pose.from_deg(*deg))
        except Unreachable:
            continue
        poses.append(deg)
    if not poses:
        raise Unreachable("refinement: no new reachable pose around the peak")
    return PlanConfig(
        name=name, type="explicit", poses_deg=tuple(poses), exposures_s=exposures_s or (0.002,)
    )


# -- adaptive plans (two phases in one run) ---------------------------------------------------

_EXPOSURE_FIELDS = ("exposures_s", "exposure_mode", "auto_exposure")


def prescan_config(cfg: PlanConfig) -> PlanConfig:
    """Phase 1 of an adaptive plan: its `prescan`, with the adaptive plan's exposure settings."""
    if cfg.type != "adaptive" or cfg.prescan is None:
        raise ValueError(f"plan {cfg.name!r} is not adaptive")
    return cfg.prescan.model_copy(update={f: getattr(cfg, f) for f in _EXPOSURE_FIELDS})


def refine_config(rig: RigConfig, cfg: PlanConfig, prescan_signal: dict[Deg4, float]) -> PlanConfig:
    """Phase 2 of an adaptive plan: `refine_around_peak` on the pre-scan signal, as an explicit
    plan carrying the adaptive plan's exposure settings. Deterministic in its inputs."""
    fine = refine_around_peak(
        rig,
        prescan_signal,
        span_deg=cfg.refine_span_deg,
        step_deg=cfg.refine_step_deg,
        name=f"{cfg.name}-refine",
    )
    return fine.model_copy(update={f: getattr(cfg, f) for f in _EXPOSURE_FIELDS})


def build_refine_plan(
    rig: RigConfig, refine_cfg: PlanConfig, index_offset: int, start_rad: dict[str, float] | None
) -> Plan:
    """The phase-2 plan, its pose indices shifted by `index_offset` (the number of phase-1
    poses) so that both phases share one manifest without colliding.

    Order: nearest neighbour + 2-opt from where phase 1 ended — unless the patches visited one
    after the other (each in its own order from the park pose, as `lab_time_estimate` bounds
    them) is quicker; that fallback keeps the phase-2 time within the announced bound.
    """
    plan = build_plan(rig, refine_cfg, start_rad)
    roles = _roles(rig)
    start = (
        np.array([_park(rig, r) for r in roles]) if start_rad is None else _vector(start_rad, roles)
    )
    patches: dict[tuple[float, float], list[Deg4]] = {}
    for deg in refine_cfg.poses_deg:
        patches.setdefault((deg[0], deg[1]), []).append(deg)
    if len(patches) > 1:
        by_deg = {tuple(round(a, 6) for a in deg): i for i, deg in enumerate(refine_cfg.poses_deg)}
        concat: list[PlannedPose] = []
        for rows in patches.values():
            sub = build_plan(rig, refine_cfg.model_copy(update={"poses_deg": tuple(rows)}))
            for q in sub.poses:
                concat.append(PlannedPose(by_deg[_deg_key(q)], q.pose, q.targets))
        vec = np.array([_vector(q.targets, roles) for q in concat])
        t_concat = tour_time_s(rig, vec, start)
        if t_concat < plan.move_time_s:
            plan.poses, plan.move_time_s = concat, t_concat
    plan.poses = [PlannedPose(p.index + index_offset, p.pose, p.targets) for p in plan.poses]
    return plan


@dataclass(frozen=True)
class LabTimeEstimate:
    """Lab time before the run (s). `phase2_max_s` is 0 for a one-phase plan. Under
    auto-exposure every figure is an upper bound (see `Plan.lab_time_s`)."""

    phase1_s: float
    phase2_max_s: float
    refine_max_poses: int

    @property
    def total_max_s(self) -> float:
        return self.phase1_s + self.phase2_max_s


def _max_leg_s(rig: RigConfig) -> float:
    """Longest single move the rig can make: every axis across its whole range."""
    roles = _roles(rig)
    axes = {r: rig.axis(r) for r in roles}
    lo = np.radians([axes[r].min_deg for r in roles])
    hi = np.radians([axes[r].max_deg for r in roles])
    return float(move_time_s(axes, lo, hi))


def lab_time_estimate(
    rig: RigConfig, cfg: PlanConfig, plan1: Plan | None = None
) -> LabTimeEstimate:
    """Phase-1 lab time, and for an adaptive plan an upper bound on phase 2.

    `plan1` is `build_plan(rig, cfg)` when the caller has it already (a large plan takes
    seconds to build and order; building it twice doubles that).

    Phase 2 depends on where the peaks are, which is unknown before the run. Bound: for every
    incidence, the largest refine patch any pre-scan pose of that incidence could produce as
    its peak, at the cost of that patch's own ordered tour; plus, per incidence, one move of
    every axis across its full range (into and out of the patch). The runner keeps the
    phase-2 tour within this bound (`order_within_bound`).
    """
    readout, settle = rig.camera.readout_s, rig.settle_s
    if plan1 is None:
        plan1 = build_plan(rig, cfg)
    phase1 = plan1.lab_time_s(readout, settle)
    if cfg.type != "adaptive":
        return LabTimeEstimate(phase1, 0.0, 0)
    by_incidence: dict[tuple[float, float], list[Deg4]] = {}
    for p in plan1.poses:
        d = _deg_key(p)
        by_incidence.setdefault((d[0], d[1]), []).append(d)
    leg = _max_leg_s(rig)
    bound, n_max = 0.0, 0
    refine_cfg_base = cfg
    for rows in by_incidence.values():
        worst_s, worst_n = 0.0, 0
        for peak in rows:
            signal = {d: (1.0 if d == peak else 0.0) for d in rows}
            try:
                fine = refine_config(rig, refine_cfg_base, signal)
            except Unreachable:
                continue
            plan2 = build_plan(rig, fine)
            t = plan2.lab_time_s(readout, settle)
            if t > worst_s:
                worst_s = t
            worst_n = max(worst_n, len(plan2.poses))
        if worst_n:
            bound += worst_s + leg
            n_max += worst_n
    return LabTimeEstimate(phase1, bound, n_max)


def _deg_key(p: PlannedPose) -> Deg4:
    """A planned pose in degrees, rounded so that float noise does not split incidences."""
    return tuple(round(a, 6) for a in p.pose.deg())  # type: ignore[return-value]


# -- plans for the models that need more of the hemisphere (issue 19 item 4) ----------------------

#: Sample orientations (distinct mod 180°) an anisotropic lobe (α_x, α_y, φ₀) needs: its width
#: along the plane of incidence is α(ψ)² = α_x² cos²(ψ − φ₀) + α_y² sin²(ψ − φ₀), three unknowns,
#: and a fourth orientation checks the fit (and the peak height fixes α_x α_y on top).
MIN_ORIENTATIONS = 4


def anisotropic_poses(
    theta_i_deg, theta_o_deg, orientations_deg, *, retro_side: bool = False
) -> list[Deg4]:
    """In-plane scans with the sample turned to each orientation ψ (deg, the sample-frame
    azimuth of the plane of incidence): (θ_i, ψ, θ_o, ψ + 180°) for every θ_i × θ_o, and
    (θ_i, ψ, θ_o, ψ) on the light's side too if ``retro_side``. A turntable reaches ψ at
    ``sample_azimuth = −ψ`` (acquisition.kinematics), a two-arm rig with its φ axes. ψ and
    ψ + 180° probe the same slopes, so ≥ 4 orientations distinct mod 180° are required."""
    distinct = {round(o % 180.0, 9) for o in orientations_deg}
    if len(distinct) < MIN_ORIENTATIONS:
        raise ValueError(
            f"an anisotropic plan needs ≥ {MIN_ORIENTATIONS} sample orientations distinct mod "
            f"180 deg; got {sorted(distinct)}"
        )
    sides = (180.0, 0.0) if retro_side else (180.0,)
    poses = [
        (float(ti), float(psi % 360.0), float(to), float((psi + side) % 360.0))
        for psi, ti, side, to in itertools.product(
            orientations_deg, theta_i_deg, sides, theta_o_deg
        )
    ]
    return _unique_directions(poses)


def anisotropic_plan_config(
    name: str,
    theta_i_deg,
    theta_o_deg,
    orientations_deg,
    exposures_s=(0.002,),
    *,
    retro_side: bool = False,
) -> PlanConfig:
    """A plan of type ``anisotropic`` (:func:`anisotropic_poses`)."""
    return PlanConfig(
        name=name,
        type="anisotropic",
        theta_i_deg=tuple(theta_i_deg),
        theta_o_deg=tuple(theta_o_deg),
        orientations_deg=tuple(orientations_deg),
        both_sides=retro_side,
        exposures_s=tuple(exposures_s),
    )


def _ring_direction(theta_i: float, radius: float, chi: float) -> np.ndarray:
    """The direction at angle ``radius`` from ω_i = (θ_i, φ = 0) at ring angle χ: χ = 0 toward
    the normal in the plane of incidence, χ = π away from it, ±π/2 out of the plane."""
    wi = np.array([math.sin(theta_i), 0.0, math.cos(theta_i)])
    down = np.array([math.cos(theta_i), 0.0, -math.sin(theta_i)])  # ∂ω/∂θ: toward the horizon
    side = np.array([0.0, 1.0, 0.0])
    return math.cos(radius) * wi + math.sin(radius) * (-math.cos(chi) * down + math.sin(chi) * side)


def retro_poses(
    theta_i_deg,
    min_separation_deg: float,
    offsets_deg=(0.0, 1.0, 2.0, 4.0, 8.0, 15.0, 25.0),
    *,
    ring_angles_deg=(0.0, 180.0),
    max_theta_deg: float = 85.0,
) -> tuple[list[Deg4], float]:
    """Poses around the retro direction ω_o = ω_i as close as the rig allows: the camera on
    rings of angular radius gap + offset around ω_i (light at φ_i = 0), gap =
    ``min_separation_deg`` (the rig's light–camera occlusion limit). Ring angles 0° and 180°
    stay in the plane of incidence (Δφ = 0, or 180° across the normal: any rig); 90°/270°
    leave it (two-arm rigs). Returns the poses and the gap they leave: the smallest
    light–camera angle among them — what no rig of this geometry can close."""
    from brdfdata.directions import vector_to_spherical

    poses: list[Deg4] = []
    seps = []
    for ti, off, chi in itertools.product(theta_i_deg, offsets_deg, ring_angles_deg):
        r = math.radians(min_separation_deg + off)
        w = _ring_direction(math.radians(ti), r, math.radians(chi))
        to, po = vector_to_spherical(w)
        to_deg, po_deg = float(np.degrees(to)), float(np.degrees(po))
        if to_deg > max_theta_deg or w[2] <= 0:
            continue
        poses.append((float(ti), 0.0, round(to_deg, 9), round(po_deg % 360.0, 9)))
        seps.append(min_separation_deg + off)
    if not poses:
        raise ValueError("no retro-reflection pose lies below max_theta_deg")
    return _unique_directions(poses), float(min(seps))


def retro_rig_poses(rig: RigConfig, theta_i_deg, offsets_deg) -> tuple[list[Deg4], float]:
    """:func:`retro_poses` for ``rig``: its min_separation_deg and max_theta_deg, out-of-plane
    rings only on a two-arm rig. Returns the poses and the gap they leave (deg)."""
    g = rig.geometry
    rings = (0.0, 180.0) if g.preset == "inplane" else (0.0, 90.0, 180.0, 270.0)
    return retro_poses(
        theta_i_deg,
        g.min_separation_deg,
        offsets_deg,
        ring_angles_deg=rings,
        max_theta_deg=g.max_theta_deg,
    )


def retro_plan_config(
    rig: RigConfig,
    theta_i_deg,
    offsets_deg=(0.0, 1.0, 2.0, 4.0, 8.0, 15.0, 25.0),
    exposures_s=(0.002,),
    name: str = "retro",
) -> tuple[PlanConfig, float]:
    """A plan of type ``retro`` for ``rig`` and the gap it leaves (deg)."""
    _, gap = retro_rig_poses(rig, theta_i_deg, offsets_deg)
    cfg = PlanConfig(
        name=name,
        type="retro",
        theta_i_deg=tuple(theta_i_deg),
        retro_offsets_deg=tuple(offsets_deg),
        exposures_s=tuple(exposures_s),
    )
    return cfg, gap


def plan_coverage(poses_deg, needs):
    """:func:`brdfdata.coverage.coverage_report` of a plan's poses (θ_i, φ_i, θ_o, φ_o deg), for
    the regions ``needs`` (e.g. a registered model's ``fitting.models.entry(name).needs``)."""
    from brdfdata.coverage import coverage_report
    from brdfdata.directions import spherical_to_vector

    a = np.radians(np.asarray(list(poses_deg), dtype=np.float64).reshape(-1, 4))
    return coverage_report(
        needs, spherical_to_vector(a[:, 0], a[:, 1]), spherical_to_vector(a[:, 2], a[:, 3])
    )
