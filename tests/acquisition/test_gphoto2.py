"""The gphoto2 camera backend (acquisition.cameras_gphoto2) with the real libgphoto2 that the
python-gphoto2 wheel bundles.

What the real library does here: camera and port selection, listing, download and deletion, all
through its "Directory Browse" driver on a folder (a card, as far as libgphoto2 is concerned), and
the one-line faults when a model or a capture is not to be had.

What cannot exist on this machine — a camera with a shutter and a settings tree — is the
`RecordedCamera` stand-in (tests/support/gphoto2_recorded.py): a recorded `--list-all-config` tree
in ptp2's Nikon naming, whose "shutter" writes files onto the Directory Browse card. Every setting
path of the driver (ISO, aperture, RAW / RAW+JPEG, nearest shutter speed, bulb) runs against it;
downloads and deletions still go through the real driver.
"""

from __future__ import annotations

from pathlib import Path

import gphoto2 as gp  # a dev dependency (make setup installs gonio[dev]): missing = failure
import pytest

from acquisition.cameras_gphoto2 import (
    Gphoto2Camera,
    open_gphoto2,
    parse_shutter,
    pick_raw_choice,
)
from acquisition.clock import VirtualClock
from acquisition.device_config import Gphoto2Config
from acquisition.protocols import DeviceFault
from calibration.decode import decode_frame
from tests.support.gphoto2_recorded import RecordedCamera
from tests.support.paths import TESTS

RECORDED = TESTS / "instruments" / "gphoto2_nikon_config.txt"


def _card(tmp_path: Path) -> tuple[Path, object]:
    folder = tmp_path / "card"
    (folder / "DCIM" / "100D750").mkdir(parents=True)
    cam = open_gphoto2(Gphoto2Config(camera="Directory Browse", port=f"disk:{folder}"))
    return folder, cam


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.is_file())


def test_directory_browse_selection_listing_download_delete(tmp_path: Path) -> None:
    folder, cam = _card(tmp_path)
    try:
        (folder / "DCIM" / "100D750" / "DSC_0001.NEF").write_bytes(b"raw bytes" * 100)
        listing = cam.folder_list_files("/DCIM/100D750")
        names = [listing.get_name(i) for i in range(listing.count())]
        assert names == ["DSC_0001.NEF"]
        f = cam.file_get("/DCIM/100D750", "DSC_0001.NEF", gp.GP_FILE_TYPE_NORMAL)
        assert bytes(memoryview(f.get_data_and_size())) == b"raw bytes" * 100
        cam.file_delete("/DCIM/100D750", "DSC_0001.NEF")
        assert _files(folder) == []
        # The real driver has no shutter: the capture is a DeviceFault with libgphoto2's reason.
        driver = Gphoto2Camera(cam, Gphoto2Config())
        assert driver.describe()["model"] == "Directory Browse"
        with pytest.raises(DeviceFault, match=r"gphoto2 capture failed: \[-6\] Unsupported"):
            driver.capture(0.01)
        # ...and one that has no settings cannot take an ISO.
        with pytest.raises(DeviceFault, match="the camera has no settings to change"):
            Gphoto2Camera(cam, Gphoto2Config(iso="100"))
    finally:
        cam.exit()
    with pytest.raises(DeviceFault, match="libgphoto2 knows no camera model 'Nikon DSC D9999'"):
        open_gphoto2(Gphoto2Config(camera="Nikon DSC D9999", port=f"disk:{folder}"))


def test_shutter_strings_and_raw_choices() -> None:
    assert [parse_shutter(s) for s in ("1/250", "0.0002s", "30s", '1/3"', "2", "Bulb")] == [
        0.004, 0.0002, 30.0, 1 / 3, 2.0, -1.0,
    ]  # fmt: skip
    nikon = ["JPEG Basic", "JPEG Fine", "NEF (Raw)", "NEF+Basic", "NEF+Fine"]
    canon = ["Large Fine JPEG", "RAW + Large Fine JPEG", "RAW", "cRAW"]
    assert pick_raw_choice(nikon, "raw") == "NEF (Raw)"
    assert pick_raw_choice(nikon, "raw+jpeg") == "NEF+Basic"
    assert pick_raw_choice(canon, "raw") == "RAW"
    assert pick_raw_choice(canon, "raw+jpeg") == "RAW + Large Fine JPEG"
    assert pick_raw_choice(["JPEG Fine"], "raw") is None


