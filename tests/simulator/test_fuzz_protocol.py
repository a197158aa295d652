"""Protocol fuzzing (issue 9, item 1): neither side of the Dynamixel / light wire may crash or
hang on bad bytes, and every failure the driver reports is a classified `DeviceFault`.

Emulator side: random bytes, valid packets (every instruction, random IDs and parameters),
truncated, bit-flipped, byte-stuffed and CRC-broken packets, and concatenations with garbage
between them go into `PacketDecoder.feed` and `EmulatedBus.handle`. Policy (as on a real
servo): the emulator swallows garbage silently and never raises; a CRC-broken packet to one of
its IDs gets a CRC-error status; valid packets among garbage are still answered.

Driver side: the real `dynamixel_sdk` under `acquisition.dynamixel.DynamixelBus`, on a
`dxlsim://` port whose device mangles every status packet as Hypothesis decides (drop,
truncate, flip bits, break or *re-fix* the CRC after mutating, prepend/append garbage,
duplicate, replace with random bytes). Every call must end in a value of the right shape or a
`DynamixelCommError` / `DynamixelError` / `HardwareAlert`. The `SerialLight` driver meets the
same treatment and must end in a value or `LightError`.

Independent ground truth: packets are built with the ROBOTIS SDK's own `addStuffing` and
`updateCRC` (not with `simulator.dxl.protocol`); model numbers come from the e-Manual (XM430-W350
= 1020). Hangs are caught by a SIGALRM watchdog (the SDK busy-polls in Python, so the signal
lands). Volume runs (>= 10^5 packets per side) live in benchmarks/bench_fuzz.py.
"""

from __future__ import annotations

import math
import uuid

from dynamixel_sdk import PacketHandler
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acquisition.clock import VirtualClock
from acquisition.dynamixel import (
    DynamixelBus,
    DynamixelCommError,
    DynamixelError,
    HardwareAlert,
)
from acquisition.light import LightError, SerialLight
from simulator.dxl import EmulatedBus, register_bus, unregister_bus
from simulator.dxl import protocol as P
from simulator.dxl.fuzzing import MANGLE_KINDS, MangledReplies, mangle_reply, watchdog
from simulator.light import EmulatedLight, register_light, unregister_light

SDK = PacketHandler(2.0)
HEADER = b"\xff\xff\xfd\x00"
XM430_MODEL = 1020  # e-Manual, XM430-W350 model number
ALL_INSTRUCTIONS = [
    P.INST_PING,
    P.INST_READ,
    P.INST_WRITE,
    P.INST_REG_WRITE,
    P.INST_ACTION,
    P.INST_FACTORY_RESET,
    P.INST_REBOOT,
    P.INST_CLEAR,
    P.INST_STATUS,
    P.INST_SYNC_READ,
    P.INST_SYNC_WRITE,
    P.INST_FAST_SYNC_READ,
    P.INST_BULK_READ,
    P.INST_BULK_WRITE,
]
CLASSIFIED = (DynamixelCommError, DynamixelError, HardwareAlert)

# Per-input wall-clock budget. The slowest legitimate input is a driver call whose every
# attempt times out: (retries + 1) x ~1 ms packet timeout here, plus the SDK's Python
# overhead; 5 s is three orders of magnitude above that, so only a real hang trips it.

