"""Benchmark: protocol fuzzing at volume (issue 9 acceptance: >= 10^5 generated packets per
side, zero crashes or hangs; report count and run time).

Emulator side: seeded numpy streams of random bytes, valid packets (every instruction, random
IDs and parameters, the header pattern planted for byte stuffing), truncated, bit-flipped and
CRC-broken packets, cut into random chunks and fed to `PacketDecoder.feed` and
`EmulatedBus.handle`. After every stream the bus must still answer a PING (resynchronisation).

Driver side: `acquisition.dynamixel.DynamixelBus` on the real `dynamixel_sdk`, over a
`dxlsim://` port whose status packets are mangled (drop, truncate, bit flips, broken CRC,
mutated with a re-fixed CRC, wrong LEN, any error byte, garbage before/after, duplicated,
random bytes). Every call must end in a value of the right shape or DynamixelCommError /
DynamixelError / HardwareAlert. Then `SerialLight` on a `lightsim://` port with garbage replies:
a value or LightError.

A crash is any other exception; a hang is a call still running after HANG_S (SIGALRM
watchdog; the SDK busy-polls in Python so the signal lands).

Run: .venv/bin/python benchmarks/bench_fuzz.py [--packets 100000] [--light 20000] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import time
import traceback
import uuid
from collections import Counter

import numpy as np

from acquisition.clock import VirtualClock
from acquisition.dynamixel import DynamixelBus, DynamixelCommError, DynamixelError, HardwareAlert
from acquisition.light import LightError, SerialLight
from simulator.dxl import EmulatedBus, register_bus, unregister_bus
from simulator.dxl import protocol as P
from simulator.dxl.fuzzing import MANGLE_KINDS, Hang, MangledReplies, mangle_reply, watchdog
from simulator.light import EmulatedLight, register_light, unregister_light

__all__ = ["main", "fuzz_emulator", "fuzz_driver", "fuzz_light"]

INSTRUCTIONS = np.array(
    [1, 2, 3, 4, 5, 6, 8, 0x10, 0x55, 0x82, 0x83, 0x8A, 0x92, 0x93], dtype=np.int64
)
CLASSIFIED = (DynamixelCommError, DynamixelError, HardwareAlert)
XM430 = 1020  # e-Manual: XM430-W350 model number, the PING reply of servo 1


def _bytes(rng: np.random.Generator, n: int) -> bytes:
    return rng.integers(0, 256, n, dtype=np.uint8).tobytes()


def _params(rng: np.random.Generator) -> bytes:
    out = bytearray(_bytes(rng, int(rng.integers(0, 48))))
    for _ in range(int(rng.integers(0, 3))):  # plant FF FF FD (stuffing) at random places
        i = int(rng.integers(0, len(out) + 1))
        out[i:i] = b"\xff\xff\xfd"
    return bytes(out)


def _valid(rng: np.random.Generator) -> bytes:
    inst = int(rng.choice(INSTRUCTIONS)) if rng.random() < 0.85 else int(rng.integers(0, 256))
    did = int(rng.integers(0, 8)) if rng.random() < 0.7 else int(rng.integers(0, 0xFF))
    return P.encode_packet(did, inst, _params(rng))


def _flip(rng: np.random.Generator, pkt: bytes, k: int) -> bytes:
    b = bytearray(pkt)
    for pos in rng.integers(0, 8 * len(b), k):
        b[pos // 8] ^= 1 << (pos % 8)
    return bytes(b)


def generate_packet(rng: np.random.Generator) -> tuple[str, bytes]:
    """One fuzzed instruction-side item: (kind, bytes)."""
    kind = ("random", "valid", "truncated", "flipped", "crc")[int(rng.integers(0, 5))]
    if kind == "random":
        return kind, _bytes(rng, int(rng.integers(0, 64)))
    pkt = _valid(rng)
    if kind == "truncated":
        return kind, pkt[: int(rng.integers(0, len(pkt)))]
    if kind == "flipped":
        return kind, _flip(rng, pkt, int(rng.integers(1, 5)))
    if kind == "crc":
        return kind, pkt[:-1] + bytes([pkt[-1] ^ int(rng.integers(1, 256))])
    return kind, pkt


def _new_bus() -> EmulatedBus:
    bus = EmulatedBus(VirtualClock(), rng=0)
    for i in range(1, 8):
        bus.add_servo(i, "XM430-W350" if i % 2 else "XL430-W250")
    return bus


def fuzz_emulator(n_packets: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    kinds: Counter[str] = Counter()
    crashes: list[str] = []
    hangs = resync_failures = replies = streams = 0
    max_s = 0.0  # longest time one stream took (the "bounded time per input")
    ping = P.encode_packet(1, P.INST_PING)
    bus, dec = _new_bus(), P.PacketDecoder()
    t0 = time.perf_counter()
    done = 0
    while done < n_packets:
        # a stream of 1..8 items with random chunking; fresh bus every 50 streams (fuzzed
        # writes change IDs, baud rates, status return levels...)
        if streams % 50 == 0:
            bus, dec = _new_bus(), P.PacketDecoder()
        items = [generate_packet(rng) for _ in range(int(rng.integers(1, 9)))]
        kinds.update(k for k, _ in items)
        done += len(items)
        streams += 1
        stream = b"".join(b for _, b in items)
        cuts = np.sort(rng.integers(0, len(stream) + 1, int(rng.integers(0, 4))))
        edges = [0, *cuts.tolist(), len(stream)]
        t_in = time.perf_counter()
        try:
            with watchdog():
                for a, b in zip(edges, edges[1:], strict=False):
                    dec.feed(stream[a:b])
                    replies += len(bus.handle(stream[a:b]))
            max_s = max(max_s, time.perf_counter() - t_in)
            # Resynchronisation, on the decoder and on a fresh bus (the fuzzed writes on `bus`
            # may legitimately have silenced servo 1, e.g. by changing its ID). The partial
            # packet a stream may end in is flushed first, as a host's inter-packet timeout
            # would.
            with watchdog():
                probe = _new_bus()
                probe.handle(stream)
                probe.reset_input()
                out = P.PacketDecoder().feed(probe.feed(ping))
                dec.clear()
                bus.reset_input()
                resynced = [q.raw for q in dec.feed(ping)] == [ping] and bool(out)
        except Hang:
            hangs += 1
            continue
        except Exception:
            crashes.append(f"{stream.hex()}: {traceback.format_exc(limit=3)}")
            continue
        if not resynced or out[-1].dxl_id != 1 or out[-1].data[:2] != XM430.to_bytes(2, "little"):
            resync_failures += 1
    wall = time.perf_counter() - t0
    return {
        "packets": done,
        "streams": streams,
        "kinds": dict(kinds),
        "replies": replies,
        "crashes": crashes,
        "hangs": hangs,
        "resync_failures": resync_failures,
        "max_s": max_s,
        "wall_s": wall,
    }


def mangle(rng: np.random.Generator, pkt: bytes) -> tuple[str, bytes]:
    """The tests' rewrite (simulator.dxl.fuzzing.mangle_reply), its choices drawn by `rng`."""
    kind = MANGLE_KINDS[int(rng.integers(0, len(MANGLE_KINDS)))]
    nums = [int(x) for x in rng.integers(0, 2**16, 3)]
    return kind, mangle_reply(kind, nums, _bytes(rng, int(rng.integers(0, 21))), pkt)


