"""Benchmark: calibrate (reduce to samples) runs of real camera size, issue 23 item 4.

What is measured, per configuration (camera size × number of poses, 3 brackets per pose):

- the whole `calibration.reduce.reduce_to_file` (what `gonio calibrate` runs: the samples
  streamed to the file pose by pose) with its default `ReduceOptions` (master darks per
  exposure, a flat field, reference-target radiometry, segmentation of the sample, per-pixel
  geometry, 4 × 4 bins), wall time and throughput in MP/s of the frames it decodes;
- the decode floor: every frame the reduce reads (pose brackets, darks, flats, reference
  captures), decoded in a fresh process exactly as the reduce does
  (`calibration.decode.decode_frame` with the manifest's SHA-256) and nothing else. The
  calibration's throughput as a fraction of the floor's (issue target ≥ 50 %) is floor wall /
  reduce wall on the same frames. LibRaw alone (`rawpy.imread` + `raw_image_visible`, no hash,
  no metadata, no float conversion) is timed too, as the floor under the floor;
- the time spent inside `decode_frame` during the reduce itself (a timing wrapper around it),
  so the decode share is measured, not only inferred from the floor;
- the peak resident set (ru_maxrss) of a fresh interpreter per configuration, at 50 and 500
  poses (issue target: independent of the number of poses), and the samples produced;
- with --fit, the time of `fitting.fit.fit_samples` on the 50-pose 2448 × 2048 samples, read as
  `gonio fit` reads them (binned into 0.1° cells above 10⁶ rows, fitting.binning).

Cameras (frames are written as the pipeline stores them for such a camera: a Bayer GenICam camera
through Aravis and a DSLR both give a raw RGGB mosaic, kept as DNG and decoded by rawpy/LibRaw):
- 2448 × 2048, 3.45 µm (Sony IMX264-class machine-vision sensor), 50 mm lens;
- 6000 × 4000, 3.92 µm (24 MP APS-C DSLR), 105 mm macro lens.
Both frame the 50 mm sample at 0.5 m about as the simulated rig's 64 × 64 camera does (it spans
about 70 % of the image height). The rest of the camera (gain, black and white level, read noise) is
the simulated rig's (configs/rigs/sim.toml); the intrinsics are the nominal ones (focal length /
pixel pitch, principal point at the centre), as run.toml records them for a lab without a
`gonio calibrate-camera` file.

How the runs are made (once; cached in --cache, never timed): the simulated rig renders them for
real at full resolution. The scene (configs/scenes/raw.toml: RGGB DNG, shot and read noise, dark
current and DSNU, PRNU and vignetting) lights the sample with a point lamp, so Mitsuba needs one
sample per pixel and the whole frame is exact geometry: ≈ 1 s a frame at 5 MP and ≈ 5 s at
24 MP on 2 cores. A 50-pose run with the plan's default calibration phases (16 darks per exposure,
32 flats, 3 reference poses × 3 brackets) is 239 frames: ≈ 4 min and 2.3 GB at 2448 × 2048,
≈ 20–30 min and 11 GB at 6000 × 4000. Upscaling small renders was not needed, and would have
given the reduce flat, blocky frames to segment instead of a real image.

The 500-pose run is the 50-pose 2448 × 2048 run repeated ten times, as a lab repeating its plan
would record it: the run directory is copied with hard links, and each repetition's captures are
new manifest rows (new pose indices, their own frame names hard-linked to the first repetition's
files, the same SHA-256, axes and exposures). The reduce does exactly the work of 500 rendered
poses — every frame is hashed, decoded, merged and reduced — but the repetitions cost no disk
(rendering 1500 more 5 MP frames would take ~15 min and 15 GB; 500 poses at 24 MP, 72 GB).
Only 2448 × 2048 is run at 500 poses: 500 poses at 24 MP would need 72 GB of frames.

Disk: --cache needs ≈ 16 GB for the default configurations (2.5 GB of it the samples files).

Run (slow: ≈ 10 min of reduces and decode floors, most of it the 500 poses and the 24 MP run,
plus ≈ 30 min to render the runs the first time; `make bench` skips it unless named:
`make bench BENCH=bench_camera_scale`):
    .venv/bin/python benchmarks/bench_camera_scale.py [--cache /tmp/gonio-bench-camera-scale]
        [--sizes 2448x2048,6000x4000] [--poses 50] [--large-poses 500] [--fit]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["main", "CAMERAS"]

REPO = Path(__file__).resolve().parent.parent
EXPOSURES_S = [0.001, 0.004, 0.016]
# 5 θ_i × 5 θ_o × 2 Δφ: every pose reachable (θ ≤ 70°, Δφ ≥ 60° keeps the arms apart); no θ_o = 0,
# where the plan keeps one azimuth only.
BASE_GRID = {
    "theta_i_deg": [10.0, 25.0, 40.0, 55.0, 70.0],
    "theta_o_deg": [8.0, 20.0, 32.0, 44.0, 56.0],
    "delta_phi_deg": [60.0, 180.0],
}
BASE_POSES = 50


@dataclass(frozen=True)
class Camera:
    key: str
    what: str
    width_px: int
    height_px: int
    pixel_pitch_m: float
    focal_length_m: float

    @property
    def megapixels(self) -> float:
        return self.width_px * self.height_px / 1e6


# The lenses frame the 50 mm sample at 0.5 m as the simulated rig's 64 × 64 camera does
# (f_x = 457.6 px over 64 px, configs/rigs/sim-camera.json): at normal view it spans 71 % of the
# height at 2448 × 2048 (f = 14 493 px) and 67 % at 6000 × 4000 (26 786 px), so about the same
# share of every frame is sample, holder and background as in the tested small runs.
CAMERAS = {
    c.key: c
    for c in (
        Camera(
            "2448x2048", "machine vision, IMX264-class 3.45 µm, 50 mm", 2448, 2048, 3.45e-6, 0.050
        ),
        Camera("6000x4000", "24 MP APS-C DSLR, 3.92 µm, 105 mm macro", 6000, 4000, 3.92e-6, 0.105),
    )
}


# -- making the runs (untimed, cached) -----------------------------------------------------------


def _rig(cam: Camera):  # -> acquisition.config.RigConfig (imported late: the CLI starts fast)
    """configs/rigs/sim.toml with this camera: resolution, pitch, lens, RGGB raw, and nominal
    intrinsics (no calibration file: sim-camera.json describes the 64 × 64 camera, not this)."""
    from acquisition.config import load_rig

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    camera = rig.camera.model_copy(
        update={
            "model": f"bench camera {cam.key} ({cam.what})",
            "resolution": (cam.width_px, cam.height_px),
            "pixel_pitch_m": cam.pixel_pitch_m,
            "focal_length_m": cam.focal_length_m,
            "color_filter": "RGGB",
        }
    )
    calibration = rig.calibration.model_copy(update={"intrinsics": None})
    return rig.model_copy(update={"camera": camera, "calibration": calibration})


def _acquire(out: Path, cam: Camera, scene: Path) -> None:
    from acquisition.config import PlanConfig
    from acquisition.operator import AutoOperator
    from gonio.pipeline import AcquireSpec, acquire

    plan = PlanConfig.model_validate(
        {
            "name": f"camera-scale-{cam.key}",
            "type": "isotropic",
            **BASE_GRID,
            "exposures_s": EXPOSURES_S,
            "order": "nearest",
            # The plan's default calibration phases, as a lab runs them.
            "calibration": {"dark": {}, "flat": {}, "reference": {}},
        }
    )
    acquire(
        out,
        AcquireSpec(rig=_rig(cam), scene=scene, plan=plan, operator=AutoOperator(), progress=False),
    )


def _replicate(src: Path, dst: Path, copies: int) -> None:
    """`dst`: the run `src` recorded `copies` times over (see the module doc). Every file is a
    hard link; repetition k's captures get pose indices + k·(poses of src) and frame names of
    their own, linked to src's frames."""
    for path in src.rglob("*"):
        rel = path.relative_to(src)
        if path.is_dir():
            (dst / rel).mkdir(parents=True, exist_ok=True)
        elif path.name.startswith("manifest.sqlite"):
            continue  # copied through SQLite below (it may have a WAL beside it)
        else:
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            os.link(path, dst / rel)
    a, b = sqlite3.connect(src / "manifest.sqlite"), sqlite3.connect(dst / "manifest.sqlite")
    try:
        a.backup(b)
    finally:
        a.close()
        b.close()
    db = sqlite3.connect(dst / "manifest.sqlite")
    try:
        cols = [r[1] for r in db.execute("PRAGMA table_info(captures)") if r[1] != "id"]
        rows = db.execute(
            f"SELECT {', '.join(cols)} FROM captures WHERE status = 'done'"
        ).fetchall()
        n_poses = 1 + max(r[cols.index("pose_index")] for r in rows)
        i_pose, i_path = cols.index("pose_index"), cols.index("frame_path")
        for k in range(1, copies):
            for row in rows:
                new = list(row)
                new[i_pose] = row[i_pose] + k * n_poses
                frame = Path(row[i_path])
                new[i_path] = str(frame.with_name(f"r{k:02d}_{frame.name}"))
                os.link(src / frame, dst / new[i_path])
                db.execute(
                    f"INSERT INTO captures ({', '.join(cols)}) "
                    f"VALUES ({', '.join('?' * len(cols))})",
                    new,
                )
        db.commit()
    finally:
        db.close()


