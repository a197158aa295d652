"""The acquisition runner: moves through a plan, captures, stores — and stops safely.

Safe stop (Ctrl-C, SIGTERM, or a device fault): finish the capture in progress so its frame is
kept, then park the arms, turn the light off and torque off, and record why in the manifest.
The run stays incomplete, so `gonio acquire` on the same directory resumes it.

Exposure per pose: the plan's fixed brackets, or auto-exposure (`acquisition.exposure`), which
decides each next frame from the sample-region levels of the pose's frames so far. Those levels
are condensed to `FrameStats` and stored with the frame (`frame_meta["sample_levels"]`), so a
resumed pose re-decides from what was seen — only its missing frames are taken.

Adaptive plans run in two phases in one run directory: the pre-scan, then — decided from the
pre-scan frames and frozen in the manifest (meta `refine_plan`) before its first capture —
the refinement around each peak; a resume reuses the frozen refinement.

Every step is also a line of `log.jsonl` (`acquisition.runlog`).
"""

from __future__ import annotations

import math
import signal
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acquisition.calibration_capture import CalibrationPhases
from acquisition.config import PlanConfig
from acquisition.exposure import FrameStats, frame_stats, next_exposure, pose_signal
from acquisition.kinematics import Unreachable
from acquisition.operator import Operator, OperatorDeclined, ask
from acquisition.operator import step as operator_step
from acquisition.plans import Plan, PlannedPose, build_refine_plan, park_targets, refine_config
from acquisition.protocols import DeviceFault, Frame, FrameLevels
from acquisition.rig import Rig
from acquisition.runlog import LOG_NAME, RunLog
from acquisition.store import CaptureRecord, CaptureStart, RunStore, exposure_taken
from plumbing.inputs import FRAME_MAX_BYTES, read_input_bytes
from plumbing.progress import Progress, progress

__all__ = ["RunOutcome", "run_acquisition", "stop_requests", "safe_stop"]


@dataclass
class RunOutcome:
    complete: bool
    captured: int  # new frames this session
    adopted: int  # frames recovered from an interrupted session
    total_done: int
    reason: str  # "complete", "interrupted (SIGINT)", "fault: ..."
    lab_time_s: float  # on the rig's clock (virtual for the simulator)
    prescan_poses: int = 0  # adaptive plans: poses of phase 1
    refine_poses: int = 0  # adaptive plans: poses of phase 2 (0 until decided)
    calibration_captured: int = 0  # new calibration frames (darks, flats, reference) this session


class _StopFlag:
    def __init__(self) -> None:
        self.reason: str | None = None
        self.event = threading.Event()

    def set(self, reason: str) -> None:
        if self.reason is None:
            self.reason = reason
        self.event.set()


@contextmanager
def stop_requests() -> Iterator[_StopFlag]:
    """SIGINT/SIGTERM set a flag instead of raising, so the current capture completes."""
    flag = _StopFlag()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, _frame):
        flag.set(f"interrupted ({signal.Signals(signum).name})")

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def safe_stop(
    rig: Rig, store: RunStore, reason: str, park: bool = True, log: RunLog | None = None
) -> None:
    """Make the rig safe and record why: park (unless `park` is False), light off, torque off.
    Best effort, each step independent: one failing must not prevent the others."""
    steps: list[tuple[str, Callable[[], None]]] = []
    if park:
        steps.append(
            (
                "park",
                lambda: (rig.move(park_targets(rig.config)), rig.wait(rig.config.move_timeout_s)),
            )
        )
    steps += [("light off", rig.light.off), ("torque off", lambda: rig.torque(False))]
    for name, step in steps:
        try:
            step()
        except Exception as exc:
            _record(store, "safe-stop", f"{name} failed: {exc}")
            if log is not None:
                log.emit("safe_stop", "error", step=name, fault=str(exc))
    _record(store, "stop", reason)
    if log is not None:
        log.emit("stop", "info" if reason == "complete" else "warning", reason=reason)


