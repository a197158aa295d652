"""Dynamixel Protocol 2.0 packets: CRC, byte stuffing, encoding and a streaming decoder.

Reference: ROBOTIS e-Manual, "DYNAMIXEL Protocol 2.0" (packet layout, CRC, byte stuffing,
status packet error field). Layout of every packet:

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM ... | CRC_L CRC_H

LEN counts the bytes after the length field: the instruction, the (stuffed) parameters and
the two CRC bytes, so LEN = n_params + 3 (+1 for the error byte of a status packet, which the
manual counts among the parameters). The CRC is CRC-16 with polynomial 0x8005, initial value
0, no input/output reflection and no final XOR ("CRC-16/BUYPASS"), computed over every byte
from the first header byte up to the last parameter, *after* stuffing.

Byte stuffing keeps a header pattern out of the payload: wherever FF FF FD occurs in the
instruction + parameter bytes, an extra FD is inserted (FF FF FD -> FF FF FD FD) and LEN
grows accordingly; the receiver removes it again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "HEADER",
    "BROADCAST_ID",
    "MAX_ID",
    "INST_PING",
    "INST_READ",
    "INST_WRITE",
    "INST_REG_WRITE",
    "INST_ACTION",
    "INST_FACTORY_RESET",
    "INST_REBOOT",
    "INST_CLEAR",
    "INST_STATUS",
    "INST_SYNC_READ",
    "INST_SYNC_WRITE",
    "INST_FAST_SYNC_READ",
    "INST_BULK_READ",
    "INST_BULK_WRITE",
    "ERRNUM_RESULT_FAIL",
    "ERRNUM_INSTRUCTION",
    "ERRNUM_CRC",
    "ERRNUM_DATA_RANGE",
    "ERRNUM_DATA_LENGTH",
    "ERRNUM_DATA_LIMIT",
    "ERRNUM_ACCESS",
    "ERRBIT_ALERT",
    "ERROR_NAMES",
    "crc16",
    "stuff",
    "unstuff",
    "encode_packet",
    "encode_instruction",
    "encode_status",
    "Packet",
    "PacketDecoder",
]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC  # 252: highest unicast ID

# Instructions (e-Manual, Protocol 2.0, "Instruction")
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_FACTORY_RESET = 0x06
INST_REBOOT = 0x08
INST_CLEAR = 0x10
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_FAST_SYNC_READ = 0x8A
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93

# Error field of a status packet: bit 7 = hardware alert, bits 0-6 = one error number.
ERRNUM_RESULT_FAIL = 1
ERRNUM_INSTRUCTION = 2
ERRNUM_CRC = 3
ERRNUM_DATA_RANGE = 4
ERRNUM_DATA_LENGTH = 5
ERRNUM_DATA_LIMIT = 6
ERRNUM_ACCESS = 7
ERRBIT_ALERT = 0x80

ERROR_NAMES: dict[int, str] = {
    ERRNUM_RESULT_FAIL: "result fail",
    ERRNUM_INSTRUCTION: "instruction error",
    ERRNUM_CRC: "CRC error",
    ERRNUM_DATA_RANGE: "data range error",
    ERRNUM_DATA_LENGTH: "data length error",
    ERRNUM_DATA_LIMIT: "data limit error",
    ERRNUM_ACCESS: "access error",
}


def _make_crc_table() -> tuple[int, ...]:
    # MSB-first (unreflected) table for polynomial 0x8005.
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16, poly 0x8005, init 0, unreflected, no final XOR (Protocol 2.0 packet CRC)."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(payload: bytes | bytearray) -> bytes:
    """Insert FD after every FF FF FD in `payload` (instruction + params).

    The pattern is checked on the *original* bytes, preceded by the ID and length bytes that
    come before the instruction on the wire; those can never be FF FF, so looking within the
    payload only is exact (as in the ROBOTIS SDK, which also checks within the payload).
    """
    out = bytearray()
    for i, b in enumerate(payload):
        out.append(b)
        if b == 0xFD and i >= 2 and payload[i - 1] == 0xFF and payload[i - 2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(payload: bytes | bytearray) -> bytes:
    """Remove the FD inserted after each FF FF FD (inverse of `stuff`)."""
    out = bytearray()
    i = 0
    n = len(payload)
    while i < n:
        b = payload[i]
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            if i + 1 < n and payload[i + 1] == 0xFD:
                i += 1  # skip the stuffing byte
        i += 1
    return bytes(out)


def encode_packet(dxl_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """A complete wire packet (header, ID, length, stuffed instruction+params, CRC)."""
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    pkt = bytearray(HEADER)
    pkt += bytes([dxl_id & 0xFF, length & 0xFF, (length >> 8) & 0xFF])
    pkt += body
    crc = crc16(pkt)
    pkt += bytes([crc & 0xFF, crc >> 8])
    return bytes(pkt)


def encode_instruction(dxl_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """An instruction packet (host -> device)."""
    return encode_packet(dxl_id, instruction, params)


def encode_status(dxl_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A status packet (device -> host): INST 0x55, then the error byte, then the data."""
    return encode_packet(dxl_id, INST_STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass
class Packet:
    """One decoded packet. `params` are unstuffed. `crc_ok` False means the CRC did not match
    (a device answers that with a CRC error status)."""

    dxl_id: int
    instruction: int
    params: bytes = b""
    crc_ok: bool = True
    raw: bytes = field(default=b"", repr=False)

    @property
    def error(self) -> int:
        """Error byte of a status packet."""
        return self.params[0] if self.instruction == INST_STATUS and self.params else 0

    @property
    def data(self) -> bytes:
        """Data of a status packet (the params after the error byte)."""
        return self.params[1:] if self.instruction == INST_STATUS else self.params


class PacketDecoder:
    """Streaming decoder: feed arbitrary chunks of a byte stream, get whole packets.

    Garbage before a header is skipped (a device resynchronises on the next FF FF FD 00).
    A packet whose length field is implausible is dropped one byte at a time, like the SDK.
    """

    MAX_LENGTH = 1024

    def __init__(self) -> None:
        self._buf = bytearray()

    def clear(self) -> None:
        self._buf.clear()

    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray) -> list[Packet]:
        self._buf += data
        out: list[Packet] = []
        buf = self._buf
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and buf[-k:] == HEADER[:k]:
                        keep = k
                        break
                del buf[: len(buf) - keep]
                break
            if start:
                del buf[:start]
            if len(buf) < 7:
                break
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > self.MAX_LENGTH:
                del buf[0]
                continue
            total = 7 + length
            if len(buf) < total:
                break
            raw = bytes(buf[:total])
            del buf[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8))
            body = unstuff(raw[7:-2])
            out.append(
                Packet(dxl_id=raw[4], instruction=body[0], params=body[1:], crc_ok=crc_ok, raw=raw)
            )
        return out
