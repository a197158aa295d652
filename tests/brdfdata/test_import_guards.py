"""Unit and range guards at load, for every source (issue 16, item 2): a CSV through
`gonio import csv`, a Parquet table written by someone else's pyarrow through `gonio fit`. Each
mistake is one line naming the column, the count and the fix, exit 2; `--merge-duplicates`
turns each group of repeated rows into one sample with the combined σ.

Ground truth for the merge: under a Gaussian likelihood, measurements f_k ± σ_k of one quantity
carry exactly the information of one measurement at the inverse-variance mean
Σ(f_k/σ_k²)/Σ(1/σ_k²) with σ = (Σ 1/σ_k²)^(−1/2) — the log-likelihoods differ by a constant —
so a fit of the merged table must give the intervals of a fit of the duplicated table itself
(fitted in memory, bypassing the guard) and of the de-duplicated table built by hand here.
"""

from __future__ import annotations

import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from brdfdata.formats.common import FormatError, SigmaRule
from brdfdata.formats.csv_table import CsvOptions, read_csv_table, write_csv_table
from brdfdata.samples import Flags, SampleTable, read_samples
from brdfdata.samples.guards import GuardError, check_samples
from fitting.fit import FitOptions, fit_samples

KD = 0.73  # the table's true albedo


def _lambert_rows(n=120, seed=0):
    rng = np.random.default_rng(seed)
    ti = rng.uniform(0, 1.3, n)
    to = rng.uniform(0, 1.3, n)
    po = rng.uniform(0, 2 * np.pi, n)
    sigma = np.full(n, 0.01)
    f = KD / np.pi + sigma * rng.standard_normal(n)
    return {"theta_i": ti, "phi_i": np.zeros(n), "theta_o": to, "phi_o": po, "f": f, "sigma": sigma}


def _write_csv(path, cols, deg=False):
    names = list(cols)
    conv = {
        k: (np.degrees(v) if deg and k.startswith(("theta", "phi")) else v) for k, v in cols.items()
    }
    lines = [",".join(names)]
    for i in range(len(cols["f"])):
        lines.append(",".join(repr(float(conv[k][i])) for k in names))
    path.write_text("\n".join(lines) + "\n")
    return path


def _write_parquet(path, cols):
    arrays = {k: pa.array(v) for k, v in cols.items()}
    arrays["channel"] = pa.array(["Y"] * len(cols["f"]))
    pq.write_table(pa.table(arrays), path)
    return path


def _run(monkeypatch, capsys, *args):
    from gonio import cli

    monkeypatch.setattr(sys, "argv", ["gonio", *map(str, args)])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr()


