"""Bad input to the reduce step: corrupt frames are skipped and counted, missing frames are an
error naming the first, and no half-written samples.parquet is ever left behind."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from acquisition.store import RunStore
from brdfdata.samples import read_samples
from calibration.reduce import CalibrationError, reduce_run
from tests.support.paths import REPO
from tests.support.small_runs import small_run


def _small_run(root: Path, scene: str) -> Path:
    return small_run(root / "run", scene)


@pytest.fixture(scope="module")
def dng_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _small_run(tmp_path_factory.mktemp("dng"), "raw.toml")


@pytest.fixture(scope="module")
def exr_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _small_run(tmp_path_factory.mktemp("exr"), "demo.toml")


def _copy(run: Path, tmp_path: Path) -> tuple[Path, list]:
    dst = tmp_path / "copy"
    shutil.copytree(run, dst)
    return dst, list(RunStore.open(dst).captures("done"))


def _skipped(table) -> dict:
    return json.loads(table.metadata["gonio.skipped_captures"])


def test_clean_run_reports_zero_skipped(dng_run: Path, tmp_path: Path) -> None:
    run, recs = _copy(dng_run, tmp_path)
    table = reduce_run(run)
    assert _skipped(table)["count"] == 0
    assert set(np.unique(table.extra["capture_id"])) <= {r.id for r in recs}


def test_truncated_dng_is_skipped_with_a_counted_warning(dng_run, tmp_path, capsys) -> None:
    run, recs = _copy(dng_run, tmp_path)
    bad = recs[0]
    frame = run / bad.frame_path
    frame.write_bytes(frame.read_bytes()[: frame.stat().st_size // 2])
    table = reduce_run(run)
    info = _skipped(table)
    assert info["count"] == 1
    assert info["captures"][0]["capture_id"] == bad.id
    assert "truncated" in info["captures"][0]["reason"]
    err = capsys.readouterr().err
    assert f"skipping capture {bad.id}" in err
    assert "1 capture(s) skipped" in err
    # The written file carries the same count (the metadata survives the round trip).
    on_disk = read_samples(run / "samples.parquet")
    assert _skipped(on_disk)["count"] == 1


def test_exr_without_colour_channels_is_skipped(exr_run: Path, tmp_path: Path) -> None:
    import OpenEXR

    run, recs = _copy(exr_run, tmp_path)
    bad = recs[1]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    zeros = np.zeros((64, 64), np.float32)
    with OpenEXR.File(header, {"Z": zeros}) as f:
        f.write(str(run / bad.frame_path))
    table = reduce_run(run)
    info = _skipped(table)
    assert info["count"] == 1
    assert "no R,G,B or Y channels" in info["captures"][0]["reason"]
    # The pose keeps its other bracket: its samples are still there, under that capture's id.
    sibling = [r.id for r in recs if r.pose_index == bad.pose_index and r.id != bad.id]
    assert set(sibling) <= set(np.unique(table.extra["capture_id"]))


def test_missing_frame_is_an_error_naming_it_and_writes_nothing(dng_run, tmp_path) -> None:
    run, recs = _copy(dng_run, tmp_path)
    (run / recs[2].frame_path).unlink()
    with pytest.raises(CalibrationError) as info:
        reduce_run(run)
    msg = str(info.value)
    assert "\n" not in msg
    assert recs[2].frame_path in msg
    assert not (run / "samples.parquet").exists()


def test_every_frame_corrupt_is_an_error(dng_run: Path, tmp_path: Path) -> None:
    run, recs = _copy(dng_run, tmp_path)
    for r in recs:
        (run / r.frame_path).write_bytes(b"not a raw file")
    with pytest.raises(CalibrationError, match="no frame could be decoded"):
        reduce_run(run)
    assert not (run / "samples.parquet").exists()


def test_a_failed_write_leaves_no_partial_file(dng_run, tmp_path, monkeypatch) -> None:
    """A crash while writing (disk full, kill) leaves neither a partial samples.parquet nor a
    temp file; an earlier samples.parquet is left intact."""
    import pyarrow.parquet as pq

    run, _ = _copy(dng_run, tmp_path)
    reduce_run(run)
    before = (run / "samples.parquet").read_bytes()
    real = pq.ParquetWriter.write_table

    def half_then_fail(self, table, *args, **kwargs):
        real(self, table.slice(0, table.num_rows // 2), *args, **kwargs)  # half-written...
        raise OSError("No space left on device")  # ...then the disk fills up

    monkeypatch.setattr(pq.ParquetWriter, "write_table", half_then_fail)
    with pytest.raises(OSError):
        reduce_run(run)
    assert (run / "samples.parquet").read_bytes() == before
    assert sorted(p.name for p in run.iterdir() if "samples" in p.name) == ["samples.parquet"]


def test_corrupt_calibration_frame_is_an_error(dng_run: Path, tmp_path: Path) -> None:
    """Darks and flats apply to every capture: a bad one cannot be skipped silently."""
    from acquisition.operator import AutoOperator
    from calibration.darks import calibration_frames
    from gonio.pipeline import capture_calibration

    run, _ = _copy(dng_run, tmp_path)
    # Darks recorded as a lab would add them to a finished run (`gonio capture dark`).
    capture_calibration(
        run,
        "dark",
        rig_path=REPO / "configs" / "rigs" / "sim.toml",
        scene_path=REPO / "configs" / "scenes" / "raw.toml",
        operator=AutoOperator(),
    )
    entries = calibration_frames(run, "dark")
    (run / entries[0]["path"]).write_bytes(b"junk")
    with pytest.raises(CalibrationError, match="dark frame unusable"):
        reduce_run(run)