DRIVER_OPS = (
    ("ping", lambda d: d.ping(1)),
    ("read4s", lambda d: d.read(1, 132, 4)),
    ("read1", lambda d: d.read(1, 64, 1)),
    ("read_bytes", lambda d: d.read_bytes(1, 122, 14)),
    ("write4", lambda d: d.write(1, 112, 4, 100)),
    ("write1", lambda d: d.write(2, 65, 1, 1)),
    ("torque_on", lambda d: d.torque(1, True)),
    ("torque_off", lambda d: d.torque(1, False)),
    ("sync_read", lambda d: d.sync_read(132, 4, [1, 2])),
    ("reboot", lambda d: d.reboot(2)),
    ("hw", lambda d: d.hardware_error(1)),
)


def _value_ok(op: str, v) -> bool:
    if op == "ping":
        return isinstance(v, int) and 0 <= v <= 0xFFFF
    if op == "read4s":
        return isinstance(v, int) and -(2**31) <= v < 2**31
    if op in ("read1", "hw"):
        return isinstance(v, int) and 0 <= v <= 0xFF
    if op == "read_bytes":
        return isinstance(v, bytes) and len(v) == 14
    if op == "sync_read":
        return isinstance(v, dict) and set(v) == {1, 2}
    return v is None


def fuzz_driver(n_packets: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    bus = EmulatedBus(VirtualClock(), rng=0)
    bus.add_servo(1, "XM430-W350")
    bus.add_servo(2, "XL430-W250")
    dev = MangledReplies(bus, lambda pkt: mangle(rng, pkt))
    name = f"benchfuzz-{uuid.uuid4().hex[:8]}"
    register_bus(name, dev)
    drivers = [
        DynamixelBus(
            f"dxlsim://{name}",
            baudrate=1_000_000,
            retries=1,
            on_alert=mode,
            clock=VirtualClock(),
            timeout_margin_ms=-33.0,  # in-process port: no FTDI latency timer to wait out
            reboot_settle_s=0.0,
        )
        for mode in ("stop", "reboot")
    ]
    try:

        def call(rng_: np.random.Generator):
            op, fn = DRIVER_OPS[int(rng_.integers(0, len(DRIVER_OPS)))]
            drv = drivers[int(rng_.integers(0, 2))]
            return op, lambda: fn(drv), lambda: setattr(drv.port, "is_using", False)

        r = _fuzz_calls(dev, n_packets, rng, call, _value_ok, CLASSIFIED)
    finally:
        for d in drivers:
            d.close()
        unregister_bus(name)
    return {**r, "kinds": dict(dev.kinds)}


def _fuzz_calls(dev, limit: int, rng, pick, value_ok, classified) -> dict:
    """Driver calls picked by `pick(rng)` → (op, call, after) until the mangling device has
    answered `limit` times: counted outcomes, malformed values (`value_ok(op, v)` False), the
    longest call, hangs (the watchdog) and crashes (anything but the `classified` faults)."""
    outcomes: Counter[str] = Counter()
    crashes: list[str] = []
    hangs = bad_values = calls = 0
    max_s = 0.0  # longest single call
    t0 = time.perf_counter()
    while dev.count < limit:
        op, fn, after = pick(rng)
        calls += 1
        t_in = time.perf_counter()
        try:
            with watchdog():
                v = fn()
            max_s = max(max_s, time.perf_counter() - t_in)
            outcomes["value"] += 1
            bad_values += not value_ok(op, v)
        except classified as exc:
            max_s = max(max_s, time.perf_counter() - t_in)
            outcomes[type(exc).__name__] += 1
        except Hang:
            hangs += 1
        except Exception:
            crashes.append(f"{op}: {traceback.format_exc(limit=4)}")
        after()
    return {
        "packets": dev.count,
        "calls": calls,
        "outcomes": dict(outcomes),
        "bad_values": bad_values,
        "max_s": max_s,
        "crashes": crashes,
        "hangs": hangs,
        "wall_s": time.perf_counter() - t0,
    }


LIGHT_CANNED = (
    b"OK\n",
    b"ERR X\n",
    b"STAT ON nan inf OK\n",
    b"STAT ON 1 2\n",
    b"IDN \xff\n",
    b"\n",
    b"STAT OFF 0.000 0.000 OK\n",
)


def _light_mangle(rng: np.random.Generator, reply: bytes) -> tuple[str, bytes]:
    u = rng.random()
    if u < 0.3:
        return "keep", reply
    if u < 0.5:
        return "canned", LIGHT_CANNED[int(rng.integers(0, len(LIGHT_CANNED)))]
    if u < 0.75:
        return "random_line", _bytes(rng, int(rng.integers(0, 40))) + b"\n"
    if u < 0.85:
        return "flip", _flip(rng, reply, int(rng.integers(1, 4)))
    return "random", _bytes(rng, int(rng.integers(0, 40)))


def fuzz_light(n_replies: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    dev = MangledReplies(EmulatedLight(VirtualClock()), lambda r: _light_mangle(rng, r))
    name = f"benchfuzzlight-{uuid.uuid4().hex[:8]}"
    register_light(name, dev)
    drv = SerialLight(f"lightsim://{name}", timeout_s=0.002, retries=1)
    ops = (
        ("identify", lambda d: d.identify()),
        ("on", lambda d: d.on()),
        ("off", lambda d: d.off()),
        ("intensity", lambda d: d.set_intensity(0.25)),
        ("status", lambda d: d.status()),
        ("clear", lambda d: d.clear_fault()),
    )

    def light_value_ok(op: str, v) -> bool:
        if op == "status":
            return math.isfinite(v.intensity) and math.isfinite(v.measured)
        return isinstance(v, str) if op == "identify" else True

    def call(rng_: np.random.Generator):
        op, fn = ops[int(rng_.integers(0, len(ops)))]
        return op, lambda: fn(drv), lambda: None

    try:
        return _fuzz_calls(dev, n_replies, rng, call, light_value_ok, LightError)
    finally:
        drv.close()
        unregister_light(name)


def _report(title: str, r: dict) -> int:
    print(
        f"{title}: {r['packets']} packets"
        + (f" in {r['calls']} calls" if "calls" in r else f" in {r['streams']} streams")
        + f", {len(r['crashes'])} crashes, {r['hangs']} hangs"
        + (f", {r['resync_failures']} resync failures" if "resync_failures" in r else "")
        + (f", {r['bad_values']} malformed values" if "bad_values" in r else "")
        + f", {r['wall_s']:.1f} s wall ({r['packets'] / r['wall_s']:.0f} packets/s)"
        + f", longest input {1e3 * r['max_s']:.1f} ms"
    )
    if "kinds" in r:
        print("  generated: " + ", ".join(f"{k} {v}" for k, v in sorted(r["kinds"].items())))
    if "outcomes" in r:
        print("  outcomes:  " + ", ".join(f"{k} {v}" for k, v in sorted(r["outcomes"].items())))
    for c in r["crashes"][:5]:
        print("  CRASH " + c)
    return len(r["crashes"]) + r["hangs"] + r.get("resync_failures", 0) + r.get("bad_values", 0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--packets", type=int, default=100_000, help="per side (emulator, driver)")
    ap.add_argument("--light", type=int, default=20_000, help="light-controller replies")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv if argv is not None else [])
    failures = _report("emulator (decoder + EmulatedBus)", fuzz_emulator(args.packets, args.seed))
    driver = fuzz_driver(args.packets, args.seed)
    failures += _report("driver (dynamixel_sdk + DynamixelBus)", driver)
    failures += _report("light driver (SerialLight)", fuzz_light(args.light, args.seed))
    print(f"total failures: {failures}")
    return 1 if failures else 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
