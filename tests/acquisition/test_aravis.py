"""The Aravis camera backend (acquisition.cameras_aravis) through the real Aravis 0.8 library and
PyGObject, against the real `arv-fake-gv-camera-0.8` started here on 127.0.0.1 — discovered,
configured and streamed over GigE Vision (GVCP/GVSP on UDP) on the loopback interface:

* discovery ("first" and by GenICam ID), configuration (ROI, pixel format, gain, software
  trigger), the read-back exposure, the device's own description;
* frames decoded by calibration's decoder at the sizes and exposures set, every pixel equal to
  the fake camera's pattern computed independently (tests/support/aravis.expected_mono);
* a lost-packet ratio: every stored frame complete; with no retries left, a DeviceFault;
* on the pretend lab (servos and a SCPI lamp supply on ptys, wall clock) with this camera:
  `gonio rig check`, an acquisition under packet loss, and the camera killed mid-run → safe
  stop (torque off and lamp off, read from the emulators) → resume after it is restarted.

The fake camera's frames are a synthetic ramp, not a render of a sample: what is asserted is
the data path (complete frames, sizes, exposures, checksums, safe stop, resume).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from acquisition.protocols import DeviceFault
from acquisition.store import RunStore
from calibration.decode import decode_frame
from tests.support.aravis import FakeCamera, expected_mono, fake_serial, require_aravis
from tests.support.pretend_lab import DEMO_SCENE, LAB_RIG, REPO, pretend_lab

# heavy and waits: scheduled first, beside a repeat pool (tests/conftest.py).
pytestmark = [pytest.mark.timeout(900), pytest.mark.heavy(62), pytest.mark.waits]


@pytest.fixture(autouse=True)
def _aravis_installed() -> None:
    require_aravis()


def _camera(device: str, pixel_format: str = "Mono16", size=(64, 48), **kw):
    from acquisition.cameras_aravis import AravisCamera, AravisOptions
    from acquisition.device_config import AravisConfig

    settings = AravisConfig(device=device, pixel_format=pixel_format, **kw)
    return AravisCamera(AravisOptions(settings, size, timeout_s=2.0))


def _decode(frame, tmp_path: Path, name: str):
    path = tmp_path / f"{name}{frame.suffix}"
    path.write_bytes(frame.data)
    return decode_frame(path)


def _assert_pattern(d, pixel_format: str, gain: int) -> None:
    h, w = d.dn.shape
    exp = expected_mono(pixel_format, w, h, d.metadata["frame_id"], gain, d.exposure_s * 1e6)
    bad = np.argwhere(d.dn.astype(np.int64) != exp)
    assert bad.size == 0, f"{len(bad)} pixels differ from the fake camera's pattern, e.g. {bad[0]}"


def test_discovery_configuration_and_frames(tmp_path: Path) -> None:
    with FakeCamera(fake_serial()) as fake:
        with pytest.raises(DeviceFault, match=r"'Aravis-Fake-NOPE' not found; Aravis sees: .*"):
            _camera("Aravis-Fake-NOPE")
        cam = _camera("first", gain=2.0)
        try:  # "first": whichever Aravis lists first; here ours is the only fake on 127.0.0.1
            assert cam.device_id.startswith("Aravis-Fake-")
        finally:
            cam.close()
        cam = _camera(fake.device_id, "Mono16", (64, 48), gain=2.0)
        try:
            info = cam.describe()
            assert info["model"] == "Aravis Fake" and info["serial"] == fake.serial
            assert info["sensor_px"] == [2048, 2048] and info["resolution"] == [64, 48]
            assert info["pixel_format"] == "Mono16" and info["bit_depth"] == 16
            assert info["gain"] == 2.0 and info["protocol"] == "GigE Vision"
            for exposure_s in (0.01, 0.1):
                frame = cam.capture(exposure_s)
                d = _decode(frame, tmp_path, f"m16-{exposure_s}")
                assert d.channels == "Y" and d.dn.shape == (48, 64) and frame.suffix == ".tif"
                assert d.exposure_s == exposure_s  # read back from ExposureTimeAbs (whole µs)
                assert d.metadata["device_id"] == fake.device_id and d.metadata["gain"] == 2.0
                _assert_pattern(d, "Mono16", 2)
            assert cam.describe()["exposure_s"] == 0.1
        finally:
            cam.close()
        cam = _camera(fake.device_id, "Mono8", (40, 30), gain=0.0)
        try:
            d = _decode(cam.capture(0.01), tmp_path, "m8")
            assert d.dn.shape == (30, 40) and d.white_level == 255
            _assert_pattern(d, "Mono8", 0)
        finally:
            cam.close()
        cam = _camera(fake.device_id, "BayerRG8", (64, 48), gain=0.0)
        try:
            frame = cam.capture(0.01)
            d = _decode(frame, tmp_path, "bayer")
            assert frame.suffix == ".dng" and d.channels == "CFA" and d.cfa_pattern == "RGGB"
            assert d.dn.shape == (48, 64) and d.exposure_s == 0.01
            # Bayer pixels are a colour map of the same ramp: along an anti-diagonal (x + y
            # constant) the ramp index is constant, so sites of one colour there are equal.
            dn = d.dn
            for c in (0, 1):
                for dy in (0, 1):
                    sites = dn[dy::2, c::2]
                    ys, xs = np.mgrid[0 : sites.shape[0], 0 : sites.shape[1]]
                    diag = 2 * (ys + xs) + dy + c
                    for k in np.unique(diag)[:20]:
                        assert np.ptp(sites[diag == k]) == 0
        finally:
            cam.close()


def test_lost_packets_every_frame_complete_then_bounded_retries(tmp_path: Path) -> None:
    # 3 % of GVSP packets dropped and never resent (the fake camera ignores resend requests).
    # A 64 × 64 Mono16 frame is 8 packets (leader, 6 × 1400 B, trailer): complete with
    # p = 0.97⁸ ≈ 0.78. With 8 retries a capture fails with (1 − p)⁹ ≈ 1e-6; 30 captures with
    # no loss at all has probability p³⁰ ≈ 6e-4 — so the retry path is surely exercised.
    with FakeCamera(fake_serial(), lost_per_thousand=30) as fake:
        cam = _camera(fake.device_id, "Mono16", (64, 64), gain=0.0, retries=8)
        try:
            for k in range(30):
                d = _decode(cam.capture(0.01), tmp_path, f"lost{k}")
                assert d.dn.shape == (64, 64)
                _assert_pattern(d, "Mono16", 0)  # complete: every pixel is the camera's
            assert cam.frames == 30 and cam.failed_attempts > 0, cam.describe()
            print(f"30 complete frames, {cam.failed_attempts} incomplete buffers retried")
        finally:
            cam.close()
    # 30 % loss: p = 0.7⁸ ≈ 0.06; with no retry a capture fails with 0.94, so 20 captures pass
    # with probability 0.06²⁰ ≈ 0: the bounded retry ends in a DeviceFault naming the buffers.
    with FakeCamera(fake_serial(), lost_per_thousand=300) as fake:
        cam = _camera(fake.device_id, "Mono16", (64, 64), gain=0.0, retries=0)
        try:
            with pytest.raises(DeviceFault, match=r"no complete frame in 1 attempt\(s\)"):
                for _ in range(20):
                    cam.capture(0.01)
        finally:
            cam.close()


# -- the pretend lab with this camera and a SCPI lamp supply -----------------------------------
PLAN = """name = "aravis-pretend-lab"
type = "isotropic"
theta_i_deg = [30.0, 50.0]
theta_o_deg = [10.0, 40.0, 60.0]
delta_phi_deg = [180.0]
exposures_s = [0.01, 0.1]
"""
N_FRAMES = 2 * 3 * 2


def _rig_text(lab: Path, device_id: str, **camera: object) -> str:
    """lab-example.toml with the bus and a SCPI supply on the lab's ptys and this camera."""
    text = LAB_RIG.read_text()
    cam = {"bit_depth": 16, "white_level_dn": 65535.0, **camera}
    for old, new in (
        (
            'url = "/dev/serial/by-id/usb-FTDI_USB__-__Serial_Converter_FT4TJ8ZQ-if00-port0"',
            f'url = "{lab / "dxl"}"',
        ),
        (
            'url = "/dev/serial/by-id/usb-gonio_light_controller-if00"',
            f'backend = "scpi"\nurl = "ASRL{lab / "scpi"}::INSTR"',
        ),
        ("# -- the camera:", "[light.scpi]\nfull_scale = 2.0\n\n# -- the camera:"),
        ('backend = "folder"', 'backend = "aravis"'),
        ("resolution = [256, 256]", "resolution = [64, 64]"),
        ('color_filter = "RGGB"', 'color_filter = "mono"'),
        ("bit_depth = 12", f"bit_depth = {cam['bit_depth']}"),
        ("black_level_dn = 240.0", "black_level_dn = 0.0"),
        ("white_level_dn = 4000.0", f"white_level_dn = {cam['white_level_dn']}"),
        (
            "# -- the sample",
            f'[camera.aravis]\ndevice = "{device_id}"\npixel_format = "Mono16"\ngain = 0.0\n'
            "retries = 8\n\n# -- the sample",
        ),
    ):
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def _gonio(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS="1000")  # one table row per line: no wrapped words
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args],
        cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env,
    )  # fmt: skip


