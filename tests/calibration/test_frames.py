"""Frame encoders (simulator.frames) and decoders (calibration.decode): exact round trips through
the independent readers (rawpy/LibRaw, OpenEXR), the docs/design.md §7 linearisation, and errors."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest
import rawpy
from conftest import data_dir

from calibration.decode import FrameError, decode_frame, demosaic_to_rgb, linear
from simulator.frames import encode_capture, encode_dng, encode_exr
from simulator.scene import SensorSpec
from simulator.sensor import Sensor, expected_dn


def _mosaic(seed=0, shape=(48, 64)):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 2**14, shape).astype(np.uint16)


def test_dng_bit_exact_through_rawpy(tmp_path):
    m = _mosaic()
    p = tmp_path / "f.dng"
    p.write_bytes(encode_dng(m, {"pose": 3}, black_level=64, white_level=16383, exposure_s=1 / 3))
    with rawpy.imread(str(p)) as raw:  # the independent reader
        np.testing.assert_array_equal(raw.raw_image_visible, m)
        assert list(raw.black_level_per_channel) == [64, 64, 64, 64]
        assert raw.white_level == 16383
        assert raw.raw_type == rawpy.RawType.Flat
    d = decode_frame(p)
    assert d.channels == "CFA" and d.cfa_pattern == "RGGB"
    np.testing.assert_array_equal(d.dn, m.astype(np.float32))
    assert d.exposure_s == 1 / 3  # exact: from the JSON metadata, not the float32 EXIF copy
    assert d.metadata["pose"] == 3
    np.testing.assert_array_equal(linear(d), ((m - 64.0) / (16383.0 - 64.0)).astype(np.float32))


def test_simulated_sensor_dng_decodes_to_expected_linear_values(tmp_path):
    # Noise-free Bayer sensor → DNG → rawpy → linear. Expected from the EMVA mean (expected_dn);
    # the only difference allowed is ADC rounding, ±0.5 DN.
    spec = SensorSpec(noise=False, bayer="RGGB", black_level_dn=64, adc_bits=14)
    rng = np.random.default_rng(5)
    L = rng.uniform(0.0, 2.0, (32, 40, 3))
    mosaic = Sensor(spec, 4.0, rng=0).capture(L, 0.02)
    white = 2**spec.adc_bits - 1
    p = tmp_path / "sim.dng"
    p.write_bytes(encode_dng(mosaic, {"exposure_s": 0.02}, black_level=64, white_level=white))
    d = decode_frame(p)
    mu = expected_dn(L, 0.02, spec, 4.0)
    lin_expect = (mu - 64) / (white - 64)
    assert np.abs(linear(d) - lin_expect).max() <= 0.5 / (white - 64) + 1e-7
    assert 0.05 < np.median(lin_expect) < 0.95  # a meaningful range of values was exercised


def test_exr_round_trip_exact(tmp_path):
    rng = np.random.default_rng(2)
    img = (rng.lognormal(0, 5, (17, 23, 3))).astype(np.float32)
    img[0, 0] = [0.0, 1e-30, 3e38]
    md = {"exposure_s": 0.0123456789012345, "third": 1 / 3, "name": "x", "list": [1.5, 2]}
    p = tmp_path / "f.exr"
    p.write_bytes(encode_exr(img, md))
    with OpenEXR.File(str(p)) as f:  # the independent reader
        np.testing.assert_array_equal(f.channels()["RGB"].pixels, img)
    d = decode_frame(p)
    assert d.channels == "RGB"
    np.testing.assert_array_equal(d.dn, img)
    assert d.metadata == md  # float64 values survive exactly (JSON string attribute)
    assert d.exposure_s == md["exposure_s"]

    mono = img[..., 1].copy()
    p2 = tmp_path / "m.exr"
    p2.write_bytes(encode_exr(mono, {}))
    d2 = decode_frame(p2)
    assert d2.channels == "Y"
    np.testing.assert_array_equal(d2.dn, mono)


def _one_line_naming(exc, path):
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_decode_errors(tmp_path):
    good = encode_dng(_mosaic(), {}, white_level=16383)
    p = tmp_path / "trunc.dng"
    p.write_bytes(good[: len(good) // 2])
    with pytest.raises(FrameError) as e:
        decode_frame(p)
    assert "truncated" in _one_line_naming(e, p)

    p = tmp_path / "tiny.dng"
    p.write_bytes(good[:100])
    with pytest.raises(FrameError) as e:
        decode_frame(p)
    _one_line_naming(e, p)

    p = tmp_path / "nochan.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Z": np.ones((4, 4), np.float32)}) as f:
        f.write(str(p))
    with pytest.raises(FrameError) as e:
        decode_frame(p)
    assert "Z" in _one_line_naming(e, p)

    p = tmp_path / "frame.png"
    p.write_bytes(b"\x89PNG")
    with pytest.raises(FrameError) as e:
        decode_frame(p)
    assert "suffix" in _one_line_naming(e, p)

    with pytest.raises(FrameError) as e:
        decode_frame(tmp_path / "missing.exr")
    assert issubclass(FrameError, ValueError)


def test_real_files():
    # Not shipped (no licence stated): skipped with `gonio data fetch camera_raw` when absent.
    camera_raw = data_dir("camera_raw")
    nef = camera_raw / "Nikon_uncompressed.nef"
    with pytest.raises(FrameError) as e:
        decode_frame(nef)
    assert "not a Bayer sensor raw (RawType.Stack)" in _one_line_naming(e, nef)

    dng = camera_raw / "Blackmagic.dng"
    d = decode_frame(dng)
    with rawpy.imread(str(dng)) as raw:
        np.testing.assert_array_equal(d.dn, raw.raw_image_visible.astype(np.float32))
        black = np.asarray(raw.black_level_per_channel)[raw.raw_colors_visible]
        white = raw.white_level
    np.testing.assert_array_equal(d.black_level, black)
    assert d.channels == "CFA" and d.cfa_pattern == "RGGB" and d.white_level == white
    lin = linear(d)
    assert lin.shape == d.dn.shape and np.isfinite(lin).all()


def test_demosaic_superpixel():
    m = np.array([[1, 2, 5, 6], [3, 4, 7, 8]], dtype=np.uint16)  # RGGB tiles
    rgb = demosaic_to_rgb(m, "RGGB")
    np.testing.assert_array_equal(rgb, [[[1, 2.5, 4], [5, 6.5, 8]]])
    rgb = demosaic_to_rgb(m, "BGGR")
    np.testing.assert_array_equal(rgb, [[[4, 2.5, 1], [8, 6.5, 5]]])


@pytest.mark.parametrize("fmt", ["dng", "exr"])
def test_encode_capture_carries_levels_and_exposure(tmp_path, fmt):
    spec = SensorSpec(bayer="RGGB" if fmt == "dng" else None, black_level_dn=200, adc_bits=12)
    dn = Sensor(spec, 2.8, rng=3).capture(np.full((24, 32, 3), 0.5), 0.004)
    data, suffix = encode_capture(dn, spec, fmt, {"exposure_s": 0.004})
    p = tmp_path / f"c{suffix}"
    p.write_bytes(data)
    d = decode_frame(p)
    np.testing.assert_array_equal(d.dn, dn.astype(np.float32))
    assert d.exposure_s == 0.004 and d.white_level == 4095
    assert np.all(np.asarray(d.black_level) == 200)
    assert d.channels == ("CFA" if fmt == "dng" else "RGB")


def test_encode_capture_rejects_rgb_dng():
    with pytest.raises(ValueError, match="Bayer"):
        encode_capture(np.zeros((24, 24, 3), np.uint16), SensorSpec(), "dng")