def _record(store: RunStore, kind: str, message: str) -> None:
    """Record an event; a manifest that cannot be written (disk full) must not prevent the
    hardware from being made safe, so the failure is reported on stderr instead."""
    try:
        store.event(kind, message)
    except Exception as exc:  # sqlite3.OperationalError "database or disk is full", OSError
        import sys

        sys.stderr.write(f"warning: could not record {kind!r} in the manifest: {exc}\n")


REFINE_META = "refine_plan"  # manifest meta key: the frozen phase-2 PlanConfig (JSON)
NO_REFINE = "none"  # ... or this, when the refinement found nothing to add
LEVELS_META = "sample_levels"  # frame_meta key: FrameStats of the sample region


class _NeedLevels(RuntimeError):
    pass


class _Stopped(Exception):
    """A stop was requested during a calibration phase."""


@dataclass
class _Session:
    store: RunStore
    rig: Rig
    stop: _StopFlag
    log: RunLog
    frame_levels: FrameLevels | None
    on_capture: Callable[[int], None] | None
    bar: Any
    t0: float
    history: dict[int, list[_Done]]  # done captures per pose, by bracket
    stats: dict[tuple[int, int], FrameStats]
    captured: int = 0
    current_pose: int | None = None


@dataclass(slots=True)
class _Done:
    """What the runner remembers of a done capture: only what resume and auto-exposure need.
    A full `CaptureRecord` (devices, metadata) is ≈ 5 KiB; keeping those for every capture made
    memory grow with run size (the 5000-capture soak found it)."""

    pose_index: int
    bracket_index: int
    exposure_s: float
    frame_path: str
    axes_measured: dict[str, float]
    levels: dict[str, Any] | None  # the stored sample-region stats, when there are any
    exposure_taken_s: float  # what the frame had (store.exposure_taken)

    @classmethod
    def of(cls, rec: CaptureRecord) -> _Done:
        levels = (rec.frame_meta or {}).get(LEVELS_META)
        return cls(
            rec.pose_index,
            rec.bracket_index,
            rec.exposure_s,
            rec.frame_path,
            rec.axes_measured,
            levels,
            rec.exposure_taken_s,
        )


def _levels_of(ses: _Session, frame: Frame, axes_measured: dict[str, float]) -> Any:
    if frame.levels is not None:
        return frame.levels
    if ses.frame_levels is None:
        raise _NeedLevels(
            "auto-exposure and adaptive plans need the sample region's pixel levels: the "
            "camera gave none and no frame decoder was supplied (run through gonio.pipeline)"
        )
    return ses.frame_levels(frame, axes_measured)


def _stats_of(ses: _Session, rec: _Done, cfg: PlanConfig) -> FrameStats:
    """A done capture's stats: stored with the frame, or (a frame adopted after a crash, whose
    row never got its metadata) recomputed from the file on disk."""
    key = (rec.pose_index, rec.bracket_index)
    if key in ses.stats:
        return ses.stats[key]
    if rec.levels is not None:
        st = FrameStats.from_dict(rec.levels)
    else:
        path = ses.store.root / rec.frame_path
        try:
            frame = Frame(read_input_bytes(path, "frame", FRAME_MAX_BYTES), path.suffix.lower(), {})
            st = frame_stats(
                _levels_of(ses, frame, rec.axes_measured), rec.exposure_taken_s, cfg.auto_exposure
            )
        except _NeedLevels:
            raise
        except Exception as exc:  # stop safely, naming the frame, rather than guess
            raise DeviceFault(f"cannot read the sample levels of {rec.frame_path}: {exc}") from exc
    ses.stats[key] = st
    return st


def _pose_history(ses: _Session, index: int, cfg: PlanConfig) -> list[FrameStats]:
    return [_stats_of(ses, r, cfg) for r in ses.history.get(index, [])]


def _pose_pending(ses: _Session, planned: PlannedPose, cfg: PlanConfig) -> bool:
    """Does this pose still need a frame?"""
    if cfg.exposure_mode == "fixed":
        have = {r.bracket_index for r in ses.history.get(planned.index, [])}
        return any(b not in have for b in range(len(cfg.exposures_s)))
    return (
        next_exposure(_pose_history(ses, planned.index, cfg), cfg.auto_exposure).exposure_s
        is not None
    )


