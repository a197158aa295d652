"""`gonio runs list`, `gonio runs show RUN` and `gonio rig check`: what runs exist, what state
they are in, why they stopped; and whether every servo of a rig answers and is healthy.

Everything here only reads: a run directory is opened read-only (an acquisition may be writing
it at the same time; SQLite WAL lets readers in), and `rig check` never moves or powers a servo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Group
from rich.table import Table

from acquisition.config import PlanConfig, RigConfig
from acquisition.store import RunStore, RunStoreError

__all__ = [
    "RunSummary",
    "find_runs",
    "summarize_run",
    "runs_table",
    "show_run",
    "ServoCheck",
    "check_rig",
    "rig_check_table",
]


@dataclass
class RunSummary:
    path: Path
    status: str  # "complete", "incomplete", or "unreadable: ..."
    done: int
    pending: int
    total: int | None  # captures the plan asks for (None when the frozen config is unusable)
    started: str
    lab_time_s: float
    last_stop: str | None  # the latest stop reason recorded in the manifest
    rig: dict[str, Any] = field(default_factory=dict)
    plan: dict[str, Any] = field(default_factory=dict)


def _total(frozen: dict[str, Any]) -> int | None:
    """Captures the frozen plan asks for on the frozen rig (same expansion as the runner)."""
    from acquisition.plans import build_plan

    try:
        rig = RigConfig.model_validate(frozen["rig"])
        plan = PlanConfig.model_validate(frozen["plan"])
        # Raster order: the count does not depend on the order, and 2-opt would cost seconds
        # per run on big plans.
        built = build_plan(rig, plan.model_copy(update={"order": "raster"}))
    except Exception:  # a summary must not fail on one odd run
        return None
    return len(built.poses) * len(plan.exposures_s)


def summarize_run(path: Path | str) -> RunSummary:
    path = Path(path)
    try:
        store = RunStore.open(path)
    except RunStoreError as exc:
        return RunSummary(path, f"unreadable: {exc}", 0, 0, None, "?", math.nan, None)
    try:
        try:
            frozen = store.run_config()
        except Exception:
            frozen = {}
        stops = [m for _, k, m in store.events() if k == "stop"]
        started = str(frozen.get("gonio", {}).get("started_at") or store.meta("created_at") or "?")
        return RunSummary(
            path=path,
            status="complete" if store.complete else "incomplete",
            done=store.count("done"),
            pending=store.count("pending"),
            total=_total(frozen) if frozen else None,
            started=started,
            lab_time_s=float(store.meta("lab_time_s") or "nan"),
            last_stop=stops[-1] if stops else None,
            rig=frozen.get("rig", {}),
            plan=frozen.get("plan", {}),
        )
    finally:
        store.close()


def find_runs(root: Path | str) -> list[Path]:
    """Run directories at `root` itself, directly under it, or one level deeper."""
    root = Path(root)
    if not root.is_dir():
        return []
    found = []
    for cand in [root, *sorted(root.iterdir()), *sorted(root.glob("*/*"))]:
        if cand.is_dir() and (cand / "manifest.sqlite").exists():
            found.append(cand)
    return found


def _fmt_s(seconds: float) -> str:
    from acquisition.runner import fmt_duration

    return fmt_duration(seconds) if math.isfinite(seconds) else "-"


def runs_table(root: Path | str) -> Table:
    t = Table(title=f"runs under {root}")
    for col in ("run", "status", "captures", "started", "lab time", "last stop"):
        t.add_column(col)
    for path in find_runs(root):
        s = summarize_run(path)
        total = "?" if s.total is None else str(s.total)
        t.add_row(
            str(path),
            s.status,
            f"{s.done}/{total}",
            s.started,
            _fmt_s(s.lab_time_s),
            s.last_stop or "",
        )
    return t


def show_run(path: Path | str, *, verify: bool = True) -> tuple[Group, list[str]]:
    """Renderable summary of one run, and the checksum problems found (empty when all verify)."""
    path = Path(path)
    s = summarize_run(path)
    if s.status.startswith("unreadable"):
        raise RunStoreError(s.status.removeprefix("unreadable: "))
    head = Table(title=f"run {path}", show_header=False)
    head.add_column("key")
    head.add_column("value")
    rig, plan = s.rig, s.plan
    head.add_row("status", s.status)
    head.add_row("started", s.started)
    total = "?" if s.total is None else str(s.total)
    head.add_row("captures", f"{s.done} done / {total} planned, {s.pending} pending")
    head.add_row("lab time", _fmt_s(s.lab_time_s))
    head.add_row(
        "rig",
        f"{rig.get('name', '?')} (bus {rig.get('bus', {}).get('url', '?')}, "
        f"{len(rig.get('axes', []))} axes, camera {rig.get('camera', {}).get('backend', '?')})",
    )
    head.add_row(
        "plan",
        f"{plan.get('name', '?')} ({plan.get('type', '?')}, order {plan.get('order', '?')}, "
        f"exposures {plan.get('exposures_s', '?')} s)",
    )
    store = RunStore.open(path)
    try:
        problems = store.verify() if verify else []
        events = store.events()
    finally:
        store.close()
    if verify:
        head.add_row(
            "checksums",
            f"all {s.done} verify" if not problems else f"{len(problems)} problem(s)",
        )
    ev = Table(title="events")
    for col in ("at", "kind", "message"):
        ev.add_column(col)
    for at, kind, message in events:
        ev.add_row(at, kind, message)
    parts: list[Any] = [head, ev]
    if problems:
        pt = Table(title="checksum problems")
        pt.add_column("frame")
        for p in problems[:50]:
            pt.add_row(p)
        parts.append(pt)
    return Group(*parts), problems


# -- rig check ----------------------------------------------------------------------------------
@dataclass
class ServoCheck:
    role: str
    servo_id: int
    ok: bool
    model: str = "-"
    firmware: int | None = None
    voltage_V: float | None = None
    temperature_C: float | None = None
    limits_ticks: tuple[int, int] | None = None
    hardware_error: list[str] = field(default_factory=list)
    problem: str = ""


def check_rig(rig: RigConfig) -> list[ServoCheck]:
    """Ping every servo of `rig` and read its model, firmware, voltage, temperature, position
    limits and hardware error status. Never writes a register (no torque, no reboot)."""
    from acquisition.clock import get_clock
    from acquisition.dynamixel import (
        ADDR,
        MODEL_NAMES,
        DynamixelBus,
        decode_hardware_error,
    )
    from acquisition.protocols import DeviceFault

    bus = DynamixelBus(
        rig.bus.url,
        baudrate=rig.bus.baudrate,
        retries=rig.bus.retries,
        on_alert="stop",
        clock=get_clock(rig.clock),
    )
    rows = []
    try:
        for a in rig.axes:
            row = ServoCheck(a.role, a.id, ok=False)
            try:
                number = bus.ping(a.id)
                row.model = MODEL_NAMES.get(number, f"model {number}")

                def reg(name: str, size: int, sid: int = a.id) -> int:
                    return bus.read(sid, ADDR[name], size, check_alert=False)

                row.firmware = reg("firmware_version", 1)
                row.voltage_V = reg("present_input_voltage", 2) / 10.0
                row.temperature_C = float(reg("present_temperature", 1))
                row.limits_ticks = (reg("min_position_limit", 4), reg("max_position_limit", 4))
                hw = reg("hardware_error_status", 1)
                row.hardware_error = decode_hardware_error(hw) if hw else []
                notes = []
                if row.model != a.model:
                    notes.append(f"config says {a.model}")
                if hw:
                    notes.append("hardware error latched (reboot clears it once the cause is gone)")
                row.problem = "; ".join(notes)
                row.ok = not notes
            except DeviceFault as exc:
                row.problem = str(exc)
            rows.append(row)
    finally:
        bus.close()
    return rows


def rig_check_table(rig: RigConfig, rows: list[ServoCheck]) -> Table:
    t = Table(title=f"rig {rig.name}: bus {rig.bus.url} at {rig.bus.baudrate} baud")
    cols = ("role", "id", "model", "firmware", "voltage", "temp", "limits (ticks)", "hw error")
    for col in (*cols, "status"):
        t.add_column(col)
    for r in rows:
        t.add_row(
            r.role,
            str(r.servo_id),
            r.model,
            "-" if r.firmware is None else str(r.firmware),
            "-" if r.voltage_V is None else f"{r.voltage_V:.1f} V",
            "-" if r.temperature_C is None else f"{r.temperature_C:.0f} °C",
            "-" if r.limits_ticks is None else f"{r.limits_ticks[0]}..{r.limits_ticks[1]}",
            ", ".join(r.hardware_error) or ("-" if r.firmware is None else "none"),
            "OK" if r.ok else f"FAIL: {r.problem}",
        )
    return t