def _truth(lab: Path) -> dict:
    from simulator.truth_channel import TRUTH_SOCKET, TruthClient

    return TruthClient(lab / TRUTH_SOCKET).state()


def _assert_frames(run: Path, n: int) -> int:
    """Complete, each (pose, bracket) once, checksums verify; every frame decodes at 64 × 64
    with its manifest exposure and equals the camera's pattern. Returns the retries taken."""
    store = RunStore.open(run)
    try:
        assert store.complete
        caps = list(store.captures())
        keys = {(c.pose_index, c.bracket_index) for c in caps}
        assert len(keys) == len(caps) == n and store.verify() == []
        retries = 0
        for c in caps:
            d = decode_frame(run / c.frame_path)
            assert d.dn.shape == (64, 64) and d.exposure_s == c.exposure_s
            _assert_pattern(d, "Mono16", 0)
            retries += int(d.metadata["retries"])
        on_disk = {f"frames/{p.name}" for p in (run / "frames").iterdir()}
        assert on_disk == {c.frame_path for c in caps}
        return retries
    finally:
        store.close()


def test_pretend_lab_rig_check_and_acquisition_under_packet_loss(tmp_path: Path) -> None:
    from simulator.scpi import IDN_MAKER

    lab, run = tmp_path / "lab", tmp_path / "run"
    with FakeCamera(fake_serial(), lost_per_thousand=30) as fake:
        rig, plan = tmp_path / "rig.toml", tmp_path / "plan.toml"
        rig.write_text(_rig_text(lab, fake.device_id))
        plan.write_text(PLAN)
        with pretend_lab(rig, lab, DEMO_SCENE):
            check = _gonio("rig", "check", "--rig", str(rig), "--exposure-s", "0.01")
            assert check.returncode == 0, check.stdout + check.stderr
            for words in ("Aravis Fake", "64 × 64 px", "DN min/mean/max", IDN_MAKER, "scpi at"):
                assert words in check.stdout, (words, check.stdout)
            assert "warning" not in check.stdout
            # The device contradicting the rig file is said (a 12-bit rig file, Mono16 frames).
            rig12 = tmp_path / "rig12.toml"
            rig12.write_text(_rig_text(lab, fake.device_id, bit_depth=12, white_level_dn=4095.0))
            check = _gonio("rig", "check", "--rig", str(rig12), "--exposure-s", "0.01")
            assert "pixel format has 16 bits, the rig file bit_depth is 12" in check.stdout
            res = _gonio("acquire", "--rig", str(rig), "--plan", str(plan), "--out", str(run),
                         "--no-progress")  # fmt: skip
            assert res.returncode == 0, res.stdout + res.stderr
            state = _truth(lab)
        assert state["light_level"] == 0.0 and not any(state["torque_enable"].values())
    retries = _assert_frames(run, N_FRAMES)
    device = tomllib.loads((run / "run.toml").read_text())["camera_device"]
    assert device["model"] == "Aravis Fake" and device["device_id"] == fake.device_id
    assert device["resolution"] == [64, 64] and device["pixel_format"] == "Mono16"
    print(f"pretend lab + Aravis under 3 % packet loss: {N_FRAMES} frames, {retries} retries")