def _capture(
    ses: _Session,
    cfg: PlanConfig,
    planned: PlannedPose,
    b: int,
    exposure_s: float,
    where: dict[str, Any],
    want_stats: bool,
) -> FrameStats | None:
    store, clock = ses.store, ses.rig.clock
    t_cap = clock.now()
    frame = ses.rig.camera.capture(exposure_s)
    capture_s = clock.now() - t_cap
    meta = dict(frame.metadata)
    stats, level_error = None, None
    if want_stats:
        try:
            stats = frame_stats(  # the signal rate is per the exposure the frame had
                _levels_of(ses, frame, where["measured"]),
                exposure_taken(meta, exposure_s),
                cfg.auto_exposure,
            )
            meta[LEVELS_META] = stats.to_dict()
        except _NeedLevels:
            raise
        except Exception as exc:  # a frame the decoder cannot read: keep it, then stop
            level_error = f"frame of pose {planned.index} bracket {b} unreadable: {exc}"
    # The pending row goes in before the frame is written: if we die after the frame lands
    # but before the row is marked done, resume adopts the frame.
    pose = where["pose"]
    cid = store.begin_capture(
        CaptureStart(
            pose_index=planned.index,
            bracket_index=b,
            exposure_s=exposure_s,
            pose=(pose.theta_i, pose.phi_i, pose.theta_o, pose.phi_o),
            axes_commanded=planned.targets,
            axes_measured=where["measured"],
            light_dir=pose.wi.tolist(),
            camera_dir=pose.wo.tolist(),
            suffix=frame.suffix,
            devices={
                "axes": where["status"],
                "light": where["light"].__dict__,
                "approach": dict(ses.rig.approach),
            },
            lab_time_s=clock.now() - ses.t0,
        )
    )
    w0 = time.perf_counter()
    store.finish_capture(cid, frame.data, meta)
    write_s = time.perf_counter() - w0
    ses.history.setdefault(planned.index, []).append(
        _Done(
            planned.index,
            b,
            exposure_s,
            "",
            where["measured"],
            meta.get(LEVELS_META),
            exposure_taken(meta, exposure_s),
        )
    )
    if stats is not None:
        ses.stats[(planned.index, b)] = stats
    ses.captured += 1
    ses.log.emit(
        "capture",
        pose=planned.index,
        bracket=b,
        exposure_s=exposure_s,
        capture_id=cid,
        frame=store.frame_name(planned.index, b, frame.suffix),
        levels=None if stats is None else stats.to_dict(),
        timings_s={"capture": capture_s, "write_wall": write_s},
    )
    if ses.on_capture is not None:
        ses.on_capture(ses.captured)
    if level_error is not None:
        raise DeviceFault(level_error)
    return stats


def _run_phase(
    ses: _Session, poses: list[PlannedPose], cfg: PlanConfig, phase: int, want_stats: bool
) -> bool:
    """Capture what is missing of `poses`; True when every pose is finished. `want_stats`:
    keep each frame's sample-region stats (auto-exposure and adaptive pre-scans need them)."""
    rig, clock, log = ses.rig, ses.rig.clock, ses.log
    auto = cfg.exposure_mode == "auto"
    todo = [p for p in poses if _pose_pending(ses, p, cfg)]
    log.emit(
        "phase_start",
        phase=phase,
        poses=len(poses),
        todo=len(todo),
        exposure_mode=cfg.exposure_mode,
    )
    for planned in todo:
        if ses.stop.reason:
            return False
        ses.current_pose = planned.index
        t_move = clock.now()
        rig.move(planned.targets)
        rig.wait(rig.config.move_timeout_s)
        move_s = clock.now() - t_move
        clock.sleep(rig.config.settle_s)
        measured = rig.positions()
        where = {
            "measured": measured,
            "pose": rig.kinematics.pose(measured),
            "status": rig.device_status(),
            "light": rig.light.status(),
        }
        light = where["light"]
        if not light.on:
            raise DeviceFault(f"light is off ({light.fault or 'no reason given'})")
        log.emit(
            "pose",
            pose=planned.index,
            phase=phase,
            pose_deg=[round(a, 6) for a in planned.pose.deg()],
            timings_s={"move": move_s, "settle": rig.config.settle_s},
        )
        if not auto:
            have = {r.bracket_index for r in ses.history.get(planned.index, [])}
            for b, exposure_s in enumerate(cfg.exposures_s):
                if b in have:
                    continue
                if ses.stop.reason:  # stop between frames, not only between poses
                    return False
                _capture(ses, cfg, planned, b, exposure_s, where, want_stats or auto)
        else:
            history = _pose_history(ses, planned.index, cfg)
            while True:
                decision = next_exposure(history, cfg.auto_exposure)
                log.emit(
                    "exposure_decision",
                    pose=planned.index,
                    bracket=len(history) if decision.exposure_s is not None else None,
                    exposure_s=decision.exposure_s,
                    reason=decision.reason,
                )
                if decision.exposure_s is None:
                    break
                if ses.stop.reason:
                    return False
                st = _capture(ses, cfg, planned, len(history), decision.exposure_s, where, True)
                history.append(st)
        ses.bar.advance()
        log.emit("pose_done", pose=planned.index, phase=phase)
    ses.current_pose = None
    return not ses.stop.reason