FUZZ = settings(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def sdk_packet(dxl_id: int, inst: int, params: bytes = b"") -> bytes:
    """A wire packet built by the ROBOTIS SDK's own stuffing and CRC (independent encoder).
    (The SDK's txPacket discards addStuffing's return value; we use it.)"""
    n = len(params)
    pkt = [0xFF, 0xFF, 0xFD, 0x00, dxl_id, (n + 3) & 0xFF, (n + 3) >> 8, inst, *params, 0, 0]
    pkt = SDK.addStuffing(pkt)
    total = (pkt[5] | pkt[6] << 8) + 7
    crc = SDK.updateCRC(0, pkt, total - 2)
    pkt[total - 2], pkt[total - 1] = crc & 0xFF, crc >> 8
    return bytes(pkt[:total])


def crc_ok(packet: bytes) -> bool:
    return SDK.updateCRC(0, list(packet), len(packet) - 2) == packet[-2] | packet[-1] << 8


def no_header(data: bytes) -> bytes:
    """Garbage that cannot start a packet: every FF FF FD 00 broken up."""
    while HEADER in data:
        data = data.replace(HEADER, b"\xff\xfe\xfd\x00")
    return data


# ---- strategies ----------------------------------------------------------------------------

ids = st.integers(0, 0xFE)
instructions = st.one_of(st.sampled_from(ALL_INSTRUCTIONS), st.integers(0, 255))
# Parameters with the header pattern planted in them, so stuffing is exercised often.
stuffable = st.lists(
    st.one_of(st.binary(max_size=6), st.just(b"\xff\xff\xfd"), st.just(b"\xff\xff\xfd\xfd")),
    max_size=8,
).map(b"".join)
params = st.one_of(st.binary(max_size=48), stuffable)
valid_packets = st.builds(sdk_packet, ids, instructions, params)


@st.composite
def truncated(draw):
    pkt = draw(valid_packets)
    return pkt[: draw(st.integers(0, len(pkt) - 1))]


@st.composite
def bit_flipped(draw):
    pkt = bytearray(draw(valid_packets))
    for pos in draw(st.lists(st.integers(0, 8 * len(pkt) - 1), min_size=1, max_size=4)):
        pkt[pos // 8] ^= 1 << (pos % 8)
    return bytes(pkt)


@st.composite
def crc_broken(draw):
    pkt = bytearray(draw(valid_packets))
    pkt[-2] ^= draw(st.integers(0, 255))
    pkt[-1] ^= draw(st.integers(1, 255))  # never zero: the CRC really is wrong
    return bytes(pkt)


segments = st.one_of(
    st.binary(max_size=64),
    valid_packets,
    truncated(),
    bit_flipped(),
    crc_broken(),
)
streams = st.lists(segments, max_size=8).map(b"".join)


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    edges = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    return [data[a:b] for a, b in zip(edges, edges[1:], strict=False)]


def make_bus() -> EmulatedBus:
    bus = EmulatedBus(VirtualClock(), rng=0)
    bus.add_servo(1, "XM430-W350")
    bus.add_servo(2, "XL430-W250")
    return bus


def status_packets(data: bytes) -> list[bytes]:
    """Split a reply stream into packets by the LEN field (replies are never garbage)."""
    out = []
    while data:
        assert data[:4] == HEADER, data.hex()
        total = 7 + (data[5] | data[6] << 8)
        out.append(data[:total])
        data = data[total:]
    return out


# ---- emulator side -------------------------------------------------------------------------


@FUZZ
@given(dxl_id=ids, inst=instructions, prm=params)
def test_encoder_matches_sdk_including_stuffing(dxl_id, inst, prm) -> None:
    assert P.encode_packet(dxl_id, inst, prm) == sdk_packet(dxl_id, inst, prm)


@settings(FUZZ, max_examples=400)
@given(
    items=st.lists(st.tuples(st.binary(max_size=24).map(no_header), valid_packets), max_size=6),
    tail=st.binary(max_size=24).map(no_header),
    cuts=st.lists(st.integers(0, 10_000), max_size=10),
)
def test_decoder_recovers_every_packet_between_garbage(items, tail, cuts) -> None:
    # Garbage that holds no header is skipped; every SDK-built packet comes out whole, with
    # its parameters unstuffed, however the stream is chunked.
    stream = b"".join(g + p for g, p in items) + tail
    dec = P.PacketDecoder()
    got = []
    with watchdog():
        for chunk in chunked(stream, cuts):
            got += dec.feed(chunk)
    assert [(q.raw, q.crc_ok) for q in got] == [(p, True) for _, p in items]
    for q, (_, p) in zip(got, items, strict=True):
        assert sdk_packet(q.dxl_id, q.instruction, q.params) == p  # unstuffed params re-encode
    assert dec.pending() <= 3  # at most a partial header is kept


@settings(FUZZ, max_examples=800)
@given(stream=streams, cuts=st.lists(st.integers(0, 10_000), max_size=6))
def test_decoder_and_bus_never_raise_or_hang(stream, cuts) -> None:
    dec = P.PacketDecoder()
    bus = make_bus()
    replies = []
    with watchdog():
        for chunk in chunked(stream, cuts):
            for q in dec.feed(chunk):
                assert len(q.raw) == 7 + (q.raw[5] | q.raw[6] << 8)
            replies += bus.handle(chunk)
    # the decoder never holds more than one maximal packet's worth of bytes
    assert dec.pending() < 7 + P.PacketDecoder.MAX_LENGTH
    # whatever the bus said is well formed: status packets with a correct CRC
    for r in replies:
        for pkt in status_packets(r.data):
            assert pkt[7] == P.INST_STATUS
            assert crc_ok(pkt) or pkt[4] == P.BROADCAST_ID  # FAST SYNC READ may be cut short


@settings(FUZZ, max_examples=500)
@given(
    junk=st.lists(
        st.one_of(st.binary(max_size=32).map(no_header), crc_broken(), valid_packets),
        max_size=5,
    ),
)
def test_ping_after_garbage_is_answered(junk) -> None:
    # Junk made of header-free bytes and *complete* packets (valid or CRC-broken) cannot
    # swallow the PING that follows: the last reply must be servo 1's PING status.
    bus = make_bus()
    for i in range(3, 9):  # more servos = more IDs a random packet can hit
        bus.add_servo(i, "XM430-W350")
    with watchdog():
        bus.handle(b"".join(junk))
        bus.reset_input()  # junk may end in a header-free partial; a real host waits it out
        reply = bus.feed(sdk_packet(1, P.INST_PING))
    pkts = status_packets(reply)
    assert len(pkts) == 1
    pkt = pkts[0]
    assert crc_ok(pkt) and pkt[4] == 1 and pkt[7] == P.INST_STATUS
    assert pkt[9] | pkt[10] << 8 == XM430_MODEL


@settings(FUZZ, max_examples=150)
@given(junk=streams, fresh=st.booleans())
def test_resynchronises_after_any_garbage(junk, fresh) -> None:
    # Arbitrary junk may end in a dangling header whose LEN swallows what follows, as on a
    # real bus. It can swallow at most 7 + MAX_LENGTH bytes, so among enough back-to-back
    # PINGs (10 bytes each) one is answered correctly.
    bus = make_bus()
    ping = sdk_packet(1, P.INST_PING)
    n = math.ceil((7 + P.PacketDecoder.MAX_LENGTH) / len(ping)) + 2
    with watchdog():
        bus.handle(junk)
        if fresh:
            bus.handle(ping)
        reply = bus.feed(ping * n)
    answers = [
        p
        for p in status_packets(reply)
        if p[4] == 1 and crc_ok(p) and len(p) == 14 and p[8] & 0x7F == 0
    ]
    assert answers and answers[-1][9] | answers[-1][10] << 8 == XM430_MODEL


def test_fast_sync_read_too_long_for_one_packet_is_swallowed() -> None:
    # Regression (found by fuzzing): FAST SYNC READ of 0xFFFF bytes from two servos needs a
    # LEN above 0xFFFF; the emulator used to raise ValueError building it. A real servo
    # cannot form that packet either: it stays silent.
    bus = make_bus()
    prm = bytes([0, 0, 0xFF, 0xFF, 1, 2])
    assert bus.feed(sdk_packet(P.BROADCAST_ID, P.INST_FAST_SYNC_READ, prm)) == b""
    # and the bus still answers afterwards
    assert len(status_packets(bus.feed(sdk_packet(2, P.INST_PING)))) == 1


@settings(FUZZ, max_examples=400)
@given(
    lines=st.lists(
        st.one_of(
            st.binary(max_size=40),
            st.sampled_from([b"IDN?", b"ON", b"OFF", b"INT 0.5", b"INT nan", b"STAT?", b"CLR"]),
        ),
        max_size=6,
    )
)
def test_light_emulator_answers_every_line_in_ascii(lines) -> None:
    light = EmulatedLight(VirtualClock())
    stream = b"".join(line + b"\n" for line in lines)
    with watchdog():
        out = b"".join(r.data for r in light.handle(stream))
    # one reply line per LF sent (docs/light-protocol.md), all ASCII
    assert out.count(b"\n") == stream.count(b"\n")
    out.decode("ascii")


# ---- driver side ---------------------------------------------------------------------------


# A rewrite, drawn before the call so the draws never depend on how many replies the driver
# asks for (which may depend on timing under load): (kind, numbers, bytes), see `mangle`.
mangle_specs = st.tuples(
    st.sampled_from(MANGLE_KINDS),
    st.lists(st.integers(0, 2**16), min_size=3, max_size=3),
    st.binary(max_size=20),
)


def mangle(spec, pkt: bytes) -> bytes:
    kind, nums, blob = spec
    return mangle_reply(kind, nums, blob, pkt)


class Scripted:
    """Rewrites successive replies with a pre-drawn list of specs; unchanged afterwards."""

    def __init__(self, specs, apply) -> None:
        self.specs, self.apply = list(specs), apply

    def __call__(self, reply: bytes) -> bytes:
        return self.apply(self.specs.pop(0), reply) if self.specs else reply


def _check_value(op: str, value) -> None:
    if op == "ping":
        assert isinstance(value, int) and 0 <= value <= 0xFFFF
    elif op == "read4s":
        assert isinstance(value, int) and -(2**31) <= value < 2**31
    elif op in ("read1", "hw"):
        assert isinstance(value, int) and 0 <= value <= 0xFF
    elif op == "read_bytes":
        assert isinstance(value, bytes) and len(value) == 14
    elif op == "sync_read":
        assert isinstance(value, dict) and set(value) == {1, 2}
        assert all(-(2**31) <= v < 2**31 for v in value.values())
    else:
        assert value is None


DRIVER_OPS = {
    "ping": lambda d: d.ping(1),
    "read4s": lambda d: d.read(1, 132, 4),
    "read1": lambda d: d.read(1, 64, 1),
    "read_bytes": lambda d: d.read_bytes(1, 122, 14),
    "write4": lambda d: d.write(1, 112, 4, 100),
    "write1": lambda d: d.write(2, 65, 1, 1),
    "torque_on": lambda d: d.torque(1, True),
    "torque_off": lambda d: d.torque(1, False),
    "sync_read": lambda d: d.sync_read(132, 4, [1, 2]),
    "reboot": lambda d: d.reboot(2),
    "hw": lambda d: d.hardware_error(1),
}


def fuzzed_driver(mode: str, specs) -> tuple[MangledReplies, DynamixelBus, str]:
    """A fresh emulated bus and DynamixelBus (no state carried between examples) on a
    `dxlsim://` port whose replies are rewritten by `specs` in turn."""
    dev = MangledReplies(make_bus(), Scripted(specs, mangle))
    name = f"fuzz-{uuid.uuid4().hex[:8]}"
    register_bus(name, dev)
    driver = DynamixelBus(
        f"dxlsim://{name}",
        baudrate=1_000_000,
        retries=1,
        on_alert=mode,
        clock=VirtualClock(),
        # the in-process port answers during write(): no FTDI latency (2 x 16 ms) to wait out
        timeout_margin_ms=-33.0,
        reboot_settle_s=0.0,
    )
    return dev, driver, name


@settings(FUZZ, max_examples=1200)
@given(
    op=st.sampled_from(sorted(DRIVER_OPS)),
    mode=st.sampled_from(["stop", "reboot"]),
    specs=st.lists(mangle_specs, min_size=1, max_size=6),
)
def test_driver_ends_in_value_or_classified_fault(op, mode, specs) -> None:
    dev, driver, name = fuzzed_driver(mode, specs)
    outcome = None
    try:
        with watchdog():
            value = DRIVER_OPS[op](driver)
    except CLASSIFIED as exc:
        outcome = exc
    finally:
        driver.close()
        unregister_bus(name)
    # not vacuous: every op asks for at least one status packet, so one went through the
    # mangler and the SDK
    assert dev.count >= 1
    if outcome is None:
        _check_value(op, value)
    else:
        assert str(outcome)  # a one-line reason for the operator


LIGHT_OPS = {
    "identify": lambda d: d.identify(),
    "on": lambda d: d.on(),
    "off": lambda d: d.off(),
    "intensity": lambda d: d.set_intensity(0.25),
    "status": lambda d: d.status(),
    "clear": lambda d: d.clear_fault(),
}

light_replies = st.one_of(
    st.binary(max_size=40),
    st.binary(max_size=40).map(lambda b: b + b"\n"),
    st.sampled_from(
        [b"OK\n", b"ERR X\n", b"STAT ON nan inf OK\n", b"STAT ON 1 2\n", b"IDN \xff\n", b"\n"]
    ),
)


def light_mangle(spec, reply: bytes) -> bytes:
    keep, replacement = spec
    return reply if keep else replacement


@settings(FUZZ, max_examples=300)
@given(
    op=st.sampled_from(sorted(LIGHT_OPS)),
    specs=st.lists(st.tuples(st.booleans(), light_replies), min_size=1, max_size=3),
)
def test_light_driver_ends_in_value_or_light_error(op, specs) -> None:
    dev = MangledReplies(EmulatedLight(VirtualClock(), name="fuzz"), Scripted(specs, light_mangle))
    name = f"fuzzlight-{uuid.uuid4().hex[:8]}"
    register_light(name, dev)
    drv = SerialLight(f"lightsim://{name}", timeout_s=0.005, retries=1)
    outcome = None
    try:
        with watchdog():
            value = LIGHT_OPS[op](drv)
    except LightError as exc:
        outcome = exc
    finally:
        drv.close()
        unregister_light(name)
    assert dev.count >= 1  # every command gets one reply line through the mangler
    if outcome is not None:
        assert str(outcome)
    elif op == "identify":
        assert isinstance(value, str)
    elif op == "status":
        assert math.isfinite(value.intensity) and math.isfinite(value.measured)
    else:
        assert value is None