def test_camera_killed_mid_run_stops_safely_then_resumes(tmp_path: Path) -> None:
    lab, run = tmp_path / "lab", tmp_path / "run"
    serial = fake_serial()
    fake = FakeCamera(serial).start()
    rig, plan = tmp_path / "rig.toml", tmp_path / "plan.toml"
    rig.write_text(_rig_text(lab, fake.device_id))
    plan.write_text(PLAN)
    cmd = [sys.executable, "-m", "gonio.cli", "acquire", "--rig", str(rig), "--plan", str(plan),
           "--out", str(run), "--no-progress"]  # fmt: skip
    try:
        with pretend_lab(rig, lab, DEMO_SCENE):
            proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            deadline = time.monotonic() + 300
            while _done(run) < 4 and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.02)
            assert proc.poll() is None, "the run ended before the camera could be killed"
            fake.kill()
            out, err = proc.communicate(timeout=300)
            assert proc.returncode != 0, out
            # Safe: the arms hold no torque and the lamp is off — the emulators' own state.
            state = _truth(lab)
            assert state["light_level"] == 0.0 and not any(state["torque_enable"].values())
            store = RunStore.open(run)
            try:
                assert not store.complete
                stops = [m for _, k, m in store.events() if k == "stop"]
                assert stops and fake.device_id in stops[-1], stops
                assert not [m for _, k, m in store.events() if k == "safe-stop"]
                killed_at = store.count("done")
            finally:
                store.close()
            assert 4 <= killed_at < N_FRAMES
            fake = FakeCamera(serial).start()  # the camera is back: the same command resumes
            res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
            assert res.returncode == 0, res.stdout + res.stderr
    finally:
        fake.kill()
    _assert_frames(run, N_FRAMES)
    print(f"camera killed after {killed_at} frames; fault: {stops[-1]}")


def _done(run: Path) -> int:
    import sqlite3

    db = run / "manifest.sqlite"
    if not db.exists():
        return 0
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            return conn.execute("SELECT COUNT(*) FROM captures WHERE status='done'").fetchone()[0]
        finally:
            conn.close()
    except sqlite3.Error:
        return 0


def test_unknown_backend_is_one_line(tmp_path: Path) -> None:
    text = LAB_RIG.read_text().replace('backend = "folder"', 'backend = "genicam"')
    rig = tmp_path / "rig.toml"
    rig.write_text(text)
    res = _gonio("rig", "check", "--rig", str(rig))
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "unknown camera backend 'genicam'" in lines[0], res.stderr
    assert "aravis" in lines[0]