def _refinement(ses: _Session, plan: Plan) -> Plan | None:
    """Phase 2: the frozen refine plan if there is one, else decided now and frozen (None:
    no pose around the peaks is new and reachable, so there is no phase 2)."""
    cfg = plan.adaptive
    assert cfg is not None
    rig_cfg = ses.rig.config
    offset = len(plan.poses)
    start = plan.poses[-1].targets  # where phase 1 ends (commanded: repeatable on resume)
    frozen = ses.store.meta(REFINE_META)
    if frozen == NO_REFINE:
        ses.log.emit("refine_plan", reason="frozen plan reused", poses=0)
        return None
    if frozen is not None:
        refine_cfg = PlanConfig.model_validate_json(frozen)
        ses.log.emit("refine_plan", reason="frozen plan reused", poses=len(refine_cfg.poses_deg))
        return build_refine_plan(rig_cfg, refine_cfg, offset, start)
    # Peak estimate: per pre-scan pose, the sample region's mean level per second (no
    # calibration: flat field, darks and geometry do not move the peak to another pose).
    signal: dict[tuple[float, float, float, float], float] = {}
    for p in plan.poses:
        hist = _pose_history(ses, p.index, plan.config)
        signal[tuple(round(a, 6) for a in p.pose.deg())] = pose_signal(hist)
    try:
        refine_cfg = refine_config(rig_cfg, cfg, signal)
    except Unreachable as exc:  # nothing new to measure around the peaks: phase 2 is empty
        ses.store.set_meta("refine_offset", str(offset))
        ses.store.set_meta(REFINE_META, NO_REFINE)
        ses.store.event("refine", f"no refine pose: {exc}")
        ses.log.emit("refine_plan", "warning", reason=f"no refine pose: {exc}", poses=0)
        return None
    ses.store.set_meta("refine_offset", str(offset))
    ses.store.set_meta(REFINE_META, refine_cfg.model_dump_json())
    ses.store.event("refine", f"{len(refine_cfg.poses_deg)} refine pose(s) decided and frozen")
    peaks: dict[str, list[float]] = {}
    for deg, v in signal.items():
        k = f"{deg[0]:g},{deg[1]:g}"
        if k not in peaks or v > peaks[k][-1]:
            peaks[k] = [deg[2], deg[3], v]
    ses.log.emit(
        "refine_plan",
        reason="decided from the pre-scan",
        poses=len(refine_cfg.poses_deg),
        peaks={
            k: {"theta_o_deg": a, "phi_o_deg": b_, "signal_per_s": v}
            for k, (a, b_, v) in peaks.items()
        },
    )
    return build_refine_plan(rig_cfg, refine_cfg, offset, start)


