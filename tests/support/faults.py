"""Shared helpers for the fault tests (test_acquisition_faults, test_fault_scenarios,
test_crash_safety): a simulated rig whose servos the real dynamixel_sdk reaches over a
pseudo-terminal, and the three checks every fault must pass:

* SAFE — torque off on every emulated servo and the lamp off, read from the emulators' own
  state (the servo's Torque Enable register, the light emulator's `is_on`), never from what our
  driver believes it sent;
* RECORDED — the stop reason is an event in the manifest;
* RESUMABLE — after the fault is cleared a resume completes: the (pose, bracket) keys equal
  the plan's grid (counted here independently of the runner), no key twice, every frame's
  SHA-256 verifies, and every frame on disk is listed.

Run as a script it is the acquisition *process* for the subprocess tests (signals, kill -9):
it builds the simulated world, serves the bus and the light on ptys that the CLI opens through
stable symlinks (as a lab rig opens /dev/serial/by-id/...), runs the real `gonio acquire`
command line, and on a clean exit writes the emulators' final state to a JSON file:

    python tests/support/faults.py --rig RIG --tty-dir DIR --state STATE.json -- acquire ...
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import sqlite3
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.support.paths import REPO

if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

import tomli_w  # noqa: E402

from acquisition.config import PlanConfig, RigConfig, load_rig  # noqa: E402
from acquisition.plans import Plan, build_plan  # noqa: E402
from acquisition.rig import Rig, build_rig  # noqa: E402
from acquisition.runner import RunOutcome, run_acquisition  # noqa: E402
from acquisition.store import RunStore  # noqa: E402

__all__ = [
    "REPO",
    "SIM_RIG",
    "PLAN",
    "EXPECTED_KEYS",
    "TICK_RAD",
    "ARRIVAL_RAD",
    "expected_keys",
    "SimSession",
    "sim_session",
    "assert_safe",
    "assert_recorded",
    "assert_all_data",
    "done_count",
    "write_pty_rig",
    "write_plan",
    "acquire_cmd",
    "read_state",
]

SIM_RIG = REPO / "configs" / "rigs" / "sim.toml"
# 3 × 2 × 2 = 12 grid poses, all reachable (θ_i ≠ θ_o or Δφ ≠ 0: separation ≥ 5°).
PLAN = PlanConfig(
    name="faults",
    theta_i_deg=(20.0, 40.0, 60.0),
    theta_o_deg=(0.0, 30.0),
    delta_phi_deg=(180.0, 90.0),
    exposures_s=(0.002,),
)
TICK_RAD = 2 * math.pi / 4096
# The driver's arrival tolerance is 8 ticks (DynamixelAxis.tolerance_ticks); gear ratio 1.
ARRIVAL_RAD = 8 * TICK_RAD


def expected_keys(plan: PlanConfig) -> set[tuple[int, int]]:
    """Every (pose, bracket) of a plan whose grid is all reachable, from the grid itself."""
    grid = itertools.product(plan.theta_i_deg, plan.theta_o_deg, plan.delta_phi_deg)
    return {(i, b) for i, _ in enumerate(grid) for b in range(len(plan.exposures_s))}


EXPECTED_KEYS = expected_keys(PLAN)


# -- in-process rig over a pty ------------------------------------------------------------------
@dataclass
class SimSession:
    world: Any
    transport: Any  # PtyTransport
    config: RigConfig  # bus.url = the pty's slave path
    store: RunStore
    plan: Plan

    def rig(self) -> Rig:
        return build_rig(self.config)

    def run(self, **kw: Any) -> RunOutcome:
        rig = self.rig()
        try:
            return run_acquisition(self.store, rig, self.plan, progress=False, **kw)
        finally:
            rig.close()

    def events(self) -> list[tuple[str, str]]:
        return [(k, m) for _, k, m in self.store.events()]

    def resume_and_check(self, expected: set[tuple[int, int]] | None = None) -> RunOutcome:
        """Resume (the fault cleared): it completes with all data, and the rig ends safe."""
        out = self.run()
        assert out.complete, out.reason
        assert_all_data(self.store, EXPECTED_KEYS if expected is None else expected)
        assert_safe(self.world, self.config)
        return out


@contextmanager
def sim_session(
    tmp_path: Path,
    *,
    on_alert: str = "stop",
    plan: PlanConfig = PLAN,
    run_dir: Path | None = None,
) -> Iterator[SimSession]:
    """The sim rig with the real SDK talking to the bus emulator over a pty; a fresh run store
    in `run_dir` (default tmp_path/run)."""
    from gonio.backends import prepare_backends
    from simulator.dxl.transport import PtyTransport

    base = load_rig(SIM_RIG)
    base = base.model_copy(update={"bus": base.bus.model_copy(update={"on_alert": on_alert})})
    world = prepare_backends(base)  # registers clock "sim", the light and the sim camera
    transport = PtyTransport(world.bus)
    config = base.model_copy(
        update={"bus": base.bus.model_copy(update={"url": transport.port_path})}
    )
    store = RunStore.create(run_dir or tmp_path / "run", tomli_w.dumps({"note": "fault test"}))
    try:
        yield SimSession(world, transport, config, store, build_plan(config, plan))
    finally:
        store.close()
        transport.close()
        assert transport.error is None, transport.error


# -- the three checks ---------------------------------------------------------------------------
def assert_safe(world: Any, config: RigConfig, skip_torque: frozenset[int] = frozenset()) -> None:
    """SAFE, from the emulators' state: the lamp is off and no servo holds torque (except those
    in `skip_torque`, which could not be reached — the caller must show that was recorded)."""
    assert not world.light.is_on, "the lamp is still on"
    for a in config.axes:
        if a.id not in skip_torque:
            assert world.bus.servo(a.id).register("torque_enable") == 0, a.role


def assert_recorded(store: RunStore, reason: str) -> None:
    """RECORDED: the stop reason is in the manifest's events."""
    events = [(k, m) for _, k, m in store.events()]
    assert ("stop", reason) in events, events


