"""The acquisition runner: moves through a plan, captures, stores — and stops safely.

Safe stop (Ctrl-C, SIGTERM, or a device fault): finish the capture in progress so its frame is
kept, then park the arms, turn the light off and torque off, and record why in the manifest.
The run stays incomplete, so `gonio acquire` on the same directory resumes it.
"""

from __future__ import annotations

import math
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from acquisition.plans import Plan, park_targets
from acquisition.protocols import DeviceFault
from acquisition.rig import Rig
from acquisition.store import RunStore

__all__ = ["RunOutcome", "run_acquisition", "stop_requests"]


@dataclass
class RunOutcome:
    complete: bool
    captured: int  # new frames this session
    adopted: int  # frames recovered from an interrupted session
    total_done: int
    reason: str  # "complete", "interrupted (SIGINT)", "fault: ..."
    lab_time_s: float  # on the rig's clock (virtual for the simulator)


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

    def handler(signum, _frame):  # noqa: ANN001 — signal handler signature
        flag.set(f"interrupted ({signal.Signals(signum).name})")

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _safe_stop(rig: Rig, store: RunStore, reason: str, park: bool = True) -> None:
    """Best effort, each step independent: one failing must not prevent the others."""
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
    _record(store, "stop", reason)


def _record(store: RunStore, kind: str, message: str) -> None:
    """Record an event; a manifest that cannot be written (disk full) must not prevent the
    hardware from being made safe, so the failure is reported on stderr instead."""
    try:
        store.event(kind, message)
    except Exception as exc:  # sqlite3.OperationalError "database or disk is full", OSError
        import sys

        sys.stderr.write(f"warning: could not record {kind!r} in the manifest: {exc}\n")


def run_acquisition(
    store: RunStore,
    rig: Rig,
    plan: Plan,
    *,
    progress: bool = True,
    stop: _StopFlag | None = None,
    on_capture: Callable[[int], None] | None = None,
) -> RunOutcome:
    """Capture every (pose, bracket) of `plan` not already done in `store`."""
    stop = stop or _StopFlag()
    adopted = store.adopt_orphans()
    if adopted:
        store.event("resume", f"adopted {adopted} frame(s) written before the interruption")
    done = store.done_keys()
    exposures = plan.config.exposures_s
    todo = [p for p in plan.poses if any((p.index, b) not in done for b in range(len(exposures)))]
    total = len(plan.poses) * len(exposures)
    store.event("start" if not done else "resume", f"{len(todo)} pose(s) to capture")
    for note in getattr(rig, "recovered", []):
        store.event("recover", note)
    clock = rig.clock
    t0 = clock.now()
    captured = 0
    reason = "complete"
    park = True

    bar = _progress(progress, total, len(done))
    try:
        rig.torque(True)
        rig.light.set_intensity(rig.config.light.level)
        rig.light.on()
        if rig.config.light.warmup_s and todo:
            clock.sleep(rig.config.light.warmup_s)
        for planned in todo:
            if stop.reason:
                break
            rig.move(planned.targets)
            rig.wait(rig.config.move_timeout_s)
            clock.sleep(rig.config.settle_s)
            measured = rig.positions()
            pose = rig.kinematics.pose(measured)
            status = rig.device_status()
            light = rig.light.status()
            if not light.on:
                raise DeviceFault(f"light is off ({light.fault or 'no reason given'})")
            for b, exposure_s in enumerate(exposures):
                if (planned.index, b) in done:
                    continue
                if stop.reason:  # stop between frames, not only between poses
                    break
                frame = rig.camera.capture(exposure_s)
                # The pending row goes in before the frame is written: if we die after the
                # frame lands but before the row is marked done, resume adopts the frame.
                cid = store.begin_capture(
                    pose_index=planned.index,
                    bracket_index=b,
                    exposure_s=exposure_s,
                    pose=(pose.theta_i, pose.phi_i, pose.theta_o, pose.phi_o),
                    axes_commanded=planned.targets,
                    axes_measured=measured,
                    light_dir=pose.wi.tolist(),
                    camera_dir=pose.wo.tolist(),
                    suffix=frame.suffix,
                    devices={"axes": status, "light": light.__dict__},
                    lab_time_s=clock.now() - t0,
                )
                store.finish_capture(cid, frame.data, frame.metadata)
                captured += 1
                bar.advance()
                if on_capture is not None:
                    on_capture(captured)
        if stop.reason:
            reason = stop.reason
    except DeviceFault as exc:
        reason = f"fault: {exc}"
    except KeyboardInterrupt:
        reason = "interrupted (KeyboardInterrupt)"
    except OSError as exc:
        # Disk full, quota, I/O error on the run directory: the frame being written is lost
        # only if it never reached disk (its row stays pending and is re-captured on resume);
        # every earlier frame is already safe. Stop the hardware rather than carry on blind.
        reason = f"storage: {exc.strerror or exc}" + (f" ({exc.filename})" if exc.filename else "")
    finally:
        bar.close()
    lab_time_s = clock.now() - t0
    total_done = store.count("done")
    complete = reason == "complete" and total_done >= total
    if complete:
        _safe_stop(rig, store, "complete", park=park)
        store.set_meta("lab_time_s", str(lab_time_s + float(store.meta("lab_time_s") or 0)))
        store.mark_complete()
    else:
        if reason == "complete":
            reason = f"incomplete: {total_done}/{total} captures done"
        _safe_stop(rig, store, reason, park=park)
        try:
            store.set_meta("lab_time_s", str(lab_time_s + float(store.meta("lab_time_s") or 0)))
        except Exception as exc:  # disk full: lab time is bookkeeping, the frames are safe
            _record(store, "warning", f"lab time not recorded: {exc}")
    return RunOutcome(complete, captured, adopted, total_done, reason, lab_time_s)


class _Bar:
    def __init__(self, total: int, completed: int) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._p = Progress(
            TextColumn("acquiring"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            transient=False,
        )
        self._task = self._p.add_task("acquire", total=total, completed=completed)
        self._p.start()

    def advance(self) -> None:
        self._p.advance(self._task)

    def close(self) -> None:
        self._p.stop()


class _NoBar:
    def advance(self) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(enabled: bool, total: int, completed: int) -> _Bar | _NoBar:
    return _Bar(total, completed) if enabled else _NoBar()


def lab_time_estimate_s(plan: Plan, rig_readout_s: float, settle_s: float) -> float:
    return plan.lab_time_s(rig_readout_s, settle_s)


def fmt_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    m, s = divmod(int(round(seconds)), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s"
