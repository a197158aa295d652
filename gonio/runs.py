"""`gonio runs list`, `gonio runs show RUN` and `gonio rig check`: what runs exist, what state
they are in, why they stopped; and whether every servo of a rig answers and is healthy.

Everything here only reads: a run directory is opened read-only (an acquisition may be writing
it at the same time; SQLite WAL lets readers in), and `rig check` never moves or powers a servo.

Where runs live, and which names are allowed (`resolve_run`, `check_run_path`):

- The *runs directory* is `--root` of `gonio runs` (default `runs/` under the working
  directory); `gonio demo` without `--out` creates its run there too.
- A *run name* is one plain path component (`2026-11-23-teflon`): it is looked up inside the
  runs directory, and must stay there — a name with `..`, a path separator, or that resolves
  outside the runs directory through a symlink, is refused.
- An explicit *run path* (`gonio runs show ./runs/x`, `gonio acquire --out /data/run7`,
  `gonio demo --out tmp/d`) is the user's own choice of place and is used as given, absolute
  or relative — but never with a `..` component: every run path the CLI accepts names its
  directory directly, so a pasted or generated name can never climb out of where it is put.
- Inside a run, paths come from the manifest and are data, not trusted: `acquisition.store`
  refuses any frame path that is absolute, has `..`, or resolves outside the run directory.
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
from gonio.errors import UserError
from gonio.plain_text import plain

__all__ = [
    "RunPathError",
    "resolve_run",
    "check_run_path",
    "RunSummary",
    "find_runs",
    "summarize_run",
    "runs_table",
    "show_run",
]


class RunPathError(UserError):
    """A run name or path that would leave its directory. One-line message."""


def check_run_path(path: Path | str, what: str = "--out") -> Path:
    """An explicit run path, refused when it has a `..` component (see the module docstring)."""
    p = Path(path)
    if ".." in p.parts:
        raise RunPathError(
            f"{what} {str(path)!r}: '..' is not allowed in run paths; give the directory "
            "without '..' (e.g. an absolute path)"
        )
    if str(path).strip() == "" or "\x00" in str(path):
        raise RunPathError(f"{what} {str(path)!r}: not a usable directory name")
    return p


def resolve_run(arg: Path | str, root: Path | str = "runs") -> Path:
    """The run directory meant by a `gonio runs show` argument: a bare name is looked up inside
    `root` (and must stay inside it); a path is used as given (without `..`)."""
    text = str(arg)
    p = check_run_path(arg, "RUN")
    root = Path(root)
    if len(p.parts) == 1 and not p.is_absolute():
        if p.exists():
            return p  # a run directory in the working directory, named explicitly
        full = root / p
        if not full.resolve().is_relative_to(root.resolve()):
            raise RunPathError(
                f"RUN {text!r}: resolves outside the runs directory {root} (symlink); refusing"
            )
        return full
    return p


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
        if plan.exposure_mode == "auto" or plan.type == "adaptive":
            # Auto-exposure decides the frames per pose, and phase 2 of an adaptive plan is
            # decided during the run: no count is known before the run ends.
            return None
        # Raster order: the count does not depend on the order, and 2-opt would cost seconds
        # per run on big plans.
        built = build_plan(rig, plan.model_copy(update={"order": "raster"}))
    except Exception:  # a summary must not fail on one odd run
        return None
    return len(built.poses) * len(plan.exposures_s)


def _exposures(plan: dict[str, Any]) -> str:
    if plan.get("exposure_mode") == "auto":
        return "auto per pose"
    return f"{plan.get('exposures_s', '?')} s"


def summarize_run(path: Path | str) -> RunSummary:
    path = Path(path)
    try:
        store = RunStore.open(path)
    except RunStoreError as exc:
        return RunSummary(path, f"unreadable: {exc}", 0, 0, None, "?", math.nan, None)
    try:
        # A damaged manifest or a run.toml from a newer gonio makes the run "unreadable" here
        # (one row of `runs list`); `runs show` turns that into its one-line error.
        frozen = store.run_config()
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
    except RunStoreError as exc:
        return RunSummary(path, f"unreadable: {exc}", 0, 0, None, "?", math.nan, None)
    except ValueError as exc:  # e.g. a lab_time_s that is not a number
        msg = f"{path}/manifest.sqlite: damaged meta value ({exc})"
        return RunSummary(path, f"unreadable: {msg}", 0, 0, None, "?", math.nan, None)
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
    t = Table(title=plain(f"runs under {root}"))
    for col in ("run", "status", "captures", "started", "lab time", "last stop"):
        t.add_column(col)
    for path in find_runs(root):
        s = summarize_run(path)
        total = "?" if s.total is None else str(s.total)
        t.add_row(
            *map(
                plain,
                (path, s.status, f"{s.done}/{total}", s.started, _fmt_s(s.lab_time_s)),
            ),
            plain(s.last_stop or ""),
        )
    return t


def show_run(path: Path | str, *, verify: bool = True) -> tuple[Group, list[str]]:
    """Renderable summary of one run, and the checksum problems found (empty when all verify)."""
    path = Path(path)
    s = summarize_run(path)
    if s.status.startswith("unreadable"):
        raise RunStoreError(s.status.removeprefix("unreadable: "))
    head = Table(title=plain(f"run {path}"), show_header=False)
    head.add_column("key")
    head.add_column("value")
    rig, plan = s.rig, s.plan
    head.add_row("status", plain(s.status))
    head.add_row("started", plain(s.started))
    if s.total is None:
        head.add_row("captures", f"{s.done} done, {s.pending} pending (count set during the run)")
    else:
        head.add_row("captures", f"{s.done} done / {s.total} planned, {s.pending} pending")
    head.add_row("lab time", _fmt_s(s.lab_time_s))
    head.add_row(
        "rig",
        plain(
            f"{rig.get('name', '?')} (bus {rig.get('bus', {}).get('url', '?')}, "
            f"{len(rig.get('axes', []))} axes, camera {rig.get('camera', {}).get('backend', '?')})"
        ),
    )
    head.add_row(
        "plan",
        plain(
            f"{plan.get('name', '?')} ({plan.get('type', '?')}, order {plan.get('order', '?')}, "
            f"exposures {_exposures(plan)})"
        ),
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
        ev.add_row(plain(at), plain(kind), plain(message))
    parts: list[Any] = [head, ev]
    if problems:
        pt = Table(title="checksum problems")
        pt.add_column("frame")
        for p in problems[:50]:
            pt.add_row(plain(p))
        parts.append(pt)
    return Group(*parts), problems