def assert_all_data(store: RunStore, expected: set[tuple[int, int]] = EXPECTED_KEYS) -> None:
    """RESUMABLE with nothing lost: complete, the plan's keys exactly once each, every checksum
    verifies, nothing pending, and the frames directory holds exactly the listed frames."""
    captures = list(store.captures())
    keys = [(c.pose_index, c.bracket_index) for c in captures]
    assert len(keys) == len(set(keys)), "duplicate captures"
    assert set(keys) == expected
    assert store.verify() == []
    assert store.count("pending") == 0
    frames = store.root / "frames"
    on_disk = {f"frames/{p.name}" for p in frames.iterdir() if not p.name.startswith(".")}
    assert on_disk == {c.frame_path for c in captures}
    assert store.complete


def done_count(run_dir: Path) -> int:
    """Frames marked done in a (possibly live) manifest, read-only; 0 before it exists."""
    db = run_dir / "manifest.sqlite"
    if not db.exists():
        return 0
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            (n,) = conn.execute("SELECT COUNT(*) FROM captures WHERE status = 'done'").fetchone()
        finally:
            conn.close()
        return int(n)
    except sqlite3.Error:  # schema not created yet, or caught mid-creation
        return 0


# -- the acquisition as a separate process ------------------------------------------------------
def write_pty_rig(dest: Path, tty_dir: Path, **top: Any) -> Path:
    """The sim rig with its bus and light on ptys reached through `tty_dir/dxl` and
    `tty_dir/light` (symlinks the launcher re-points every session); `top` overrides top-level
    keys (e.g. settle_s)."""
    text = SIM_RIG.read_text()
    for old, new in (
        ('"dxlsim://sim-two-arm"', json.dumps(str(tty_dir / "dxl"))),
        ('"lightsim://sim-two-arm"', json.dumps(str(tty_dir / "light"))),
        ('"../scenes/demo.toml"', json.dumps(str(REPO / "configs" / "scenes" / "demo.toml"))),
        ('"sim-camera.json"', json.dumps(str(REPO / "configs" / "rigs" / "sim-camera.json"))),
    ):
        assert old in text, old
        text = text.replace(old, new)
    for key, value in top.items():
        line = f"{key} = {json.dumps(value)}"
        text, n = re.subn(rf"^{key}\s*=.*$", line, text, count=1, flags=re.M)
        if not n:
            text = line + "\n" + text
    dest.write_text(text)
    return dest