def run_acquisition(
    store: RunStore,
    rig: Rig,
    plan: Plan,
    *,
    progress: bool = True,
    stop: _StopFlag | None = None,
    on_capture: Callable[[int], None] | None = None,
    frame_levels: FrameLevels | None = None,
    operator: Operator | None = None,
) -> RunOutcome:
    """Capture every frame of `plan` not already done in `store`: its calibration phases
    (darks, flat, reference target; acquisition.calibration_capture), then the measurement
    poses (both phases of an adaptive plan). `frame_levels` gives the sample region's linear
    levels of a frame; auto-exposure and adaptive plans need it unless the camera attaches
    `Frame.levels` itself. `operator` is asked before every step that needs hands (needed
    when the plan has calibration phases or the lamp is switched by hand); a "no" stops the
    rig safely without moving it and raises `OperatorDeclined`."""
    stop = stop or _StopFlag()
    needs_hands = not plan.config.calibration.empty or rig.config.light.manual
    if needs_hands and operator is None:
        raise ValueError("this plan/rig needs an operator (calibration phases or a manual lamp)")
    log = RunLog(Path(store.root) / LOG_NAME, rig.clock.now)
    adopted = store.adopt_orphans()
    if adopted:
        store.event("resume", f"adopted {adopted} frame(s) written before the interruption")
        log.emit("adopt", frames=adopted, reason="frames written before the interruption")
    history: dict[int, list[_Done]] = {}
    for rec in store.captures("done"):
        history.setdefault(rec.pose_index, []).append(_Done.of(rec))
    ses = _Session(
        store,
        rig,
        stop,
        log,
        frame_levels,
        on_capture,
        _progress(False, 0, 0),
        rig.clock.now(),
        history,
        {},
    )
    calib = CalibrationPhases(
        store, rig, plan.config, operator, log.emit, lambda: bool(stop.reason)
    )
    run = _Run(plan, calib, operator, needs_hands)
    try:
        _measure(ses, run, progress)
        if stop.reason:
            run.reason = stop.reason
    except _Stopped:
        run.reason = stop.reason or "stopped"
    except OperatorDeclined as exc:
        # Nothing is moved on the way out (the operator may be at the rig): light and torque
        # off, the reason recorded; the run stays resumable.
        safe_stop(rig, store, f"operator: {exc}", park=False, log=log)
        ses.bar.close()
        log.close()
        raise
    except (DeviceFault, _NeedLevels, OSError, sqlite3.Error, KeyboardInterrupt) as exc:
        run.reason = _stop_reason(exc)
        if not isinstance(exc, KeyboardInterrupt):
            # A device's own words for its fault; a storage fault as the recorded reason.
            fault = str(exc) if isinstance(exc, DeviceFault | _NeedLevels) else run.reason
            log.emit("fault", "error", pose=ses.current_pose, fault=fault)
    except Exception as exc:
        # A bug, not a device fault: make the hardware safe first, then let it surface.
        safe_stop(rig, store, f"internal error: {type(exc).__name__}: {exc}", log=log)
        log.close()
        raise
    finally:
        ses.bar.close()
    return _finish(ses, run, adopted)


@dataclass
class _Run:
    """What one session of a run is doing, and how far it got."""

    plan: Plan
    calib: CalibrationPhases
    operator: Operator | None
    needs_hands: bool
    reason: str = "complete"
    finished: bool = False
    refine: Plan | None = None


