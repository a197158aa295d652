"""Soak (issue 9): a long simulated run with faults injected at 0.5 % of operations.

The rig is the simulated two-arm rig with real drivers over pseudo-terminals: the unmodified
dynamixel_sdk talks to the Protocol 2.0 emulator, `SerialLight` to the light emulator. Frames
are real files (EXR from a 16×16 sensor, so the run stays I/O- and driver-bound) in a real
SQLite manifest. Faults, each at rate `--rate` (default 0.005):

* status packets (per packet): dropped, truncated or with a broken CRC — the driver retries;
* hardware alerts (per capture): an overload on a random servo, dated to the middle of its
  next move; `on_alert = "reboot"` — the driver reboots the servo and goes on;
* camera misses (per capture): the capture returns no frame — the runner stops safely;
* light glitches (per capture): the lamp drops out — the runner stops at the next pose.

After every safe stop the bench checks the rig is safe *in the emulators* (no servo torqued,
lamp off), then resumes on the same run directory, as an operator would. At the end every
frame's SHA-256 is verified and the (pose, bracket) keys are compared with the plan. Memory is
sampled from /proc (VmRSS, VmHWM) once the first session has warmed up and at the end.

Peak memory (issue 23, item 6). The 741 MiB "peak RSS" one `make bench` printed was not the
soak's: VmHWM is a per-process high-water mark, and run_all.py then ran every benchmark in one
process, so the soak reported bench_big_fit's and bench_render's peaks. The soak now resets the
mark when it starts (/proc/self/clear_refs, Linux ≥ 4.0) and run_all.py runs each benchmark in a
process of its own; alone it peaks at 175–197 MiB: the interpreter with numpy, Mitsuba's
imports and OpenEXR (≈ 140 MiB before the first capture) plus the manifest, the emulators and
the pty buffers. The run fails above PEAK_RSS_LIMIT_MIB, or if the peak grows more than 10 %
between the warm point and the end (a leak per capture would show there).

Run: .venv/bin/python benchmarks/bench_soak.py [--captures 5000] [--rate 0.005] [--seed 0]
"""

from __future__ import annotations

import argparse
import gc
import itertools
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import tomli_w
from _common import reachable_poses

__all__ = ["main", "soak"]

REPO = Path(__file__).resolve().parent.parent
BRACKETS = (0.001, 0.002, 0.004, 0.008)  # 4 exposures per pose: captures = 4 × poses
# Bound on the soak's own peak resident set: 1.5× the 197 MiB measured alone (docs/performance.md),
# so a leak of ~20 KiB per capture over 5000 captures, or a stray full-frame buffer kept per
# pose, fails the run.
PEAK_RSS_LIMIT_MIB = 300
GROWTH_LIMIT = 0.10  # peak after warm-up vs at the end


def _trim() -> None:
    """Collect garbage and hand freed heap back to the OS (glibc malloc_trim), so RSS shows
    memory still in use rather than free blocks the allocator keeps."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def _reset_peak() -> bool:
    """Reset this process's VmHWM to its current RSS, so the peak measured is the soak's own
    (writing "5" to /proc/self/clear_refs; Linux ≥ 4.0). False where that is not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _mem_kib(trim: bool = False) -> dict[str, int]:
    """Current (VmRSS) and peak (VmHWM) resident set of this process, KiB."""
    if trim:
        _trim()
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(rest.split()[0])
    return out


def _poses(rig, n: int) -> list[tuple[float, float, float, float]]:
    grid = itertools.product(
        np.arange(5.0, 80.0, 2.5), np.arange(0.0, 85.0, 5.0), (0.0, 45.0, 90.0, 135.0, 180.0)
    )
    poses = reachable_poses(rig, grid, n)
    if len(poses) < n:
        raise ValueError(f"only {len(poses)} reachable poses in the soak grid, {n} asked")
    return poses


