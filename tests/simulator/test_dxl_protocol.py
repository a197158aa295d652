"""Protocol 2.0 packet layer of the emulator, checked against independent ground truth:
the ROBOTIS e-Manual's example packets, the CRC-16/BUYPASS check value, and the packet code
of the real `dynamixel_sdk` (its own CRC table, stuffing and packet assembly)."""

from __future__ import annotations

import numpy as np
import pytest
from dynamixel_sdk import PacketHandler
from hypothesis import given
from hypothesis import strategies as st

from acquisition.clock import VirtualClock
from simulator.dxl import protocol as P
from simulator.dxl.bus import EmulatedBus
from simulator.dxl.faults import FaultInjector, ReplyFaults

SDK = PacketHandler(2.0)


class _CapturePort:
    """Just enough of a PortHandler for the SDK's txPacket: records what it would send."""

    def __init__(self) -> None:
        self.is_using = False
        self.sent = b""

    def clearPort(self) -> None:  # SDK name
        pass

    def writePort(self, packet) -> int:  # SDK name
        self.sent = bytes(packet)
        return len(packet)


def _raw(dxl_id: int, inst: int, params: bytes) -> list[int]:
    pkt = [0] * (len(params) + 10)
    pkt[4] = dxl_id
    length = len(params) + 3
    pkt[5], pkt[6] = length & 0xFF, length >> 8
    pkt[7] = inst
    pkt[8 : 8 + len(params)] = list(params)
    return pkt


def sdk_packet(dxl_id: int, inst: int, params: bytes) -> bytes:
    """The exact bytes the real SDK's txPacket puts on the wire for this instruction."""
    port = _CapturePort()
    SDK.txPacket(port, _raw(dxl_id, inst, params))
    return port.sent


def sdk_stuffed_packet(dxl_id: int, inst: int, params: bytes) -> bytes:
    """The packet the SDK's own addStuffing + updateCRC produce (header, stuffing, CRC)."""
    pkt = SDK.addStuffing(_raw(dxl_id, inst, params))
    pkt[0:4] = [0xFF, 0xFF, 0xFD, 0x00]
    n = (pkt[5] | pkt[6] << 8) + 7
    crc = SDK.updateCRC(0, pkt, n - 2)
    pkt[n - 2 : n] = [crc & 0xFF, crc >> 8]
    return bytes(pkt[:n])


def test_crc_check_value() -> None:
    # CRC-16/BUYPASS (poly 0x8005, init 0, unreflected, xorout 0): check("123456789") = 0xFEE8
    # (Greg Cook's CRC catalogue) — the algorithm the Protocol 2.0 manual specifies.
    assert P.crc16(b"123456789") == 0xFEE8


def test_manual_example_packets() -> None:
    # e-Manual, Protocol 2.0, "Ping" example: instruction to ID 1, and a status packet from a
    # device with model number 1030 (0x0406) and firmware 0x26.
    assert P.encode_instruction(1, P.INST_PING) == bytes.fromhex("FFFFFD0001030001194E")
    assert P.encode_status(1, 0, bytes([0x06, 0x04, 0x26])) == bytes.fromhex(
        "FFFFFD00010700550006042665 5D".replace(" ", "")
    )


@given(st.binary(min_size=0, max_size=300))
def test_crc_matches_sdk(data: bytes) -> None:
    assert P.crc16(data) == SDK.updateCRC(0, list(data), len(data))


# Parameters biased toward the stuffing pattern FF FF FD.
_stuffy = st.lists(
    st.sampled_from([0xFF, 0xFD, 0x00, 0x55]) | st.integers(0, 255), max_size=60
).map(bytes)


@given(st.integers(0, 252), st.sampled_from([P.INST_WRITE, P.INST_READ, P.INST_REG_WRITE]), _stuffy)
def test_encoding_matches_sdk_bytes(dxl_id: int, inst: int, params: bytes) -> None:
    ours = P.encode_instruction(dxl_id, inst, params)
    assert ours == sdk_stuffed_packet(dxl_id, inst, params)
    if b"\xff\xff\xfd" not in params:
        # Byte-identical to what txPacket sends. (When stuffing changes the length, the
        # Python SDK 4.1's addStuffing rebinds its local list and txPacket sends the packet
        # UNstuffed; the emulator decodes such packets like a device would.)
        assert ours == sdk_packet(dxl_id, inst, params)


@given(_stuffy)
def test_stuffing_round_trip_and_no_header_inside(payload: bytes) -> None:
    stuffed = P.stuff(payload)
    assert P.unstuff(stuffed) == payload
    # after stuffing, every FF FF FD inside the payload is followed by the FD marker
    for i in range(len(stuffed) - 2):
        if stuffed[i : i + 3] == b"\xff\xff\xfd":
            assert i + 3 < len(stuffed) and stuffed[i + 3] == 0xFD


def test_stuffing_example() -> None:
    # e-Manual: "FF FF FD" in the payload is sent as "FF FF FD FD"; LEN counts the extra byte
    pkt = P.encode_instruction(1, P.INST_WRITE, bytes([0x74, 0x00, 0xFF, 0xFF, 0xFD, 0x00]))
    assert pkt[7:15] == bytes([0x03, 0x74, 0x00, 0xFF, 0xFF, 0xFD, 0xFD, 0x00])
    assert pkt[5] | pkt[6] << 8 == 1 + 6 + 1 + 2  # inst + params + stuffing + CRC


