"""`gonio import merl` / `gonio export merl`: the MERL ``.binary`` layout and lookup of
Matusik et al. 2003 (BRDFRead.cpp), checked against an independent lookup written here from the
format's description (rotation matrices and arccos, not brdfdata.rusinkiewicz's atan2 form), and
a write → read round trip of an analytic model.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from brdfdata.directions import spherical_to_vector
from brdfdata.formats.common import FormatError
from brdfdata.formats.convert import ImportOptions, import_samples
from brdfdata.formats.merl import DIMS, SCALES, MerlTable, read_merl, write_merl
from brdfdata.rusinkiewicz import from_half_diff
from fitting.export import export_fit, fit_evaluator
from tests.support.fits import fit_json

N_BINS = DIMS[0] * DIMS[1] * DIMS[2]


def _independent_lookup(raw: np.ndarray, wi: np.ndarray, wo: np.ndarray):
    """BRDFRead.cpp's lookup_brdf_val from the published description: half vector h, the
    difference vector d = R_y(−θ_h) R_z(−φ_h) ω_i, indices θ_h: ⌊√(θ_h/(π/2))·90⌋,
    θ_d: ⌊θ_d/(π/2)·90⌋, φ_d: ⌊φ_d/π·180⌋ with φ_d < 0 → φ_d + π; f = raw·scale.
    Returns f (N, 3) and the continuous indices (to spot bin-edge cases)."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    theta_h = np.arccos(np.clip(h[:, 2], -1, 1))
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    cz, sz = np.cos(-phi_h), np.sin(-phi_h)
    cy, sy = np.cos(-theta_h), np.sin(-theta_h)
    rz = np.zeros((len(h), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = cz, -sz, sz, cz, 1
    ry = np.zeros((len(h), 3, 3))
    ry[:, 0, 0], ry[:, 0, 2], ry[:, 1, 1], ry[:, 2, 0], ry[:, 2, 2] = cy, sy, 1, -sy, cy
    d = np.einsum("nij,njk,nk->ni", ry, rz, wi)
    theta_d = np.arccos(np.clip(d[:, 2], -1, 1))
    phi_d = np.arctan2(d[:, 1], d[:, 0])
    phi_d = np.where(phi_d < 0, phi_d + np.pi, phi_d)
    cont = np.stack(
        [np.sqrt(theta_h / (np.pi / 2) * 90 * 90), theta_d / (np.pi / 2) * 90, phi_d / np.pi * 180],
        axis=1,
    )
    idx = np.minimum(np.floor(cont).astype(int), np.array(DIMS) - 1)
    f = np.stack([raw[c][idx[:, 0], idx[:, 1], idx[:, 2]] * SCALES[c] for c in range(3)], axis=1)
    return f, cont


def _dirs(rng, n):
    ct = rng.uniform(0.02, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct**2)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=1)


def test_lookup_agrees_with_an_independent_implementation() -> None:
    rng = np.random.default_rng(11)
    raw = rng.uniform(0.0, 3000.0, (3, *DIMS))  # every bin different: an index error shows
    table = MerlTable(raw=raw)
    wi, wo = _dirs(rng, 200_000), _dirs(rng, 200_000)
    ours = table.lookup(wi, wo)
    ref, cont = _independent_lookup(raw, wi, wo)
    differ = np.any(ours != ref, axis=1)
    # Two float paths to the same angles can only disagree on a bin edge (arccos vs atan2
    # rounding, ~1e-12 in index units here).
    edge = np.min(np.abs(cont - np.round(cont)), axis=1) < 1e-9
    assert np.all(edge[differ]), int((differ & ~edge).sum())
    assert differ.mean() < 1e-4


def test_export_then_import_reproduces_the_model(tmp_path) -> None:
    fit = fit_json(tmp_path)
    out, what = export_fit("merl", tmp_path / "fit-torrance-sparrow.json", tmp_path / "m.binary")
    assert out.stat().st_size == 12 + 3 * N_BINS * 8 and "bin centres" in what
    table = import_samples("merl", out, ImportOptions())
    n = len(table) // 3
    assert set(table.channels) == {"R", "G", "B"} and n > 1_000_000
    # Rows follow the bins in file order; a bin's direction is its centre (module docstring of
    # brdfdata.formats.merl), built here from the index-space centres.
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(d) for d in DIMS), indexing="ij"))
    wi_c, wo_c = from_half_diff(
        ((i + 0.5) / 90) ** 2 * np.pi / 2, (j + 0.5) / 90 * np.pi / 2, (k + 0.5) / 180 * np.pi
    )
    up = (wi_c[:, 2] > 0) & (wo_c[:, 2] > 0)
    assert up.sum() == n
    want = fit_evaluator(fit)(wi_c[up], wo_c[up])
    got = table.f.reshape(3, n).T
    # f/scale on export, ·scale on import: two float64 roundings, ≤ 2 × 2^-53 relative.
    assert np.max(np.abs(got - want) / want) <= 2 * 2.0**-53 * 1.01
    # The stored angles give back those directions to float64 rounding (a few ulp).
    wi = spherical_to_vector(table.theta_i[:n], table.phi_i[:n])
    wo = spherical_to_vector(table.theta_o[:n], table.phi_o[:n])
    assert np.max(np.abs(wi - wi_c[up])) < 1e-15 and np.max(np.abs(wo - wo_c[up])) < 1e-15
    # The file itself: read → write is byte-identical.
    write_merl(tmp_path / "again.binary", read_merl(out))
    assert (tmp_path / "again.binary").read_bytes() == out.read_bytes()


