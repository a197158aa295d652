"""Benchmark: `gonio fit` of a 10⁷-row samples table in bounded memory (issue 22 item 8: peak
RSS < 4 GB).

The table is what a camera run gives: POSES poses of the isotropic plan, each seen by a
PIXELS × PIXELS grid of pixels over a 10 mm sample with light and camera at 0.6 m (so each
pixel has its own (ω_i, ω_o), ±0.5° around the pose), three channels, f from gonio's
Torrance-Sparrow (Beckmann, F ≡ 1: kd 0.2/0.15/0.1, ks 0.5, m 0.15) with 2 % Gaussian noise.
It is written in row groups of 10⁶ rows without ever holding the whole table.

Then `gonio fit TABLE --model torrance-sparrow --option fresnel=none --steps 1000` and
`gonio report --samples TABLE --fit FIT.json` run in fresh processes (both bin by default above
10⁶ rows, fitting.binning, 0.1° cells; the fit corrects each bin for the model's curvature and
states what binning still moves) and the benchmark reports their wall time, peak RSS (getrusage
of the children), the bins, the verdicts and the recovered parameters against the truth.

Run: .venv/bin/python benchmarks/bench_big_fit.py [--rows 10000000] [--bin 0.1]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from brdfdata.directions import isotropic_gonio_directions, normalize, vector_to_spherical
from fitting import models

__all__ = ["main"]

TRUTH = {"kd": (0.2, 0.15, 0.1), "ks": 0.5, "m": 0.15}
OPTIONS = {"distribution": "beckmann", "fresnel": "none"}
DISTANCE_M = 0.6
SAMPLE_M = 0.010


def write_table(path: Path, rows: int, rng: np.random.Generator) -> int:
    """A camera-like table of about ``rows`` rows (module docstring), streamed to ``path``."""
    wi0, wo0 = isotropic_gonio_directions()
    poses = len(wi0)
    pixels = max(2, int(round(np.sqrt(rows / (3 * poses)))))
    g = np.linspace(-SAMPLE_M / 2, SAMPLE_M / 2, pixels)
    px, py = np.meshgrid(g, g)
    points = np.stack([px.ravel(), py.ravel(), np.zeros(px.size)], axis=1)
    model = models.get("torrance-sparrow", **OPTIONS)
    writer = None
    written = 0
    per_group = max(1, 1_000_000 // (3 * points.shape[0]))
    try:
        for start in range(0, poses, per_group):
            sl = slice(start, min(poses, start + per_group))
            wi = normalize((wi0[sl, None, :] * DISTANCE_M - points[None]).reshape(-1, 3))
            wo = normalize((wo0[sl, None, :] * DISTANCE_M - points[None]).reshape(-1, 3))
            keep = (wi[:, 2] > 0.02) & (wo[:, 2] > 0.02)
            pose = np.repeat(np.arange(sl.start, sl.stop), points.shape[0])[keep]
            wi, wo = wi[keep], wo[keep]
            ti, pi = vector_to_spherical(wi)
            to, po = vector_to_spherical(wo)
            names = ("theta_i", "phi_i", "theta_o", "phi_o", "channel", "f", "sigma", "capture_id")
            cols = {k: [] for k in names}
            for c, kd in zip("RGB", TRUTH["kd"], strict=True):
                params = {
                    "kd": np.array([[kd]]),
                    "ks": np.array([[TRUTH["ks"]]]),
                    "m": np.array([[TRUTH["m"]]]),
                }
                f = np.asarray(model.evaluate(params, wi, wo), dtype=np.float64).reshape(-1)
                sigma = 0.02 * f + 1e-4
                noisy = np.abs(f + rng.normal(0.0, 1.0, f.size) * sigma)
                for k, v in (
                    ("theta_i", ti),
                    ("phi_i", pi),
                    ("theta_o", to),
                    ("phi_o", po),
                    ("f", noisy),
                    ("sigma", sigma),
                ):
                    cols[k].append(v)
                cols["channel"].append(np.full(f.size, c))
                cols["capture_id"].append(pose)  # one capture per pose, as a run's table has
            table = pa.table(
                {
                    k: (
                        pa.array(np.concatenate(v))
                        if k != "channel"
                        else pa.array(np.concatenate(v).astype(str))
                    )
                    for k, v in cols.items()
                }
            )
            if writer is None:
                writer = pq.ParquetWriter(path, table.schema)
            writer.write_table(table)
            written += table.num_rows
    finally:
        if writer is not None:
            writer.close()
    return written


def _fit(table: Path, out: Path, bin_deg: float | None) -> tuple[float, float, int]:
    """Wall s, peak RSS (MB) and exit code of `gonio fit` in a fresh process."""
    cmd = [
        sys.executable,
        "-m",
        "gonio.cli",
        "fit",
        str(table),
        "--model",
        "torrance-sparrow",
        "--option",
        "fresnel=none",
        "--steps",
        "1000",
        "--out",
        str(out),
        "--accept-poor-fit",
    ]
    if bin_deg is not None:
        cmd += ["--bin", str(bin_deg)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.perf_counter() - t0
    for line in proc.stdout.splitlines():
        if "binned" in line or line.startswith("error"):
            print("   ", line.strip())
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return wall, rss, proc.returncode


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=10_000_000)
    ap.add_argument(
        "--bin", type=float, default=None, help="--bin for gonio fit (default: its own)"
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.parquet"
        t0 = time.perf_counter()
        n = write_table(path, args.rows, np.random.default_rng(0))
        print(
            f"table: {n:,} rows, {path.stat().st_size / 1e6:.0f} MB on disk, written in "
            f"{time.perf_counter() - t0:.0f} s"
        )
        wall, rss, rc = _fit(path, Path(tmp) / "fit", args.bin)
        print(f"gonio fit: {wall:.0f} s wall, peak RSS {rss:.0f} MB, exit {rc}")
        fit = json.loads((Path(tmp) / "fit" / "fit-torrance-sparrow.json").read_text())
        binning = fit["diagnostics"].get("binning", {})
        print(f"bins: {binning.get('bins')}, bias bound {binning.get('bias_bound_sd')} sd")
        for v in fit.get("verdicts", []):
            print(f"  verdict {v['name']}: {v['status']} — {v['reason']}")
        t0 = time.perf_counter()
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        cmd = [
            sys.executable,
            "-m",
            "gonio.cli",
            "report",
            "--samples",
            str(path),
            "--fit",
            str(Path(tmp) / "fit" / "fit-torrance-sparrow.json"),
        ]
        rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT).returncode
        after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        # ru_maxrss of the children is the largest child's: report only if it exceeded the fit.
        peak = f"{after:.0f} MB" if after > before else f"≤ {before:.0f} MB (below the fit's)"
        print(f"gonio report: {time.perf_counter() - t0:.0f} s wall, peak RSS {peak}, exit {rc}")
        p = fit["parameters"]
        for name, truth in (("m", TRUTH["m"]), ("kd_R", TRUTH["kd"][0]), ("ks_G", TRUTH["ks"])):
            q = p[name]
            print(f"  {name}: {q['median']:.6g} [{q['p2.5']:.6g}, {q['p97.5']:.6g}] truth {truth}")


if __name__ == "__main__":
    main()