def soak(captures: int = 5000, rate: float = 0.005, seed: int = 0, root: str | None = None):
    from acquisition.config import PlanConfig, load_rig
    from acquisition.plans import build_plan
    from acquisition.rig import build_rig
    from acquisition.runner import run_acquisition
    from acquisition.store import RunStore
    from simulator.dxl import ReplyFaults
    from simulator.dxl.transport import PtyTransport
    from simulator.scene import load_scene
    from simulator.world import SimWorld

    peak_reset = _reset_peak()
    rng = np.random.default_rng(seed)
    base = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    scene = load_scene(base.scene)
    scene = scene.model_copy(
        update={"camera": scene.camera.model_copy(update={"resolution": (16, 16)})}
    )
    n_poses = -(-captures // len(BRACKETS))
    plan_cfg = PlanConfig(
        name="soak",
        type="explicit",
        poses_deg=tuple(_poses(base, n_poses)),
        exposures_s=BRACKETS,
    )
    world = SimWorld(base, scene)  # clock "sim", camera "sim"
    bus_pty, light_pty = PtyTransport(world.bus), PtyTransport(world.light)
    rig_cfg = base.model_copy(
        update={
            "bus": base.bus.model_copy(update={"url": bus_pty.port_path, "on_alert": "reboot"}),
            "light": base.light.model_copy(update={"url": light_pty.port_path}),
        }
    )
    plan = build_plan(rig_cfg, plan_cfg)
    total = len(plan.poses) * len(BRACKETS)
    ids = [a.id for a in rig_cfg.axes]
    # Alerts go to servos that move in this plan (light_phi stays at 0 for every pose here, and
    # an alert dated to mid-move would wait for a move that never comes).
    moving_ids = [
        a.id for a in rig_cfg.axes if len({round(p.targets[a.role], 6) for p in plan.poses}) > 1
    ]

    # Packet faults on every servo, 0.5 % of status packets in all (2:1:2 drop:truncate:crc).
    world.bus.set_reply_faults(
        ReplyFaults(drop_p=0.4 * rate, truncate_p=0.2 * rate, bad_crc_p=0.4 * rate)
    )
    world.camera_faults.miss_p = rate
    injected: Counter[str] = Counter()
    driver: Counter[str] = Counter()
    stops: Counter[str] = Counter()
    unsafe_stops = 0
    mem_warm: dict[str, int] | None = None
    # (captures done, session, VmRSS KiB, VmRSS KiB after gc + malloc_trim)
    rss_trace: list[tuple[int, int, int, int]] = []
    done_at_warm = 0

    with tempfile.TemporaryDirectory(dir=root) as tmp:
        store = RunStore.create(Path(tmp) / "run", tomli_w.dumps({"note": "soak"}))

        def on_capture(n: int) -> None:
            nonlocal mem_warm, done_at_warm
            done = store.count("done")
            if mem_warm is None and done >= min(500, total // 10):
                gc.collect()
                mem_warm, done_at_warm = _mem_kib(), done
            if done % 500 == 0:
                rss_trace.append((done, sessions, _mem_kib()["VmRSS"], _mem_kib(True)["VmRSS"]))
            if rng.random() < rate:
                world.bus.inject_alert(int(rng.choice(moving_ids)), "overload", while_moving=True)
                injected["alert"] += 1
            if rng.random() < rate:
                world.light.is_on = False  # the lamp drops out; the runner sees it next pose
                injected["light_glitch"] += 1

        t0 = time.perf_counter()
        sessions = 0
        while True:
            sessions += 1
            rig = build_rig(rig_cfg)
            try:
                out = run_acquisition(store, rig, plan, progress=False, on_capture=on_capture)
            finally:
                for bus in {id(ax.bus): ax.bus for ax in rig.axes.values()}.values():
                    driver.update(bus.stats)
                rig.close()
            if out.complete:
                break
            kind = (
                "camera"
                if "camera" in out.reason
                else "light"
                if "light" in out.reason
                else "servo/bus"
            )
            stops[kind] += 1
            torque = [world.bus.servo(i).register("torque_enable") for i in ids]
            if any(torque) or world.light.is_on:
                unsafe_stops += 1
            if sessions > 10 * (1 + total * rate * 4):
                raise RuntimeError(f"soak does not converge: {out.reason}")
        wall = time.perf_counter() - t0
        gc.collect()
        mem_end = _mem_kib()
        keys = [(c.pose_index, c.bracket_index) for c in store.captures()]
        problems = store.verify()
        expected = {(p.index, b) for p in plan.poses for b in range(len(BRACKETS))}
        ok = (
            store.complete
            and not problems
            and len(keys) == len(set(keys))
            and set(keys) == expected
            and unsafe_stops == 0
        )
        store.close()
    for t in (bus_pty, light_pty):
        t.close()
        if t.error is not None:
            raise RuntimeError(f"pty transport failed: {t.error!r}")

    packet = sum(world.bus.faults.counts.values())
    injected["packet"] = packet
    injected["camera_miss"] = world.camera_faults.counts["camera_miss"]
    fired = len(world.bus.fired_alerts)
    return {
        "captures": len(keys),
        "planned": total,
        "poses": len(plan.poses),
        "sessions": sessions,
        "injected": dict(injected),
        "alerts_fired": fired,
        "instructions": world.bus.packets_in,
        "driver": dict(driver),
        "stops": dict(stops),
        "unsafe_stops": unsafe_stops,
        "verified_ok": ok,
        "checksum_problems": len(problems),
        "mem_warm": mem_warm or {},
        "done_at_warm": done_at_warm,
        "mem_end": mem_end,
        "rss_trace": rss_trace,
        "peak_reset": peak_reset,
        "wall_s": wall,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=5000)
    ap.add_argument("--rate", type=float, default=0.005)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--root", default=None, help="directory for the temporary run")
    ap.add_argument("--trace-mem", action="store_true", help="print RSS every 500 captures")
    args = ap.parse_args(argv if argv is not None else [])
    r = soak(args.captures, args.rate, args.seed, args.root)
    inj, drv, stops = r["injected"], r["driver"], r["stops"]
    n_inj = inj["packet"] + r["alerts_fired"] + inj["camera_miss"] + inj.get("light_glitch", 0)
    # Survived: a packet fault retried, an alert rebooted through, or a stop that was safe
    # (checked in the emulators) and resumed — the run completing with every frame verified.
    survived = (n_inj - r["unsafe_stops"]) if r["verified_ok"] else 0
    print(
        f"soak: {r['captures']} captures ({r['poses']} poses × {len(BRACKETS)} exposures, "
        f"16×16 EXR) in {r['sessions']} session(s), {r['wall_s']:.0f} s wall"
    )
    print(
        f"  faults injected at {args.rate:.1%}: {n_inj} — {inj['packet']} status packets "
        f"(drop/truncate/bad CRC) in {r['instructions']} bus transactions, "
        f"{r['alerts_fired']} overload alerts mid-move "
        f"({inj.get('alert', 0)} armed), {inj['camera_miss']} camera misses, "
        f"{inj.get('light_glitch', 0)} light glitches"
    )
    print(
        f"  driver: {drv.get('retries', 0)} retries, {drv.get('alerts', 0)} alerts seen, "
        f"{drv.get('reboots', 0)} reboots; safe stops + resumes: "
        + (", ".join(f"{v} {k}" for k, v in sorted(stops.items())) or "none")
        + f"; unsafe stops: {r['unsafe_stops']}"
    )
    print(
        f"  faults survived: {survived}/{n_inj}; every frame verified: {r['verified_ok']} "
        f"({r['checksum_problems']} checksum problems)"
    )
    w, e = r["mem_warm"], r["mem_end"]
    memory_ok = True
    if w:
        growth = e["VmHWM"] / w["VmHWM"] - 1
        memory_ok = growth <= GROWTH_LIMIT and e["VmHWM"] / 1024 <= PEAK_RSS_LIMIT_MIB
        whose = "the soak's own" if r["peak_reset"] else "this process's (peak could not be reset)"
        print(
            f"  memory ({whose}): peak RSS {w['VmHWM'] / 1024:.0f} MiB after "
            f"{r['done_at_warm']} captures, {e['VmHWM'] / 1024:.0f} MiB at the end "
            f"({growth:+.1%}, limit +{GROWTH_LIMIT:.0%}; bound {PEAK_RSS_LIMIT_MIB} MiB); "
            f"RSS {w['VmRSS'] / 1024:.0f} → {e['VmRSS'] / 1024:.0f} MiB"
        )
    if args.trace_mem:
        for done, session, rss, trimmed in r["rss_trace"]:
            print(
                f"    {done:6d} captures  session {session:3d}  RSS {rss / 1024:6.1f} MiB  "
                f"(after malloc_trim {trimmed / 1024:6.1f} MiB)"
            )
    if not r["verified_ok"]:
        raise SystemExit("soak FAILED: run incomplete, duplicates, bad checksums or unsafe stop")
    if not memory_ok:
        raise SystemExit("soak FAILED: peak memory above its bound or growing during the run")


if __name__ == "__main__":
    main(sys.argv[1:])