def test_sdk_decodes_our_stuffed_status() -> None:
    # a status whose data contains FF FF FD: the SDK's removeStuffing must recover it
    data = bytes([0xFF, 0xFF, 0xFD, 0x7F])
    pkt = list(P.encode_status(3, 0, data))
    out = SDK.removeStuffing(pkt)
    assert bytes(out[9:13]) == data


@given(_stuffy, st.integers(1, 7))
def test_decoder_handles_any_chunking_and_garbage(params: bytes, chunk: int) -> None:
    stream = b"\x00\xff\x12" + P.encode_instruction(7, P.INST_WRITE, params) + b"\xfd"
    stream += P.encode_instruction(8, P.INST_PING)
    dec = P.PacketDecoder()
    got = []
    for k in range(0, len(stream), chunk):
        got += dec.feed(stream[k : k + chunk])
    assert [(p.dxl_id, p.instruction, p.params, p.crc_ok) for p in got] == [
        (7, P.INST_WRITE, params, True),
        (8, P.INST_PING, b"", True),
    ]


def test_decoder_flags_bad_crc() -> None:
    pkt = bytearray(P.encode_instruction(1, P.INST_PING))
    pkt[-1] ^= 0xFF
    (p,) = P.PacketDecoder().feed(bytes(pkt))
    assert not p.crc_ok


def test_bus_answers_corrupt_instruction_with_crc_error() -> None:
    bus = EmulatedBus(VirtualClock())
    bus.add_servo(1)
    pkt = bytearray(P.encode_instruction(1, P.INST_PING))
    pkt[-2] ^= 0x01
    (reply,) = P.PacketDecoder().feed(bus.feed(bytes(pkt)))
    assert reply.instruction == P.INST_STATUS and reply.error == P.ERRNUM_CRC


def test_fault_injector_rates_follow_probabilities() -> None:
    # 4000 draws at p = 0.2 each: binomial sd = sqrt(4000·0.2·0.8) ≈ 25, so ±5 sd = ±126.
    inj = FaultInjector(np.random.default_rng(1))
    inj.configure(ReplyFaults(drop_p=0.2, bad_crc_p=0.2))
    pkt = P.encode_status(1, 0, b"\x01\x02")
    results = [inj.apply(1, pkt) for _ in range(4000)]
    assert abs(sum(r is None for r in results) - 800) < 126
    assert abs(sum(r is not None and r.data != pkt for r in results) - 800) < 126


def test_fault_injector_is_reproducible() -> None:
    def run(seed: int) -> list:
        inj = FaultInjector(seed)
        inj.configure(ReplyFaults(drop_p=0.3, truncate_p=0.3))
        return [inj.apply(2, b"\xff\xff\xfd\x00\x02\x04\x00\x55\x00\xaa\xbb") for _ in range(50)]

    assert run(5) == run(5)
    assert run(5) != run(6)


def test_fault_injector_rejects_bad_probability() -> None:
    with pytest.raises(ValueError, match="drop_p"):
        ReplyFaults(drop_p=1.5)


def _ping_reply(bus: EmulatedBus, dxl_id: int) -> list[P.Packet]:
    return P.PacketDecoder().feed(bus.feed(P.encode_instruction(dxl_id, P.INST_PING)))


def test_reply_faults_per_servo() -> None:
    bus = EmulatedBus(VirtualClock())
    bus.add_servo(1)
    bus.add_servo(2, "XL430-W250")
    bus.set_reply_faults(ReplyFaults(drop_p=1.0), servo_id=2)
    assert _ping_reply(bus, 2) == []
    (reply,) = _ping_reply(bus, 1)
    assert reply.dxl_id == 1 and reply.data == bytes([0xFC, 0x03, 48])  # 1020 = 0x03FC


def test_alert_after_n_packets() -> None:
    bus = EmulatedBus(VirtualClock())
    bus.add_servo(4)
    bus.inject_alert(4, "overload", after_packets=3)
    errors = [_ping_reply(bus, 4)[0].error for _ in range(4)]
    assert errors == [0, 0, P.ERRBIT_ALERT, P.ERRBIT_ALERT]


def test_broadcast_write_executes_without_reply() -> None:
    bus = EmulatedBus(VirtualClock())
    for i in (1, 2):
        bus.add_servo(i)
    out = bus.feed(P.encode_instruction(P.BROADCAST_ID, P.INST_WRITE, bytes([65, 0, 1])))
    assert out == b""
    assert [bus.servo(i).register("led") for i in (1, 2)] == [1, 1]


def test_status_return_level_zero_silences_all_but_ping() -> None:
    bus = EmulatedBus(VirtualClock())
    bus.add_servo(1)
    wire = bus.feed(P.encode_instruction(1, P.INST_WRITE, bytes([68, 0, 0])))
    assert wire == b""  # level 0 already applies to the reply of the write that set it
    assert bus.feed(P.encode_instruction(1, P.INST_READ, bytes([7, 0, 1, 0]))) == b""
    assert len(_ping_reply(bus, 1)) == 1
