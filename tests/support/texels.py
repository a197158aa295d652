"""Helpers for the per-texel tests: per-texel samples of the textured scene, and a Dask cluster of
separate processes (`dask scheduler` + `dask worker`, as on two hosts) on localhost.

The samples are Mitsuba's own evaluation of the textured BSDF (simulator.texture, the same bitmaps
the simulated rig renders) at each texel's centre, with photon-like (Poisson) noise: a full
simulated acquisition of 32 × 32 texels would take minutes, and the per-texel calibration itself is
tested on a real simulated run in tests/calibration/test_texel_samples.py. The ground truth is the
scene's texture (simulator.texture.texel_truth), never the model under test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from brdfdata.directions import spherical_to_vector
from brdfdata.samples import write_samples
from fitting.fit import FitOptions
from fitting.texels import texel_fit_options
from simulator.scene import load_scene
from simulator.texture import texel_direct_samples
from tests.support.paths import REPO

DASK = str(Path(sys.executable).with_name("dask"))
# What a gonioreflectometer pose set gives every texel: 3 incidence × 4 view × 3 azimuth
# differences, each texel seeing them ≈ 1° off (its own position on the sample at a finite
# distance), so no two texels share exact directions.
POSES_DEG = [(ti, to, dp) for ti in (15, 35, 55) for to in (0, 20, 40, 60) for dp in (180, 135, 90)]


def textured_material(texels: int):
    scene = load_scene(REPO / "configs" / "scenes" / "textured.toml")
    return scene.material.model_copy(update={"texels": texels})


def texel_samples(path: Path, texels: int, seed: int = 1):
    """Write per-texel samples of a `texels` × `texels` textured sample to `path`; returns
    the material (its truth: simulator.texture.texel_truth)."""
    material = textured_material(texels)
    rng = np.random.default_rng(seed)
    n = texels * texels
    tex = np.repeat(np.arange(n), len(POSES_DEG))
    deg = np.tile(np.array(POSES_DEG, dtype=float), (n, 1)) + rng.normal(0, 1.0, (n * 36, 3))
    ti, to, dphi = np.radians(deg).T
    wi = spherical_to_vector(ti, np.zeros_like(ti))
    wo = spherical_to_vector(to, dphi)
    table, _ = texel_direct_samples(material, wi, wo, tex, rng=rng)
    write_samples(path, table)
    return material


def fit_options(steps: int = 400) -> FitOptions:
    """The model Mitsuba renders (Lambert + Beckmann lobe, F ≡ 1, Smith G1 rational: the demo's
    match, gonio.pipeline.demo_fit_options) with ks and m shared by the channels (the texture's
    lobe is white); no discrepancy term (the model is exact for these data)."""
    base = FitOptions(
        model="torrance-sparrow",
        model_options={"fresnel": "none", "shadowing": "smith-rational"},
        shared=("m", "ks"),
        discrepancy=False,
        seed=3,
    )
    return texel_fit_options(base, steps=steps)


class ProcessCluster:
    """`dask scheduler` and `dask worker` processes on localhost (no nanny: killing a worker
    kills it, nothing restarts it)."""

    def __init__(self, folder: Path, workers: int = 2) -> None:
        self.file = folder / "scheduler.json"
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        log = open(folder / "dask.log", "ab")  # closed in stop()
        self._log = log
        self.scheduler = subprocess.Popen(
            [
                DASK,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(self.file),
            ],
            stdout=log,
            stderr=log,
            env=env,
            cwd=folder,
        )
        deadline = time.monotonic() + 60
        while not self.file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        self.address = json.loads(self.file.read_text())["address"]
        self._env = env
        self.workers: list[subprocess.Popen] = []
        for _ in range(workers):
            self.add_worker()
        self.wait_workers(workers)

    def add_worker(self) -> subprocess.Popen:
        k = len(self.workers)
        cmd = [DASK, "worker", self.address, "--nthreads", "1", "--no-nanny"]
        cmd += ["--no-dashboard", "--name", f"w{k}"]
        proc = subprocess.Popen(
            cmd, stdout=self._log, stderr=self._log, env=self._env, cwd=self.file.parent
        )
        self.workers.append(proc)
        return proc

    def alive(self) -> list[subprocess.Popen]:
        return [p for p in self.workers if p.poll() is None]

    def wait_workers(self, n: int, timeout_s: float = 60) -> None:
        from distributed import Client

        with Client(self.address, timeout="20s") as c:
            c.wait_for_workers(n, timeout=timeout_s)

    def stop(self) -> None:
        # A short grace, then SIGKILL: a worker's graceful close can wait ~20 s on heartbeats.
        for p in [*self.workers, self.scheduler]:
            if p.poll() is None:
                p.terminate()
        for p in [*self.workers, self.scheduler]:
            try:
                p.wait(timeout=3)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self._log.close()