def test_invalid_bins_are_dropped_and_counted(tmp_path) -> None:
    rng = np.random.default_rng(2)
    raw = rng.uniform(1.0, 100.0, (3, *DIMS))
    bad = [(10, 20, 30), (50, 5, 100), (1, 1, 1)]  # bins whose centres are above the horizon
    for i, j, k in bad:
        raw[:, i, j, k] = -1.0
    raw[1, 2, 2, 2] = -1.0  # one channel only
    write_merl(tmp_path / "x.binary", MerlTable(raw=raw))
    table = import_samples("merl", tmp_path / "x.binary", ImportOptions())
    meta = json.loads(table.metadata["gonio.source.conversion"])
    assert meta["invalid_dropped"] == 3 * len(bad) + 1
    assert np.all(table.f > 0) and table.metadata["gonio.source.format"] == "merl"


def test_a_merl_file_of_absurd_values_is_refused_in_one_line(tmp_path) -> None:
    """Issue 47: a MERL file whose values are 1e300 became 3.3 M rows of a table any fit would
    overflow on. Guard 7 (|f| ≤ 10⁸ sr⁻¹, brdfdata.samples.guards) refuses it, naming the file."""
    from brdfdata.samples.guards import GuardError

    write_merl(tmp_path / "absurd.binary", MerlTable(raw=np.full((3, *DIMS), 1e300)))
    with pytest.raises(GuardError, match=r"column f: .* beyond ±1e\+08 sr\^-1") as exc:
        import_samples("merl", tmp_path / "absurd.binary", ImportOptions())
    assert "absurd.binary" in str(exc.value) and "\n" not in str(exc.value)


def test_not_a_merl_file(tmp_path) -> None:
    p = tmp_path / "x.binary"
    p.write_bytes(np.array([90, 90, 90], "<i4").tobytes() + b"\0" * 64)
    with pytest.raises(FormatError, match=r"header dims \(90, 90, 90\)"):
        read_merl(p)
    p.write_bytes(np.array(DIMS, "<i4").tobytes() + b"\0" * 64)
    with pytest.raises(FormatError, match="truncated"):
        read_merl(p)


def test_cli_round_trip_and_one_line_errors(tmp_path, monkeypatch, capsys) -> None:
    from gonio import cli

    fit_json(tmp_path)

    def run(*args):
        monkeypatch.setattr(sys, "argv", ["gonio", *map(str, args)])
        try:
            cli.main()
            code = 0
        except SystemExit as exc:
            code = exc.code
        return code, capsys.readouterr()

    fit = tmp_path / "fit-torrance-sparrow.json"
    code, _ = run("export", "merl", fit, "--out", tmp_path / "m.binary")
    assert code == 0
    code, _ = run("import", "merl", tmp_path / "m.binary", "--out", tmp_path / "s.parquet")
    assert code == 0 and (tmp_path / "s.parquet").is_file()
    code, io = run("import", "merl", fit, "--out", tmp_path / "t.parquet")
    assert code == 2 and len(io.err.strip().splitlines()) == 1 and "MERL" in io.err
    code, io = run("import", "merl", tmp_path / "m.binary", "--angles", "deg", "--out", "x")
    assert code == 2 and "--angles" in io.err
