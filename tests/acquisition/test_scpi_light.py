"""The SCPI light (`light.backend = "scpi"`, acquisition.light_scpi) through the real PyVISA:

* against a pyvisa-sim instrument definition kept here (tests/instruments/scpi_lamp.yaml), on a
  serial (ASRL) and a TCPIP resource;
* against the project's own SCPI lamp-supply emulator (simulator.scpi) over a pseudo-terminal,
  through pyvisa-py's serial session — the path a USB–serial supply takes;
* in the runner: a latched instrument error and a timeout each end in a safe stop (torque off,
  read from the emulated servos; the lamp off where the instrument still answers) with the
  reason recorded, and the run resumes once the cause is cleared.

Nothing is mocked: the only stand-ins are the emulated instruments themselves.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from acquisition.clock import VirtualClock
from acquisition.config import ConfigError, LightConfig, load_rig
from acquisition.device_config import ScpiConfig
from acquisition.light import LightError
from acquisition.light_scpi import ScpiLight, parse_scpi_error
from acquisition.protocols import LightSource
from simulator.dxl.transport import PtyTransport
from simulator.light import EmulatedLight
from simulator.scpi import IDN_MAKER, ScpiSupply
from tests.support.faults import assert_all_data, assert_safe, sim_session
from tests.support.paths import TESTS

HERE = TESTS
SIM_YAML = HERE / "instruments" / "scpi_lamp.yaml"


def sim_settings(**kw) -> ScpiConfig:
    """The pyvisa-sim supply: its output setter takes 0/1, its current 0..1 A."""
    base = {
        "visa_library": f"{SIM_YAML}@sim",
        "full_scale": 1.0,
        "output_on": "OUTP 1",
        "output_off": "OUTP 0",
        "timeout_s": 0.3,
    }
    return ScpiConfig(**{**base, **kw})


# -- PyVISA ↔ pyvisa-sim -----------------------------------------------------------------------
@pytest.mark.parametrize("resource", ["ASRL1::INSTR", "TCPIP::10.0.0.5::INSTR"])
def test_round_trips_against_pyvisa_sim(resource: str) -> None:
    light = ScpiLight(resource, sim_settings())
    try:
        assert isinstance(light, LightSource)
        assert light.identify() == "GONIO,PYVISA-SIM-LAMP,0001,1.0"
        assert light.status().on is False
        light.set_intensity(0.75)
        assert float(light.query("CURR?")) == 0.75  # the set point the instrument stored
        light.on()
        st = light.status()
        # The YAML's fixed monitor reading (0.742 A) over the 1 A full scale.
        assert st.on is True and st.intensity == 0.75 and st.measured == pytest.approx(0.742)
        light.off()
        assert light.status().on is False
    finally:
        light.close()


def test_pyvisa_sim_instrument_error_and_timeout() -> None:
    # 1.5 A full scale: level 1 asks CURR 1.5, beyond the instrument's 1 A — it queues an error,
    # which the check after the command reads (pyvisa-sim reports every refusal as -100).
    light = ScpiLight("ASRL1::INSTR", sim_settings(full_scale=1.5))
    try:
        with pytest.raises(LightError, match=r"'CURR 1\.500000' → SCPI error -100"):
            light.set_intensity(1.0)
    finally:
        light.close()
    # A query the instrument does not know gets no reply at all: a timeout, re-asked once.
    light = ScpiLight("ASRL1::INSTR", sim_settings(monitor_query="MEAS:VOLT?"))
    try:
        with pytest.raises(LightError, match=r"no reply to 'MEAS:VOLT\?' after 2 attempt"):
            light.status()
    finally:
        light.close()


# -- PyVISA + pyvisa-py ↔ the project's emulator over a pty -----------------------------------
@pytest.fixture
def supply():
    """(emulator, lamp, ASRL resource, clock): a 2 A supply whose lamp drifts −1 %/h."""
    clock = VirtualClock()
    lamp = EmulatedLight(clock, name="bench", drift_per_hour=-0.01)
    emu = ScpiSupply(lamp, name="bench", full_scale=2.0)
    t = PtyTransport(emu)
    yield emu, lamp, f"ASRL{t.port_path}::INSTR", clock
    t.close()
    assert t.error is None, t.error


def test_pty_emulator_round_trips(supply) -> None:
    emu, lamp, resource, clock = supply
    light = ScpiLight(resource, ScpiConfig(full_scale=2.0, timeout_s=0.5), clock)
    try:
        assert light.identify() == f"{IDN_MAKER},bench,1.0"
        light.set_intensity(0.5)
        assert lamp.level == pytest.approx(0.5) and not lamp.is_on  # 1 A of 2 A
        light.on()
        assert lamp.is_on
        st = light.status()
        assert st.on and st.measured == pytest.approx(0.5, abs=1e-6)  # 6 decimals of amperes
        # The monitor follows the lamp: one hour on at −1 %/h reads 1 % low (the emulator's
        # drift law, docs/light-protocol.md), to the reply's 1e-6 A resolution.
        clock.sleep(3600.0)
        assert light.status().measured == pytest.approx(0.5 * 0.99, abs=1e-6)
        # Long forms and optional nodes are the same commands (SCPI-99 header rules).
        light.command("SOURce:CURRent:LEVel:IMMediate:AMPLitude 1.5")
        assert float(light.query(":MEASure:CURRent?")) == pytest.approx(1.5 * 0.99, abs=1e-6)
        light.off()
        assert not lamp.is_on and light.status().measured == 0.0
        assert parse_scpi_error(light.query("SYST:ERR?")) == (0, "No error")
    finally:
        light.close()


def test_pty_emulator_errors_and_timeout(supply) -> None:
    emu, lamp, resource, clock = supply
    light = ScpiLight(resource, ScpiConfig(full_scale=2.0, timeout_s=0.3), clock)
    try:
        with pytest.raises(LightError, match=r'CURR 2\.5.*-222,"Data out of range"'):
            light.command("CURR 2.5")
        with pytest.raises(LightError, match=r"-113"):
            light.command("FLASH")
        light.on()
        emu.trip("overtemperature")  # latched: the output drops and stays off
        with pytest.raises(LightError, match=r"-300.*overtemperature"):
            light.status()
        with pytest.raises(LightError, match=r"-221.*protection tripped"):
            light.on()
        assert not lamp.is_on
        light.command("OUTP:PROT:CLE")
        light.on()
        assert lamp.is_on
        emu.mute = True  # a hung instrument: nothing answers
        with pytest.raises(LightError, match=r"no reply to 'OUTP\?' after 2 attempt"):
            light.status()
        emu.mute = False
        assert light.status().on is True  # answering again, the dialogue in step
    finally:
        light.close()


# -- rig file -------------------------------------------------------------------------------------
def test_rig_file_light_backends(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown light backend 'visa'; known: gonio-ascii, scpi"):
        LightConfig(backend="visa", url="/dev/ttyUSB1")
    with pytest.raises(ValueError, match=r'backend "scpi" needs url = a VISA resource'):
        LightConfig(backend="scpi", url="manual", scpi={"full_scale": 1.0})
    text = (HERE.parent / "configs" / "rigs" / "lab-example.toml").read_text()
    for old, new in (
        (
            'url = "/dev/serial/by-id/usb-gonio_light_controller-if00"',
            'backend = "scpi"\nurl = "ASRL1::INSTR"',
        ),
        (
            "# -- the camera:",
            '[light.scpi]\nfull_scale = 1.0\nvisa_library = "lamp.yaml@sim"\n\n# -- the camera:',
        ),
    ):
        assert old in text, old
        text = text.replace(old, new, 1)
    rig_text = text
    rig = tmp_path / "rig.toml"
    rig.write_text(rig_text)
    with pytest.raises(ConfigError, match=r"light.scpi.visa_library: no such file .*lamp.yaml"):
        load_rig(rig)
    (tmp_path / "lamp.yaml").write_text(SIM_YAML.read_text())
    cfg = load_rig(rig)  # the definition travels with the rig file
    assert cfg.light.scpi.visa_library == f"{tmp_path / 'lamp.yaml'}@sim"


# -- in the runner: safe stop, reason recorded, resume -------------------------------------------
def _scpi_session_config(s, resource: str, **kw):
    light = s.config.light.model_copy(
        update={"backend": "scpi", "url": resource, "scpi": ScpiConfig(**kw)}
    )
    return s.config.model_copy(update={"light": light})


def test_latched_instrument_error_stops_safely_then_resumes(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        emu = ScpiSupply(s.world.light, name="sim", full_scale=2.0)
        t = PtyTransport(emu)
        try:
            s.config = _scpi_session_config(
                s, f"ASRL{t.port_path}::INSTR", full_scale=2.0, timeout_s=0.5
            )
            out = s.run(on_capture=lambda n: emu.trip("overtemperature") if n == 3 else None)
            assert not out.complete and out.total_done == 3
            assert "-300" in out.reason and "overtemperature" in out.reason, out.reason
            assert_safe(s.world, s.config)  # lamp off, torque off, from the emulators
            assert ("stop", out.reason) in s.events()
            assert not [m for k, m in s.events() if k == "safe-stop"]  # every step succeeded
            # Resuming while the trip is still latched stops again before any capture...
            again = s.run()
            assert not again.complete and "-221" in again.reason and again.captured == 0
            emu.clear_trip()  # ...the cause removed, the run completes with all its data
            s.resume_and_check()
        finally:
            t.close()


def test_instrument_timeout_stops_safely_then_resumes(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        emu = ScpiSupply(s.world.light, name="sim", full_scale=2.0)
        t = PtyTransport(emu)
        try:
            s.config = _scpi_session_config(
                s, f"ASRL{t.port_path}::INSTR", full_scale=2.0, timeout_s=0.3
            )
            out = s.run(on_capture=lambda n: setattr(emu, "mute", True) if n == 4 else None)
            assert not out.complete and out.total_done == 4
            assert "no reply" in out.reason, out.reason
            events = s.events()
            assert ("stop", out.reason) in events
            # A hung instrument cannot be switched off over the bus: the safe stop says so
            # (and still parks and removes torque); the lamp is on until someone acts.
            assert any(k == "safe-stop" and m.startswith("light off failed") for k, m in events)
            for a in s.config.axes:
                assert s.world.bus.servo(a.id).register("torque_enable") == 0, a.role
            emu.mute = False
            s.resume_and_check()
        finally:
            t.close()


def test_pyvisa_sim_faults_stop_the_run_safely(tmp_path: Path) -> None:
    with sim_session(tmp_path) as s:
        base = {k: v for k, v in sim_settings().model_dump().items() if v is not None}
        s.config = _scpi_session_config(s, "ASRL1::INSTR", **{**base, "full_scale": 1.5})
        out = s.run()  # the level 1.0 of sim.toml asks 1.5 A of a 1 A instrument
        assert not out.complete and out.captured == 0 and "SCPI error -100" in out.reason
        assert ("stop", out.reason) in s.events()
        s.config = _scpi_session_config(s, "ASRL1::INSTR", **{**base, "monitor_query": "X?"})
        out = s.run()  # the monitor is read at the first pose: no reply
        assert not out.complete and out.captured == 0 and "no reply to 'X?'" in out.reason
        assert ("stop", out.reason) in s.events()
        for a in s.config.axes:
            assert s.world.bus.servo(a.id).register("torque_enable") == 0, a.role
        s.config = _scpi_session_config(s, "ASRL1::INSTR", **base)
        out = s.run()
        assert out.complete, out.reason
        assert_all_data(s.store)
