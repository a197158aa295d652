"""The light-controller protocol (docs/light-protocol.md): emulator and `SerialLight` driver,
over the in-process `lightsim://` URL and over a real pseudo-terminal."""

from __future__ import annotations

import uuid

import pytest
import serial

from acquisition.clock import VirtualClock
from acquisition.light import LightError, SerialLight
from acquisition.protocols import DeviceFault, LightSource
from simulator.dxl.transport import PtyTransport
from simulator.light import EmulatedLight, register_light, unregister_light


@pytest.fixture(params=["lightsim", "pty"])
def lamp(request):
    """(emulator, url, clock); the emulator drifts −1 %/h."""
    clock = VirtualClock()
    emu = EmulatedLight(clock, name="bench", drift_per_hour=-0.01)
    if request.param == "pty":
        t = PtyTransport(emu)
        yield emu, t.port_path, clock
        t.close()
    else:
        name = f"l-{uuid.uuid4().hex[:8]}"
        register_light(name, emu)
        yield emu, f"lightsim://{name}", clock
        unregister_light(name)


def test_raw_protocol_lines(lamp) -> None:
    emu, url, _ = lamp
    with serial.serial_for_url(url, timeout=1.0) as port:

        def ask(line: bytes) -> bytes:
            port.write(line)
            return port.read_until(b"\n")

        assert ask(b"IDN?\n") == b"IDN GONIO,LIGHTSIM,bench,1.0\n"
        assert ask(b"int 0.75\r\n") == b"OK\n"  # case-insensitive, CR tolerated
        assert ask(b"INT?\n") == b"INT 0.750\n"
        assert ask(b"STAT?\n") == b"STAT OFF 0.750 0.000 OK\n"
        assert ask(b"ON\n") == b"OK\n"
        assert ask(b"STAT?\n") == b"STAT ON 0.750 0.750 OK\n"
        assert ask(b"INT 1.5\n") == b"ERR RANGE\n"
        assert ask(b"INT abc\n") == b"ERR SYNTAX\n"
        assert ask(b"ON 3\n") == b"ERR SYNTAX\n"
        assert ask(b"FLASH\n") == b"ERR UNKNOWN FLASH\n"
        # two commands in one write: two replies, in order
        assert ask(b"OFF\nINT?\n") == b"OK\n"
        assert port.read_until(b"\n") == b"INT 0.750\n"


def test_driver_implements_light_source(lamp) -> None:
    emu, url, clock = lamp
    light = SerialLight(url, clock)
    try:
        assert isinstance(light, LightSource)
        assert light.identify() == "GONIO,LIGHTSIM,bench,1.0"
        light.set_intensity(0.6)
        light.on()
        st = light.status()
        assert (st.on, st.intensity, st.measured, st.fault) == (True, 0.6, 0.6, None)
        assert emu.is_on and emu.level == 0.6
        light.off()
        assert not light.status().on and not emu.is_on
    finally:
        light.close()


def test_drift_follows_virtual_time(lamp) -> None:
    emu, url, clock = lamp
    light = SerialLight(url, clock)
    light.set_intensity(0.8)
    light.on()
    clock.advance(2 * 3600.0)
    # measured = level·(1 + drift·hours) = 0.8·(1 − 0.02) = 0.784, sent with 3 decimals
    assert light.status().measured == pytest.approx(0.784, abs=5e-4)
    light.off()
    light.on()  # switching on again restarts the warm-up drift
    assert light.status().measured == pytest.approx(0.8, abs=5e-4)
    light.close()


def test_fail_to_turn_on_is_a_device_fault(lamp) -> None:
    emu, url, clock = lamp
    emu.fail_to_turn_on = True
    light = SerialLight(url, clock)
    with pytest.raises(LightError, match="LAMP_FAIL") as info:
        light.on()
    assert isinstance(info.value, DeviceFault)
    st = light.status()
    assert not st.on and st.fault == "LAMP_FAIL"
    emu.fail_to_turn_on = False
    light.clear_fault()
    light.on()
    assert light.status().fault is None and light.status().on
    light.close()


def test_driver_validates_and_reports_errors(lamp) -> None:
    _, url, clock = lamp
    light = SerialLight(url, clock)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        light.set_intensity(1.2)
    with pytest.raises(ValueError):
        light.set_intensity(float("nan"))
    with pytest.raises(LightError, match="ERR UNKNOWN"):
        light.query("SELF-DESTRUCT")
    light.close()


def test_settle_time_is_clock_time() -> None:
    clock = VirtualClock()
    emu = EmulatedLight(clock)
    register_light("settle", emu)
    light = SerialLight("lightsim://settle", clock, settle_s=2.5)
    light.on()
    light.set_intensity(0.5)
    assert clock.now() == pytest.approx(5.0)  # two settles, no wall time
    light.close()
    unregister_light("settle")


def test_no_reply_is_a_light_error() -> None:
    # a pty whose emulator never starts: nothing answers, the driver retries then gives up
    dead = PtyTransport(EmulatedLight(VirtualClock()), start=False)
    light = SerialLight(dead.port_path, VirtualClock(), timeout_s=0.05, retries=1)
    with pytest.raises(LightError, match="no reply to 'OFF' after 2 attempt"):
        light.off()
    light.close()
    dead.close()


def test_unexpected_reply_is_a_light_error() -> None:
    # pySerial's loopback echoes the command: a line, but not one the protocol allows
    light = SerialLight("loop://", VirtualClock(), timeout_s=0.05)
    with pytest.raises(LightError, match="expected OK"):
        light.off()
    light.close()


def test_monitor_noise_is_seeded() -> None:
    def readings(seed: int) -> list[float]:
        emu = EmulatedLight(VirtualClock(), monitor_noise=0.01, rng=seed)
        emu.command("ON")
        return [emu.measured() for _ in range(5)]

    assert readings(3) == readings(3)
    assert readings(3) != readings(4)


def test_unknown_light_name() -> None:
    with pytest.raises(LightError, match="no emulated light named"):
        SerialLight("lightsim://nobody", VirtualClock())