def _one_line(io) -> str:
    lines = [ln for ln in io.err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in io.err, io.err
    return lines[0]


CASES = {
    # name: (edit of the rows, expected fragments of the one line)
    "degrees": (lambda c: c, ["theta_", "exceed π/2", "looks like degrees", "--angles deg"]),
    "sigma_zero": (
        lambda c: {**c, "sigma": np.where(np.arange(c["f"].size) % 10 == 3, 0.0, c["sigma"])},
        ["column sigma", "12 row(s)", "σ ≤ 0", "first: row 3", "--sigma rel="],
    ),
    "below_horizon": (
        lambda c: {**c, "theta_o": np.where(np.arange(c["f"].size) < 5, 1.7, c["theta_o"])},
        ["column theta_o", "5 row(s) below the horizon", "flags bit 4"],
    ),
    "duplicates": (
        lambda c: {k: np.concatenate([v, v[:7]]) for k, v in c.items()},
        ["14 row(s) in 7 group(s)", "--merge-duplicates"],
    ),
    # σ = 0.01: −0.06 is 6σ below zero, beyond z_max = 5 for 120 rows (guards module
    # docstring); a value within its noise below zero is data (test_negative_within_noise_*)
    "negative_f": (
        lambda c: {**c, "f": np.where(np.arange(c["f"].size) == 8, -0.06, c["f"])},
        ["column f", "1 row(s) more than 5σ below zero", "first: row 8", "sign or offset"],
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_mistake_is_one_line_exit_2_from_every_source(case, tmp_path, monkeypatch, capsys):
    edit, fragments = CASES[case]
    cols = edit(_lambert_rows())
    csv = _write_csv(tmp_path / "t.csv", cols, deg=case == "degrees")
    code, io = _run(monkeypatch, capsys, "import", "csv", csv, "--out", tmp_path / "s.parquet")
    line = _one_line(io)
    assert code == 2 and str(csv) in line and all(f in line for f in fragments), line
    assert not (tmp_path / "s.parquet").exists()
    # The same table as Parquet from another tool: refused by `gonio fit` the same way.
    if case == "degrees":
        cols = {
            k: (np.degrees(v) if k.startswith(("theta", "phi")) else v) for k, v in cols.items()
        }
    parquet = _write_parquet(tmp_path / "other.parquet", cols)
    code, io = _run(monkeypatch, capsys, "fit", parquet, "--model", "lambert", "--no-mcmc")
    line = _one_line(io)
    assert code == 2 and str(parquet) in line and all(f in line for f in fragments), line


def test_degrees_accepted_with_angles_deg(tmp_path) -> None:
    """The reason for the guard: fitted silently, a degrees table gives a wrong kd."""
    cols = _lambert_rows(n=400, seed=3)
    csv = _write_csv(tmp_path / "deg.csv", cols, deg=True)
    table = read_csv_table(csv, CsvOptions(angles="deg"))
    np.testing.assert_allclose(table.theta_o, cols["theta_o"], rtol=1e-15)
    fit = fit_samples(
        check_samples(table, "deg.csv"), FitOptions(model="lambert", mcmc=None, discrepancy=False)
    )
    assert abs(fit.parameters["kd_Y"]["median"] - KD) < 0.01
    with pytest.raises(GuardError, match="looks like degrees"):
        check_samples(read_csv_table(csv), "deg.csv")


def test_excluded_and_censored_rows_may_hold_anything(tmp_path) -> None:
    cols = _lambert_rows()
    cols["theta_o"][:3] = 1.9
    cols["sigma"][3:6] = 0.0
    cols["f"][6:9] = -1.0
    flags = np.zeros(cols["f"].size, np.int32)
    flags[:3], flags[3:6], flags[6:9] = Flags.BELOW_HORIZON, Flags.DARK, Flags.MASKED
    path = _write_parquet(tmp_path / "t.parquet", {**cols, "flags": flags})
    table = read_samples(path)
    assert len(table) == cols["f"].size and len(table.good()) == cols["f"].size - 9


def test_negative_within_noise_is_data_and_flag_16_does_not_hide_an_error(tmp_path) -> None:
    """f < 0 within its σ passes unflagged and is fitted; flag 16 marks a row and keeps it, so
    a value no noise explains is refused with or without it (FLAG_ROLES: 16 is "keep")."""
    cols = _lambert_rows()
    cols["f"][:5] = -0.02  # 2σ below zero: an honest noisy value near a dark part
    table = read_samples(_write_parquet(tmp_path / "ok.parquet", cols))
    assert len(table.good()) == cols["f"].size
    cols["f"][5] = -1.0  # 100σ below zero
    flags = np.zeros(cols["f"].size, np.int32)
    flags[5] = Flags.NEGATIVE
    with pytest.raises(GuardError, match="1 row.*below zero.*first: row 5"):
        read_samples(_write_parquet(tmp_path / "bad.parquet", {**cols, "flags": flags}))


def _dedup_by_hand(cols, groups):
    """One row per direction: inverse-variance mean and combined σ (module docstring)."""
    out = {k: [] for k in cols}
    for idx in groups:
        w = 1 / cols["sigma"][idx] ** 2
        for k in ("theta_i", "phi_i", "theta_o", "phi_o"):
            out[k].append(cols[k][idx[0]])
        out["f"].append(np.sum(w * cols["f"][idx]) / np.sum(w))
        out["sigma"].append(1 / np.sqrt(np.sum(w)))
    return {k: np.asarray(v) for k, v in out.items()}


def _table(cols) -> SampleTable:
    n = cols["f"].size
    return SampleTable(
        cols["theta_i"], cols["phi_i"], cols["theta_o"], cols["phi_o"],
        np.full(n, "Y"), cols["f"], cols["sigma"], np.zeros(n, np.int32),
    )  # fmt: skip


def test_merge_duplicates_matches_the_deduplicated_table(tmp_path, monkeypatch, capsys) -> None:
    base = _lambert_rows(n=150, seed=7)
    rng = np.random.default_rng(8)
    # Rows 0–39 measured three times (different values and σ), the rest once.
    reps = {k: np.concatenate([v, v[:40], v[:40]]) for k, v in base.items()}
    n_rep = reps["f"].size
    reps["sigma"] = rng.uniform(0.005, 0.03, n_rep)
    reps["f"] = KD / np.pi + reps["sigma"] * rng.standard_normal(n_rep)
    groups = [np.array([i, 150 + i, 190 + i]) for i in range(40)]
    groups += [np.array([i]) for i in range(40, 150)]
    csv = _write_csv(tmp_path / "rep.csv", reps)
    code, io = _run(monkeypatch, capsys, "import", "csv", csv, "--out", tmp_path / "s.parquet")
    assert code == 2 and "--merge-duplicates" in _one_line(io)
    code, _ = _run(
        monkeypatch,
        capsys,
        "import",
        "csv",
        csv,
        "--merge-duplicates",
        "--out",
        tmp_path / "m.parquet",
    )
    assert code == 0
    merged = read_samples(tmp_path / "m.parquet")
    assert len(merged) == 150 and merged.metadata["gonio.merged_duplicates"] == "80"
    by_hand = _table(_dedup_by_hand(reps, groups))

    def intervals(table):
        # Plain least squares (loss "linear"): the Gaussian likelihood the equivalence is about;
        # the default soft_l1 loss down-weights large residuals and is not additive that way.
        fit = fit_samples(
            table, FitOptions(model="lambert", mcmc=None, discrepancy=False, loss="linear", seed=1)
        )
        p = fit.parameters["kd_Y"]
        return np.array([p["map"], p["p2.5"], p["p16"], p["median"], p["p84"], p["p97.5"]])

    a, b, c = intervals(merged), intervals(by_hand), intervals(_table(reps))
    # Merged vs by hand: the same numbers up to the order of float sums (~1e-16 relative).
    np.testing.assert_allclose(a, b, rtol=1e-12)
    # Merged vs the duplicated rows themselves: the same likelihood up to a constant, so the
    # same optimum and curvature; only least squares' stopping tolerance (1e-8 relative in
    # the parameters, fitting.lsq) separates them.
    np.testing.assert_allclose(a, c, rtol=1e-6)


def test_sigma_from_repeats_and_wide_layout(tmp_path) -> None:
    rng = np.random.default_rng(4)
    n, k = 30, 4
    ti, to, po = rng.uniform(0, 1.2, n), rng.uniform(0, 1.2, n), rng.uniform(0, 6, n)
    rows = ["ti,to,po,red,green"]
    vals = rng.uniform(0.1, 0.3, (k, n, 2))
    for r in range(k):
        for i in range(n):
            rows.append(",".join(repr(float(x)) for x in (ti[i], to[i], po[i], *vals[r, i])))
    path = tmp_path / "wide.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(FormatError, match="no column 'phi_i'.*--column phi_i=YOUR_COLUMN"):
        read_csv_table(path, CsvOptions(columns={"theta_i": "ti"}))
    opts = CsvOptions(
        # φ_i: any column of zeros would do; reuse θ_i's to keep the file small (φ is free).
        columns={"theta_i": "ti", "theta_o": "to", "phi_o": "po", "phi_i": "ti"},
        values={"R": "red", "G": "green"},
        sigma=SigmaRule("repeats"),
    )
    table = read_csv_table(path, opts)
    assert len(table) == 2 * n and table.channels == ["R", "G"]
    for c, name in enumerate("RG"):
        m = table.channel == name
        order = np.argsort(table.theta_i[m])
        src = np.argsort(ti)
        np.testing.assert_allclose(table.f[m][order], vals[:, src, c].mean(axis=0), rtol=1e-14)
        want = vals[:, src, c].std(axis=0, ddof=1) / np.sqrt(k)
        np.testing.assert_allclose(table.sigma[m][order], want, rtol=1e-12)


def test_csv_write_read_round_trip_is_exact(tmp_path) -> None:
    cols = _lambert_rows(n=50, seed=9)
    table = _table(cols)
    table.flags[:4] = Flags.DARK
    write_csv_table(tmp_path / "t.csv", table)
    back = read_csv_table(tmp_path / "t.csv")
    for k in ("theta_i", "phi_i", "theta_o", "phi_o", "f", "sigma"):
        assert np.array_equal(getattr(back, k), getattr(table, k)), k
    assert (
        np.array_equal(back.flags, table.flags) and back.channel.tolist() == table.channel.tolist()
    )


def test_two_captures_of_one_pose_are_not_duplicates() -> None:
    cols = _lambert_rows(n=20)
    twice = {k: np.concatenate([v, v]) for k, v in cols.items()}
    table = _table(twice)
    with pytest.raises(GuardError, match="20 group"):
        check_samples(table, "t")
    table.extra["capture_id"] = np.repeat([1, 2], 20)
    assert len(check_samples(table, "t")) == 40


def test_duplicate_groups_are_the_partition_of_equal_keys() -> None:
    """The grouping (one lexicographic sort) against an independent one: numpy's unique rows of
    the stacked keys, on a table with planted repeats (angles, channel and capture each shared
    with another row while a single other key differs) and flagged rows left out."""
    from brdfdata.samples.guards import _duplicate_groups

    rng = np.random.default_rng(3)
    n = 600
    base = {k: rng.choice(rng.uniform(0, 1.2, 40), n) for k in ("theta_i", "theta_o")}
    cols = {
        **base,
        "phi_i": rng.choice([0.0, 0.5], n),
        "phi_o": rng.choice([0.0, 1.0, 2.0], n),
        "f": rng.uniform(0.1, 0.2, n),
        "sigma": np.full(n, 0.01),
    }
    table = _table(cols)
    table.channel = rng.choice(np.array(["R", "G"]), n)
    table.extra["capture_id"] = rng.integers(0, 3, n)
    table.flags[rng.choice(n, 50, replace=False)] = int(Flags.SATURATED)
    idx, group, counts = _duplicate_groups(table)
    assert np.array_equal(idx, np.flatnonzero(table.flags == 0))
    keys = np.stack(
        [
            *(getattr(table, k)[idx] for k in ("theta_i", "phi_i", "theta_o", "phi_o")),
            (table.channel[idx] == "R").astype(float),
            table.extra["capture_id"][idx].astype(float),
        ],
        axis=1,
    )
    _, ref, ref_counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    ref = ref.ravel()
    # the same partition: each of our groups maps to exactly one of numpy's and back
    pairs = np.unique(np.stack([group, ref], axis=1), axis=0)
    assert pairs.shape[0] == counts.size == ref_counts.size
    assert np.array_equal(np.sort(counts), np.sort(ref_counts))
    assert np.array_equal(counts[group], ref_counts[ref])
    assert (counts > 1).any() and (counts == 1).any()  # the draw has repeats and singles
    # no row flagged (the columns are used without a copy), and an angle of −0.0 is 0.0
    table.flags[:] = 0
    table.phi_i[:2] = [0.0, -0.0]
    for k in ("theta_i", "theta_o", "phi_o"):
        getattr(table, k)[1] = getattr(table, k)[0]
    table.channel[1], table.extra["capture_id"][1] = table.channel[0], table.extra["capture_id"][0]
    idx, group, counts = _duplicate_groups(table)
    assert idx.size == n and group[0] == group[1] and counts[group[0]] >= 2