def _stop_reason(exc: BaseException) -> str:
    """The recorded reason for a stop by `exc` (a fault of a device, the storage, or Ctrl-C)."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted (KeyboardInterrupt)"
    if isinstance(exc, DeviceFault | _NeedLevels):
        return f"fault: {exc}"
    if isinstance(exc, sqlite3.Error):  # the manifest could not be written (disk full)
        return f"storage: manifest: {exc}"
    # Disk full, quota, I/O error on the run directory: the frame being written is lost only
    # if it never reached disk (its row stays pending and is re-captured on resume); every
    # earlier frame is already safe. Stop the hardware rather than carry on blind.
    where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    return f"storage: {getattr(exc, 'strerror', None) or exc}" + where


def _measure(ses: _Session, run: _Run, progress: bool) -> None:
    """Calibration phases, lamp on, then the plan's poses (both phases of an adaptive plan)."""
    store, rig, plan, calib = ses.store, ses.rig, run.plan, run.calib
    # What is left, counted in poses (auto-exposure decides the frames as it goes).
    todo1 = [p for p in plan.poses if _pose_pending(ses, p, plan.config)]
    refine_decided = plan.adaptive is not None and store.meta(REFINE_META) is not None
    if refine_decided:
        run.refine = _refinement(ses, plan)
    refine = run.refine
    n_total = len(plan.poses) + (len(refine.poses) if refine else 0)
    n_todo = len(todo1) + (
        sum(_pose_pending(ses, p, refine.config) for p in refine.poses) if refine else 0
    )
    done_before = store.count("done")
    store.event("start" if not done_before else "resume", f"{n_todo} pose(s) to capture")
    ses.log.emit(
        "session_start" if not done_before else "resume",
        plan=plan.config.name,
        poses=n_total,
        todo=n_todo,
        frames_done=done_before,
        exposure_mode=plan.config.exposure_mode,
        adaptive=plan.adaptive is not None,
    )
    for note in getattr(rig, "recovered", []):
        store.event("recover", note)
        ses.log.emit("recover", "warning", reason=note)
    # Darks and the flat need neither the lamp nor a servo: they come first, so an operator
    # who declines stops the run before anything has moved.
    if not calib.before_light():
        raise _Stopped()
    ses.bar = _progress(progress, n_total, n_total - n_todo)
    _lamp_on(rig, run.operator, warm_up=bool(n_todo or calib.reference_todo()))
    ref = plan.config.calibration.reference
    if ref is not None and not calib.reference(ref):
        raise _Stopped()
    if run.needs_hands:
        calib.ready_for_measurement()
    adaptive = plan.adaptive is not None
    run.finished = _run_phase(ses, plan.poses, plan.config, 1, adaptive)
    if run.finished and adaptive:
        if run.refine is None and not refine_decided:
            run.refine = _refinement(ses, plan)
            ses.bar.grow(len(run.refine.poses) if run.refine else 0)
        if run.refine is not None:
            run.finished = _run_phase(ses, run.refine.poses, run.refine.config, 2, adaptive)


def _lamp_on(rig: Rig, operator: Operator | None, *, warm_up: bool) -> None:
    """Torque on, the lamp at the run's level and on (asked for, for a manual lamp), warmed up
    when there is something left to capture."""
    rig.torque(True)
    rig.light.set_intensity(rig.config.light.level)
    if rig.config.light.manual:
        ask(operator, operator_step("lamp_on", warmup_s=rig.config.light.warmup_s))
    rig.light.on()
    if rig.config.light.warmup_s and warm_up:
        rig.clock.sleep(rig.config.light.warmup_s)


def _finish(ses: _Session, run: _Run, adopted: int) -> RunOutcome:
    """Make the rig safe, record the stop and the lab time, mark a complete run complete."""
    store, rig, log, plan = ses.store, ses.rig, ses.log, run.plan
    lab_time_s = rig.clock.now() - ses.t0
    total_done = store.count("done")
    complete = run.reason == "complete" and run.finished
    reason = run.reason
    if complete:
        safe_stop(rig, store, "complete", log=log)
        store.set_meta("lab_time_s", str(lab_time_s + float(store.meta("lab_time_s") or 0)))
        store.mark_complete()
        log.emit("complete", frames=total_done, captured=ses.captured, lab_time_s=lab_time_s)
    else:
        if reason == "complete":
            reason = f"incomplete: {total_done} capture(s) done, poses remain"
        safe_stop(rig, store, reason, log=log)
        try:
            store.set_meta("lab_time_s", str(lab_time_s + float(store.meta("lab_time_s") or 0)))
        except Exception as exc:  # disk full: lab time is bookkeeping, the frames are safe
            _record(store, "warning", f"lab time not recorded: {exc}")
    log.emit("session_end", reason=reason, captured=ses.captured, lab_time_s=lab_time_s)
    log.close()
    return RunOutcome(
        complete,
        ses.captured,
        adopted,
        total_done,
        reason,
        lab_time_s,
        len(plan.poses) if plan.adaptive is not None else 0,
        len(run.refine.poses) if run.refine is not None else 0,
        calibration_captured=run.calib.captured,
    )


def _progress(enabled: bool, total: int, completed: int) -> Progress:
    return progress("acquiring (poses)", total, completed=completed, enabled=enabled)


def fmt_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    m, s = divmod(int(round(seconds)), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s"
