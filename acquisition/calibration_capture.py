"""Calibration captures as phases of a run: darks, a flat field and reference-target poses.

A plan's `[calibration]` section (acquisition.config.CalibrationPhasesConfig) asks for them;
`run_acquisition` records them into RUN/calibration/ before the first measurement pose, on any
rig: the same camera `capture()` as the measurement, the operator asked before each step that
needs hands (acquisition.operator). Frames go through the manifest's calibration table with the
same pending → frame → done protocol as every capture (acquisition.store), so a killed run
resumes in the middle of a phase and nothing captured is lost. `gonio capture KIND RUN` records
a new take of one kind into an existing run (the older take stays on disk and in the manifest).

What the operator changed is remembered in the manifest (meta `operator_state`: lens open /
capped / flat source, holder sample / reference / board), so a run resumed after a crash in the
reference phase asks for the sample back before measuring.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acquisition.config import (
    CalibrationPhasesConfig,
    DarkPhaseConfig,
    FlatPhaseConfig,
    PlanConfig,
    ReferencePhaseConfig,
    RigConfig,
)
from acquisition.exposure import exposure_ladder
from acquisition.kinematics import Kinematics, Pose
from acquisition.operator import Operator, ask, step
from acquisition.store import RunStore
from plumbing.atomic import atomic_write_bytes
from plumbing.config import ConfigError

__all__ = [
    "plan_exposures_s",
    "reference_exposures_s",
    "CalibrationPhases",
    "check_calibration_plan",
    "OPERATOR_STATE",
]

OPERATOR_STATE = "operator_state"  # manifest meta key: {"lens": ..., "holder": ...}
_NORMAL = {"lens": "open", "holder": "sample"}


def plan_exposures_s(plan: PlanConfig) -> tuple[float, ...]:
    """Every exposure the plan may take: its brackets, or the auto-exposure ladder (what the
    master darks must cover)."""
    if plan.exposure_mode == "auto":
        return exposure_ladder(plan.auto_exposure)
    return tuple(plan.exposures_s)


def reference_exposures_s(plan: PlanConfig, phase: ReferencePhaseConfig) -> tuple[float, ...]:
    """The phase's exposures, or three brackets at most (shortest, middle, longest) of the
    plan's: they span its HDR range; a long auto-exposure ladder would only multiply frames."""
    if phase.exposures_s:
        return tuple(phase.exposures_s)
    t = sorted(plan_exposures_s(plan))
    return tuple(t if len(t) <= 3 else [t[0], t[len(t) // 2], t[-1]])


def check_calibration_plan(rig: RigConfig, plan: PlanConfig, plan_name: str = "plan") -> None:
    """Refuse, before any device opens, a calibration plan this rig cannot carry out."""
    cal = plan.calibration
    if cal.reference is None:
        return
    if rig.reference is None:
        raise ConfigError(
            f"{plan_name}: calibration.reference asks for reference-target captures, but the "
            "rig file has no [reference] section (the target's albedo or f_ref table, size_m)"
        )
    kin = Kinematics(rig)
    for deg in cal.reference.poses_deg:
        kin.targets(Pose.from_deg(*deg))  # raises Unreachable with the reason


@dataclass
class CalibrationPhases:
    """Records the calibration phases of `plan` into `store` with `rig` and `operator`.

    `emit(event, **fields)` writes to the run log; `stopping()` is True when a stop was
    requested (checked between frames).
    """

    store: RunStore
    rig: Any  # acquisition.rig.Rig
    plan: PlanConfig
    operator: Operator
    emit: Callable[..., None]
    stopping: Callable[[], bool]
    captured: int = 0

    # -- operator state ---------------------------------------------------------------------
    def _state(self) -> dict[str, str]:
        raw = self.store.meta(OPERATOR_STATE)
        return {**_NORMAL, **(json.loads(raw) if raw else {})}

    def _set_state(self, **changes: str) -> None:
        self.store.set_meta(OPERATOR_STATE, json.dumps({**self._state(), **changes}))

    def _ask(self, action: str, **detail: Any) -> None:
        s = step(action, **detail)
        self.emit("operator", action=action, prompt=s.prompt)
        ask(self.operator, s)

    def set_lens(self, want: str, *, confirm: bool = False) -> None:
        """Bring the lens to "open", "capped" or "flat", asking for each change; `confirm`
        asks for the wanted state even if the manifest says it holds (after a crash the
        operator checks it again — and a restarted simulator has lost it)."""
        have = self._state()["lens"]
        if have == want and not confirm:
            return
        if have != want:
            if have == "capped":
                self._ask("uncap_lens")
            elif have == "flat":
                self._ask("unmount_flat")
            self._set_state(lens="open")
        if want == "capped":
            self._ask("cap_lens")
        elif want == "flat":
            self._ask("mount_flat")
        self._set_state(lens=want)

    def set_holder(self, want: str, *, confirm: bool = False, **detail: Any) -> None:
        """Bring the holder to "sample", "reference" or "board" (asking for the swap)."""
        if self._state()["holder"] == want and not confirm:
            return
        if want == "sample":
            self._ask("mount_sample", mark=self.rig.config.sample.orientation_mark)
        elif want == "reference":
            self._ask("mount_reference", target=_target_words(self.rig.config))
        else:
            self._ask("mount_board", **detail)
        self._set_state(holder=want)

    def ready_for_measurement(self) -> None:
        """Lens open, sample in the holder: what the measurement poses need."""
        self.set_lens("open")
        self.set_holder("sample")

    # -- phases -----------------------------------------------------------------------------
    def before_light(self, phases: CalibrationPhasesConfig | None = None) -> bool:
        """Darks, then the flat (neither needs the lamp or a servo). False if stopped."""
        cal = phases or self.plan.calibration
        if cal.dark is not None and not self.dark(cal.dark):
            return False
        return cal.flat is None or self.flat(cal.flat)

    def dark(self, cfg: DarkPhaseConfig, *, new_take: bool = False) -> bool:
        exposures = tuple(cfg.exposures_s or plan_exposures_s(self.plan))
        shots = [(t, None) for t in exposures for _ in range(cfg.count)]
        return self._frames("dark", shots, "capped", {"count": cfg.count}, new_take)

    def flat(self, cfg: FlatPhaseConfig, *, new_take: bool = False) -> bool:
        t = cfg.exposure_s or max(plan_exposures_s(self.plan))
        shots = [(t, None) for _ in range(cfg.count)]
        return self._frames("flat", shots, "flat", {"count": cfg.count}, new_take)

    def reference(self, cfg: ReferencePhaseConfig, *, new_take: bool = False) -> bool:
        """The target in the sample's place at each pose, every exposure (light on)."""
        ref = self.rig.config.reference
        if ref is None:
            raise ConfigError("the rig file has no [reference] section")
        exposures = reference_exposures_s(self.plan, cfg)
        shots = [(t, (j, deg)) for j, deg in enumerate(cfg.poses_deg) for t in exposures]
        take, todo = self._take("reference", len(shots), new_take, self._target_record)
        if not todo:
            return True
        done = self.store.calibration_done_seqs("reference", take)
        self.set_lens("open")
        self.set_holder("reference", confirm=True)
        kin: Kinematics = self.rig.kinematics
        self.emit("phase_start", phase="calibration:reference", frames=len(shots), todo=todo)
        where: dict[int, dict[str, Any]] = {}
        for seq, (t, (j, deg)) in enumerate(shots):
            if seq in done:
                continue
            if self.stopping():
                return False
            if j not in where:
                where[j] = self._go_to(kin.targets(Pose.from_deg(*deg)))
            meta = {"pose": j, "pose_deg": list(deg), **where[j]}
            self._capture("reference", take, seq, t, meta)
        self.emit("phase_done", phase="calibration:reference", take=take)
        return True

    def reference_todo(self) -> bool:
        """Does the plan's reference phase still have frames to take?"""
        cfg = self.plan.calibration.reference
        if cfg is None:
            return False
        take = self.store.calibration_take("reference")
        info = self.store.calibration_take_info("reference", take) if take else None
        return info is None or info["done"] < info["expected"]

    # -- plumbing -----------------------------------------------------------------------------
    def _take(
        self, kind: str, expected: int, new_take: bool, describe: Callable[[int], dict] | None
    ) -> tuple[int, int]:
        """(take number, frames still to capture): the run's take 1 resumed, or a new take."""
        take = self.store.calibration_take(kind)
        info = self.store.calibration_take_info(kind, take) if take else None
        if new_take or info is None:
            take = self.store.start_calibration_take(kind, expected)
            if describe is not None:
                self.store.set_take_description(kind, take, describe(take))
            return take, expected
        return take, max(info["expected"] - info["done"], 0)

    def _frames(
        self,
        kind: str,
        shots: Sequence[tuple[float, Any]],
        lens: str,
        desc: dict[str, Any],
        new_take: bool,
    ) -> bool:
        take, todo = self._take(kind, len(shots), new_take, lambda _t: desc)
        if not todo:
            return True
        done = self.store.calibration_done_seqs(kind, take)
        self.set_lens(lens, confirm=True)
        self.emit("phase_start", phase=f"calibration:{kind}", frames=len(shots), todo=todo)
        for seq, (t, _) in enumerate(shots):
            if seq in done:
                continue
            if self.stopping():
                return False
            self._capture(kind, take, seq, t, {})
        self.emit("phase_done", phase=f"calibration:{kind}", take=take)
        return True

    def _go_to(self, targets: dict[str, float]) -> dict[str, Any]:
        rig = self.rig
        rig.move(targets)
        rig.wait(rig.config.move_timeout_s)
        rig.clock.sleep(rig.config.settle_s)
        light = rig.light.status()
        if not light.on:
            from acquisition.protocols import DeviceFault

            raise DeviceFault(f"light is off ({light.fault or 'no reason given'})")
        return {"axes_rad": rig.positions(), "light_measured": light.measured}

    def _capture(self, kind: str, take: int, seq: int, t: float, meta: dict[str, Any]) -> None:
        frame = self.rig.camera.capture(float(t))
        rid = self.store.begin_calibration(kind, take, seq, float(t), frame.suffix, meta)
        self.store.finish_calibration(rid, frame.data, dict(frame.metadata))
        self.captured += 1
        self.emit("calibration_capture", kind=kind, take=take, seq=seq, exposure_s=float(t))

    def _target_record(self, take: int) -> dict[str, Any]:
        """The reference target's description for this take (the f_ref table copied into the
        run, so the run stays self-contained)."""
        ref = self.rig.config.reference
        d: dict[str, Any] = {"size_m": ref.size_m, "rel_sigma": ref.rel_sigma}
        if ref.type == "lambertian":
            return {**d, "type": "lambertian", "reflectance": list(ref.albedo)}
        src = Path(ref.table)
        rel = f"calibration/reference/f_ref-t{take:02d}{src.suffix.lower()}"
        dest = self.store.root / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        if not dest.exists():
            atomic_write_bytes(dest, src.read_bytes())
        return {**d, "type": "table", "file": rel, "source": str(src)}


def _target_words(rig: RigConfig) -> str:
    ref = rig.reference
    if ref is None:
        return "reference target"
    if ref.type == "lambertian":
        return f"Lambertian, albedo {', '.join(f'{a:g}' for a in ref.albedo)}"
    return f"table {Path(ref.table).name}"