def _ensure_run(cache: Path, cam: Camera, poses: int, scene: Path) -> Path:
    """The run of `poses` poses at this camera size, made once: built under a temporary name
    and renamed into place, so an existing directory is a complete run."""
    if poses % BASE_POSES:
        raise SystemExit(f"--poses/--large-poses must be multiples of {BASE_POSES} (got {poses})")
    run = cache / f"run-{cam.key}-p{poses}"
    if run.is_dir():
        return run
    partial = run.with_name(run.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    t0 = time.perf_counter()
    if poses == BASE_POSES:
        _acquire(partial, cam, scene)
        what = "simulated"
    else:
        _replicate(_ensure_run(cache, cam, BASE_POSES, scene), partial, poses // BASE_POSES)
        what = "replicated"
    partial.rename(run)
    print(f"{what} {run.name} in {time.perf_counter() - t0:.0f} s (cached)", flush=True)
    return run


def _frames(run: Path) -> tuple[list[tuple[str, str | None]], int]:
    """(path inside the run, SHA-256) of every frame the reduce decodes, and how many of them
    are pose brackets (the rest are darks, flats and reference captures)."""
    from acquisition.store import RunStore
    from calibration.darks import calibration_frames

    with RunStore.open(run) as store:
        poses = [(r.frame_path, r.sha256) for r in store.captures("done")]
    calib = [
        (e["path"], e.get("sha256"))
        for kind in ("dark", "flat", "reference")
        for e in calibration_frames(run, kind)
    ]
    return poses + calib, len(poses)


def _warm(run: Path, frames: list[tuple[str, str | None]]) -> None:
    """Read every frame once, untimed, so the reduce and the decode floor start from the same
    page cache (whatever of the run fits in memory)."""
    for rel, _sha in frames:
        with open(run / rel, "rb") as fh:
            while fh.read(1 << 24):
                pass


# -- the measurements, each in a fresh interpreter -------------------------------------------------


def _peak_rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _cpu_s() -> float:
    """CPU seconds of this process so far (user + system): beside the wall time, since the
    two cores may be shared with other work while the benchmark runs."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _child_reduce(run: Path, out: Path) -> dict:
    import calibration.darks
    import calibration.decode
    import calibration.reduce
    from calibration.reduce import ReduceOptions, reduce_to_file

    decode_s = [0.0]
    inner = calibration.decode.decode_frame

    def timed(*args, **kwargs):  # decode_frame's own signature
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            decode_s[0] += time.perf_counter() - t0

    # Every module that calls it by its own name (flatfield imports it at call time).
    for mod in (calibration.decode, calibration.darks, calibration.reduce):
        mod.decode_frame = timed
    rss_before_mib = _peak_rss_mib()
    cpu0_s, t0 = _cpu_s(), time.perf_counter()
    # As `gonio calibrate` does: written pose by pose, not read back.
    done = reduce_to_file(run, ReduceOptions(), out=out)
    wall_s = time.perf_counter() - t0
    return {
        "reduce_s": wall_s,
        "reduce_cpu_s": _cpu_s() - cpu0_s,
        "decode_in_reduce_s": decode_s[0],
        "samples": done.rows,
        "rss_before_mib": rss_before_mib,
        "peak_rss_mib": _peak_rss_mib(),
    }


def _child_decode(run: Path) -> dict:
    import numpy as np
    import rawpy

    from calibration.decode import decode_frame

    frames, _n_pose = _frames(run)
    cpu0_s, t0 = _cpu_s(), time.perf_counter()
    for rel, sha in frames:
        decode_frame(run / rel, sha)
    decode_s = time.perf_counter() - t0
    decode_cpu_s = _cpu_s() - cpu0_s
    t0 = time.perf_counter()
    for rel, _sha in frames:
        with rawpy.imread(str(run / rel)) as raw:
            np.array(raw.raw_image_visible)
    libraw_s = time.perf_counter() - t0
    return {
        "decode_s": decode_s,
        "decode_cpu_s": decode_cpu_s,
        "libraw_s": libraw_s,
        "peak_rss_mib": _peak_rss_mib(),
    }


def _child_fit(samples: Path) -> dict:
    from brdfdata.samples import read_samples
    from fitting.binning import AUTO_BIN_DEG, AUTO_BIN_ROWS, BinOptions, read_binned, rows_in
    from fitting.fit import FitOptions, fit_samples

    rows = rows_in(samples)
    t0 = time.perf_counter()
    # As `gonio fit` reads a samples file (gonio/cli/fit.py: _read_for_fit): binned above 10⁶ rows.
    if rows > AUTO_BIN_ROWS:
        table, _report = read_binned(samples, BinOptions(width_deg=AUTO_BIN_DEG))
        opts = FitOptions(binned_source=samples)
    else:
        table, opts = read_samples(samples), FitOptions()
    read_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    fit_samples(table, opts)
    return {
        "rows": rows,
        "fitted_rows": int(len(table.f)),
        "read_s": read_s,
        "fit_s": time.perf_counter() - t0,
        "peak_rss_mib": _peak_rss_mib(),
    }


def _in_child(*args: str) -> dict:
    """Run one measurement in a fresh interpreter (its peak RSS is its own) → its JSON."""
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"measurement {' '.join(args)} failed (exit {proc.returncode})")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _child_main(argv: list[str]) -> None:
    kind, *paths = argv
    if kind == "reduce":
        result = _child_reduce(Path(paths[0]), Path(paths[1]))
    elif kind == "decode":
        result = _child_decode(Path(paths[0]))
    elif kind == "fit":
        result = _child_fit(Path(paths[0]))
    else:
        raise SystemExit(f"unknown measurement {kind!r}")
    print(json.dumps(result), flush=True)


# -- the benchmark --------------------------------------------------------------------------------


def bench_one(cache: Path, cam: Camera, poses: int, scene: Path) -> dict:
    run = _ensure_run(cache, cam, poses, scene)
    frames, n_pose_frames = _frames(run)
    total_mp = len(frames) * cam.megapixels
    (cache / "samples").mkdir(exist_ok=True)
    out = cache / "samples" / f"{run.name}.parquet"
    _warm(run, frames)
    red = _in_child("reduce", str(run), str(out))
    _warm(run, frames)
    dec = _in_child("decode", str(run))
    return {
        "camera": cam.key,
        "poses": poses,
        "pose_frames": n_pose_frames,
        "frames": len(frames),
        "total_mp": total_mp,
        "pose_mp": n_pose_frames * cam.megapixels,
        **red,
        **{f"floor_{k}": v for k, v in dec.items()},
        "samples_file": str(out),
    }


def _report(rows: list[dict]) -> None:
    print(
        "\nreduce_to_file, default ReduceOptions (darks, flat, reference scale, segmentation, 4×4 "
        "bins), 3 brackets per pose, DNG through rawpy.\nMP = megapixels of every frame the "
        "reduce reads (pose brackets + darks, flats, reference); 'floor' = decode_frame of those "
        "frames alone; CPU s in brackets."
    )
    print(
        f"{'camera':>10} {'poses':>5} {'frames':>10} {'reduce s':>14} {'MP/s':>6} "
        f"{'floor s':>12} {'floor MP/s':>10} {'calib/floor':>13} {'decode share':>12} "
        f"{'LibRaw s':>8} {'peak RSS MiB':>12} {'samples':>10}"
    )
    for r in rows:
        frames = f"{r['pose_frames']}+{r['frames'] - r['pose_frames']}"
        ratio_wall = r["floor_decode_s"] / r["reduce_s"]
        ratio_cpu = r["floor_decode_cpu_s"] / r["reduce_cpu_s"]
        print(
            f"{r['camera']:>10} {r['poses']:>5} {frames:>10} "
            f"{r['reduce_s']:>6.0f} ({r['reduce_cpu_s']:>5.0f}) "
            f"{r['total_mp'] / r['reduce_s']:>6.2f} "
            f"{r['floor_decode_s']:>5.1f} ({r['floor_decode_cpu_s']:>4.0f}) "
            f"{r['total_mp'] / r['floor_decode_s']:>10.1f} "
            f"{100 * ratio_wall:>5.1f}% ({100 * ratio_cpu:.1f}%) "
            f"{100 * r['decode_in_reduce_s'] / r['reduce_s']:>11.1f}% "
            f"{r['floor_libraw_s']:>8.1f} {r['peak_rss_mib']:>12.0f} {r['samples']:>10}"
        )
    print(
        "target (issue 23 item 4): calib/floor ≥ 50 %; peak RSS independent of the number of "
        "poses. 'decode share': time inside decode_frame during the reduce / reduce wall."
    )


def main(argv: list[str] | None = None) -> None:
    argv = argv if argv is not None else []
    if argv[:1] == ["--child"]:
        _child_main(argv[1:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/gonio-bench-camera-scale"))
    ap.add_argument("--scene", type=Path, default=REPO / "configs" / "scenes" / "raw.toml")
    ap.add_argument("--sizes", default=",".join(CAMERAS), help="camera sizes, comma-separated")
    ap.add_argument("--poses", type=int, default=BASE_POSES, help="poses of every size's run")
    ap.add_argument(
        "--large-poses",
        type=int,
        default=500,
        help="poses of the large-run memory check, at 2448x2048 only (0: skip)",
    )
    ap.add_argument("--fit", action="store_true", help="also time fit_samples (2448x2048 run)")
    args = ap.parse_args(argv)
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    unknown = [s for s in sizes if s not in CAMERAS]
    if unknown:
        raise SystemExit(f"unknown size(s) {unknown}; known: {', '.join(CAMERAS)}")
    args.cache.mkdir(parents=True, exist_ok=True)
    configs = [(CAMERAS[s], args.poses) for s in sizes]
    if args.large_poses and "2448x2048" in sizes:
        configs.append((CAMERAS["2448x2048"], args.large_poses))
    # Make every run first (slow, untimed), then measure.
    for cam, poses in configs:
        _ensure_run(args.cache, cam, poses, args.scene)
    rows = []
    for cam, poses in configs:
        print(f"measuring {cam.key} × {poses} poses ...", flush=True)
        rows.append(bench_one(args.cache, cam, poses, args.scene))
        # each configuration as it finishes (the whole benchmark takes about an hour)
        print(json.dumps(rows[-1]), flush=True)
    _report(rows)
    if args.fit:
        first = next((r for r in rows if r["camera"] == "2448x2048"), None)
        if first is None:
            print("--fit needs the 2448x2048 size")
            return
        fit = _in_child("fit", first["samples_file"])
        print(
            f"fit_samples (torrance-sparrow, defaults) of {first['poses']} poses' "
            f"{fit['rows']} samples, binned to {fit['fitted_rows']} rows: read+bin "
            f"{fit['read_s']:.1f} s, fit {fit['fit_s']:.1f} s, "
            f"peak RSS {fit['peak_rss_mib']:.0f} MiB"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
