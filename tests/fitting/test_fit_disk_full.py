"""Issue 22, "nothing poisons a run": a fit whose chain file meets a full disk.

Before, emcee's HDF backend wrote every step into fit-<model>.h5 in place; on a real full disk
HDF5 swallowed the write error in a destructor, the process died with a segmentation fault, and
the half-written file made every later fit into that folder fail ("not a readable MCMC chain").
Now the chain is saved whole and atomically (fitting.chain_file): the full disk is one line
naming the file, nothing partial is left, and the same command succeeds once space is freed.

The disk is real: a 64 KiB tmpfs mounted over the fit's output folder (tests/conftest.py
`tmpfs`; where mounting is not permitted the test says so and checks the in-process path only).
"""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import emcee
import numpy as np

from brdfdata.samples import SampleTable, write_samples
from fitting.chain_file import load_chain, save_chain


def _lambert_samples(path: Path) -> Path:
    """400 directions × 3 channels of a Lambertian surface with 1 % noise (the data's values do
    not matter here: only the files the fit writes)."""
    rng = np.random.default_rng(0)
    n = 400
    theta_i, theta_o = rng.uniform(0, 1.3, n), rng.uniform(0, 1.3, n)
    phi_o = rng.uniform(-3, 3, n)
    kd = np.repeat([0.5, 0.4, 0.3], n)
    sigma = 0.01 * kd / np.pi
    table = SampleTable(
        theta_i=np.tile(theta_i, 3),
        phi_i=np.zeros(3 * n),
        theta_o=np.tile(theta_o, 3),
        phi_o=np.tile(phi_o, 3),
        channel=np.repeat(np.array(["R", "G", "B"]), n),
        f=kd / np.pi + rng.normal(0, 1, 3 * n) * sigma,
        sigma=sigma,
        flags=np.zeros(3 * n, np.int32),
    )
    return write_samples(path, table)


def _fit(samples: Path, out: Path) -> subprocess.CompletedProcess:
    # 3000 steps × 32 walkers × 4 parameters ≈ 3 MB of chain: far beyond 64 KiB.
    args = ["fit", str(samples), "--model", "lambert", "--steps", "3000", "--out", str(out)]
    return subprocess.run(
        [sys.executable, "-m", "gonio.cli", *args, "--accept-poor-fit"],
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_full_disk_during_a_fit_leaves_nothing_and_the_fit_succeeds_after(tmp_path, tmpfs):
    samples = _lambert_samples(tmp_path / "samples.parquet")
    out = tmp_path / "fit"
    out.mkdir()
    grow = tmpfs(out, "64k")
    if grow is None:
        warnings.warn("mount not permitted: the full-disk fit is not exercised", stacklevel=1)
        return
    first = _fit(samples, out)
    # One line naming the file and the fix; exit 2 (a user-fixable condition), not a crash
    # (-11 / 139 before) nor an internal error.
    assert first.returncode == 2, first.stderr
    lines = first.stderr.strip().splitlines()
    assert lines == [lines[0]] and lines[0].startswith("error: ")
    assert "fit-lambert.h5" in lines[0] and "No space left on device" in lines[0]
    assert sorted(p.name for p in out.iterdir()) == []  # no chain, no temp file, no JSON
    grow()  # the operator frees space; the same command now works
    second = _fit(samples, out)
    assert second.returncode == 0, second.stderr
    assert {"fit-lambert.h5", "fit-lambert.json", "material-lambert.xml"} <= {
        p.name for p in out.iterdir()
    }
    assert emcee.backends.HDFBackend(str(out / "fit-lambert.h5"), read_only=True).iteration > 0


def test_chain_file_round_trip_keeps_other_ensembles(tmp_path):
    """save_chain replaces one group and keeps the others; load_chain gives back exactly what
    was saved (chain, log_prob, acceptance, random state, fingerprint), and emcee's own reader
    reads the file."""
    path = tmp_path / "chain.h5"
    rng = np.random.default_rng(1)
    backends = []
    for name, steps in (("mcmc", 5), ("mcmc_1", 7)):
        b = emcee.backends.Backend()
        b.reset(6, 2)
        b.grow(steps, None)
        b.chain[:] = rng.normal(size=b.chain.shape)
        b.log_prob[:] = rng.normal(size=b.log_prob.shape)
        b.accepted[:] = rng.integers(0, steps, 6)
        b.random_state = np.random.RandomState(3).get_state()
        b.iteration = steps
        save_chain(path, name, b, f"fp-{name}")
        backends.append(b)
    for name, b in zip(("mcmc", "mcmc_1"), backends, strict=True):
        loaded, fingerprint = load_chain(path, name)
        assert fingerprint == f"fp-{name}" and loaded.iteration == b.iteration
        np.testing.assert_array_equal(loaded.chain, b.chain)
        np.testing.assert_array_equal(loaded.log_prob, b.log_prob)
        np.testing.assert_array_equal(loaded.accepted, b.accepted)
        assert loaded.random_state[0] == "MT19937"
        np.testing.assert_array_equal(loaded.random_state[1], b.random_state[1])
        theirs = emcee.backends.HDFBackend(str(path), name=name, read_only=True)
        np.testing.assert_array_equal(theirs.get_chain(), b.chain)
    assert load_chain(path, "mcmc_2") is None
    assert not [p for p in tmp_path.iterdir() if p.name != "chain.h5"]  # no temp left
