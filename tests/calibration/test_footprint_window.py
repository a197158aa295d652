"""Calibration processes each pose only around the sample's image (calibration.planes:
`footprint_window`) and streams the samples to the file pose by pose (calibration.reduce:
`reduce_to_file`, brdfdata.samples: `SampleStream`); neither may change a sample.

- A pose reduced in its window gives exactly the whole frame's planes, geometry and
  segmentation there, and nothing on the sample outside it. Exact: every per-pixel step
  reads only pixels inside the window (the merge's neighbours are on the sample, the
  segmentation's search band is in the window's padding), so the same IEEE operations run on
  the same values. The camera sees the 50 mm sample ~45 px wide on a 160 × 160 sensor, with
  the holder and background around it (real edges for the segmentation to find).
- A samples file written in several row groups, its metadata given at the end, reads back as
  the table written at once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acquisition.store import RunStore
from brdfdata.samples import SampleStream, SampleTable, read_samples, write_samples
from calibration.planes import pose_planes
from calibration.reduce import ReduceOptions, _captures_by_pose, _decode_pose, _run_calibration
from tests.support.small_runs import REPO, small_run


@pytest.fixture(scope="module", params=["raw.toml", "demo.toml"], ids=["dng-mosaic", "exr-rgb"])
def run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-pose run as RGGB DNG (raw.toml) and as RGB EXR (demo.toml): a mosaic's window
    steps by 2 photosites, an RGB frame's by 1 with 3 values per pixel."""
    from acquisition.config import load_rig

    # The sim rig's camera with a 160 × 160 sensor and nominal intrinsics: the sample spans
    # ~45 px of it, as on a lab camera a part of the frame is sample.
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    rig = rig.model_copy(
        update={
            "camera": rig.camera.model_copy(update={"resolution": (160, 160)}),
            "calibration": rig.calibration.model_copy(update={"intrinsics": None}),
        }
    )
    out = tmp_path_factory.mktemp("window") / "run"
    return small_run(out, request.param, theta_o_deg=(0.0, 50.0), rig=rig)


def test_a_pose_in_its_window_is_the_whole_frame_there(run: Path) -> None:
    with RunStore.open(run) as store:
        cal, _rig = _run_calibration(store, run, ReduceOptions(bin_px=2))
        by_pose = _captures_by_pose(store, run)
    for recs in by_pose.values():
        good, decoded = _decode_pose(recs, run, [], False)
        exposures = [float(r.exposure_s) for r in good]
        args = (cal, decoded, exposures, good[0].axes_measured)
        whole, seg_whole = pose_planes(*args, crop=False)
        part, seg_part = pose_planes(*args)
        assert part[0].flux.size < 0.5 * whole[0].flux.size  # the window is a part
        for a, b in zip(whole, part, strict=True):
            assert a.origin == (0, 0) and b.origin != (0, 0)
            x0, y0 = b.origin[0] // b.step, b.origin[1] // b.step
            h, w = b.flux.shape
            sl = (slice(y0, y0 + h), slice(x0, x0 + w))
            on = b.geo.on_sample
            assert on.sum() == a.geo.on_sample.sum() > 20  # nothing on the sample outside
            np.testing.assert_array_equal(a.geo.on_sample[sl], on)
            for name in ("flux", "var", "all_sat"):
                np.testing.assert_array_equal(getattr(a, name)[sl][on], getattr(b, name)[on])
            for name in ("point_m", "wi", "wo", "light_distance_m"):
                np.testing.assert_array_equal(getattr(a.geo, name)[sl], getattr(b.geo, name))
        np.testing.assert_array_equal(seg_whole[sl], seg_part)  # the whole quadrilateral


def _table(rng: np.random.Generator, n: int, capture: int) -> dict[str, np.ndarray]:
    return {
        "theta_i": rng.uniform(0, 1.4, n),
        "phi_i": rng.uniform(-3, 3, n),
        "theta_o": rng.uniform(0, 1.4, n),
        "phi_o": rng.uniform(-3, 3, n),
        "channel": rng.choice(np.array(["R", "G", "B"], dtype=object), n),
        "f": rng.uniform(0.1, 2.0, n),
        "sigma": rng.uniform(0.01, 0.1, n),
        "flags": rng.integers(0, 3, n).astype(np.int32),
        "capture_id": np.full(n, capture, np.int64),
        "pixel_x": rng.integers(0, 2448, n).astype(np.int32),
        "pixel_y": rng.integers(0, 2048, n).astype(np.int32),
    }


def test_a_streamed_file_reads_back_as_the_table_written_at_once(tmp_path, monkeypatch) -> None:
    import pyarrow.parquet as pq

    from brdfdata.samples import write_samples_streamed

    rng = np.random.default_rng(3)
    pieces = [_table(rng, n, i) for i, n in enumerate((700, 0, 1300, 450))]
    meta = {"gonio.calibration": '{"late": true}'}
    monkeypatch.setattr(SampleStream, "ROW_GROUP_ROWS", 1000)

    def produce(stream: SampleStream) -> dict[str, str]:
        for piece in pieces:
            stream.append(piece)
        return meta

    rows = write_samples_streamed(tmp_path / "streamed.parquet", produce)
    assert rows == 2450
    assert pq.ParquetFile(tmp_path / "streamed.parquet").num_row_groups == 2
    cat = {k: np.concatenate([p[k] for p in pieces]) for k in pieces[0]}
    core = ("theta_i", "phi_i", "theta_o", "phi_o", "channel", "f", "sigma", "flags")
    whole = SampleTable(
        **{k: cat[k] for k in core},
        extra={k: cat[k] for k in cat if k not in core},
        metadata=meta,
    )
    write_samples(tmp_path / "whole.parquet", whole)
    a = read_samples(tmp_path / "streamed.parquet")
    b = read_samples(tmp_path / "whole.parquet")
    assert a.metadata == b.metadata and a.metadata["gonio.calibration"] == '{"late": true}'
    for name in core:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.extra.keys() == b.extra.keys()
    for name in a.extra:
        np.testing.assert_array_equal(a.extra[name], b.extra[name])
        assert a.extra[name].dtype == b.extra[name].dtype


def test_a_failed_stream_leaves_no_file(tmp_path) -> None:
    from brdfdata.samples import write_samples_streamed

    rng = np.random.default_rng(4)

    def produce(stream: SampleStream) -> dict[str, str]:
        stream.append(_table(rng, 10, 0))
        raise RuntimeError("the reduction failed half way")

    with pytest.raises(RuntimeError):
        write_samples_streamed(tmp_path / "s.parquet", produce)
    assert list(tmp_path.iterdir()) == []