def write_plan(dest: Path, plan: PlanConfig) -> Path:
    doc = {
        "name": plan.name,
        "type": "isotropic",
        "theta_i_deg": list(plan.theta_i_deg),
        "theta_o_deg": list(plan.theta_o_deg),
        "delta_phi_deg": list(plan.delta_phi_deg),
        "exposures_s": list(plan.exposures_s),
    }
    dest.write_text(tomli_w.dumps(doc))
    return dest


def acquire_cmd(rig: Path, plan: Path, out: Path, tty_dir: Path, state: Path) -> list[str]:
    """`gonio acquire` (the real CLI) in a process that also hosts the emulators on ptys."""
    return [
        sys.executable,
        str(Path(__file__).resolve()),
        "--rig",
        str(rig),
        "--tty-dir",
        str(tty_dir),
        "--state",
        str(state),
        "--",
        "acquire",
        "--rig",
        str(rig),
        "--plan",
        str(plan),
        "--out",
        str(out),
        "--no-progress",
    ]


def read_state(state: Path) -> dict[str, Any]:
    return json.loads(state.read_text())


def _relink(link: Path, target: str) -> None:
    tmp = link.with_name(f".{link.name}.{os.getpid()}")
    os.symlink(target, tmp)
    os.replace(tmp, link)  # atomic: a reader never sees the link missing


def _serve_and_acquire(argv: list[str]) -> int:
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--rig", type=Path, required=True)
    ap.add_argument("--tty-dir", type=Path, required=True)
    ap.add_argument("--state", type=Path, required=True)
    ap.add_argument("cli", nargs=argparse.REMAINDER)
    ns = ap.parse_args(argv)
    cli_args = ns.cli[1:] if ns.cli[:1] == ["--"] else ns.cli

    import gonio.cli
    import gonio.pipeline
    from simulator.dxl.transport import PtyTransport
    from simulator.scene import load_scene
    from simulator.world import SimWorld

    rig = load_rig(ns.rig)
    # The rig must open the links this launcher serves; a rig naming another session's links
    # would reach a pty that no longer exists (or, by chance, someone else's).
    for url, name in ((rig.bus.url, "dxl"), (rig.light.url, "light")):
        if Path(url) != ns.tty_dir / name:
            ap.error(f"rig {ns.rig} opens {url}, not this launcher's {ns.tty_dir / name}")
    # The emulators live in this process (they die with it, as a rig on the same power strip
    # would): build them as the in-process sim rig, then serve them on ptys.
    local = rig.model_copy(
        update={
            "bus": rig.bus.model_copy(update={"url": "dxlsim://faults"}),
            "light": rig.light.model_copy(update={"url": "lightsim://faults"}),
        }
    )
    world = SimWorld(local, load_scene(rig.scene))  # registers clock "sim" and camera "sim"
    ns.tty_dir.mkdir(parents=True, exist_ok=True)
    bus_pty, light_pty = PtyTransport(world.bus), PtyTransport(world.light)
    _relink(ns.tty_dir / "dxl", bus_pty.port_path)
    _relink(ns.tty_dir / "light", light_pty.port_path)
    # The CLI would build a second world; it must use this one (whose devices sit on the
    # ptys). This is the only seam: everything else is the unmodified command line.
    gonio.pipeline.prepare_backends = lambda _rig, _scene=None: world
    sys.argv = ["gonio", *cli_args]
    code: int | str | None = 0
    try:
        gonio.cli.main()
    except SystemExit as exc:
        code = exc.code
    state = {
        "exit_code": code,
        "torque_enable": {
            str(a.id): world.bus.servo(a.id).register("torque_enable") for a in rig.axes
        },
        "light_on": world.light.is_on,
        "light_fault": world.light.fault,
        "pty_errors": [repr(t.error) for t in (bus_pty, light_pty) if t.error is not None],
    }
    for t in (bus_pty, light_pty):
        t.close()
    tmp = ns.state.with_name(ns.state.name + ".tmp")
    tmp.write_text(json.dumps(state))
    os.replace(tmp, ns.state)
    return code if isinstance(code, int) else 1


if __name__ == "__main__":
    sys.exit(_serve_and_acquire(sys.argv[1:]))