def _recorded(tmp_path: Path) -> tuple[Path, RecordedCamera, VirtualClock]:
    folder, card = _card(tmp_path)
    clock = VirtualClock()
    return folder, RecordedCamera(card, folder, RECORDED.read_text(), clock), clock


def test_settings_raw_jpeg_download_delete_against_a_recorded_tree(tmp_path: Path) -> None:
    folder, cam, clock = _recorded(tmp_path)
    settings = Gphoto2Config(iso="100", aperture="8", image_format="raw+jpeg")
    driver = Gphoto2Camera(cam, settings, clock)
    try:
        # Set once at open, in the camera's own spellings.
        assert cam.log == [("iso", "100"), ("f-number", "f/8"), ("imagequality", "NEF+Basic")]
        info = driver.describe()
        assert info["model"] == "D750" and info["serial"] == "6021644"
        assert info["manufacturer"] == "Nikon Corporation" and info["image_format"] == "NEF+Basic"
        assert info["shutter_speeds_s"] == [0.0002, 30.0]
        frame = driver.capture(0.003)  # nearest in log space: 0.0031 s (not 0.0020 s)
        assert cam.log[-1] == ("shutterspeed", "0.0031s")
        assert frame.metadata["exposure_s"] == 0.0031
        assert frame.metadata["exposure_commanded_s"] == 0.003
        assert frame.suffix == ".nef" and frame.metadata["discarded"] == ["DSC_0001.JPG"]
        # Downloaded untouched (a raw file calibration decodes), then both files deleted from
        # the card through the real Directory Browse driver: nothing left, the JPEG unread.
        path = tmp_path / "f.nef"
        path.write_bytes(frame.data)
        assert float(decode_frame(path).dn[0, 0]) == 101
        assert _files(folder) == [] and driver.discarded == ["DSC_0001.JPG"]
    finally:
        driver.close()


def test_bulb_beyond_the_longest_speed_and_refusals(tmp_path: Path) -> None:
    folder, cam, clock = _recorded(tmp_path)
    driver = Gphoto2Camera(cam, Gphoto2Config(image_format="raw"), clock)
    try:
        assert ("imagequality", "NEF (Raw)") in cam.log
        assert driver.supported_exposures() == (0.0002, 3600.0)
        t0 = clock.now()
        frame = driver.capture(120.0)  # 4 × the longest timed speed (30 s)
        assert cam.log[-3:] == [("shutterspeed", "Bulb"), ("bulb", 1), ("bulb", 0)]
        assert cam.bulb_s == [120.0] and clock.now() - t0 == 120.0  # held on the rig's clock
        assert frame.metadata["bulb"] is True and frame.metadata["exposure_s"] == 120.0
        assert frame.metadata["discarded"] == [] and _files(folder) == []
    finally:
        driver.close()
    folder, cam, clock = _recorded(tmp_path / "2")
    driver = Gphoto2Camera(cam, Gphoto2Config(bulb="none"), clock)
    with pytest.raises(DeviceFault, match=r"beyond the longest shutter speed 30.0000s"):
        driver.capture(60.0)
    assert driver.supported_exposures()[-1] == 30.0
    with pytest.raises(DeviceFault, match=r"iso has no choice '12800'; it offers: 100, 125"):
        Gphoto2Camera(cam, Gphoto2Config(iso="12800"), clock)
    with pytest.raises(DeviceFault, match=r"imagequality has no choice 'TIFF \(RGB\)'"):
        Gphoto2Camera(cam, Gphoto2Config(raw_choice="TIFF (RGB)"), clock)
