"""Unit and range guards every source of samples passes through (docs/design.md §3, §4): the samples
loader (:func:`brdfdata.samples.read_samples`) and every importer call :func:`check_samples`.

A table is refused — :class:`GuardError`, one line naming the source, the column, the count and
the fix; the CLI exits 2 — when, on the rows a fit takes as measured values (no excluding or
censoring flag, :data:`brdfdata.samples.table.FLAG_ROLES`; excluded and censored rows may hold
anything):

1. an angle column looks like degrees: most θ exceed π/2, or most |φ| exceed 2π;
2. θ lies outside [0, π] (not a polar angle at all);
3. θ lies in (π/2, π]: the direction is below the horizon, where f_r is 0 by convention;
4. σ ≤ 0 or σ, f or an angle is not finite;
5. f lies further below zero than any noise explains: f < −z_max·σ, with z_max the larger of
   ``NEGATIVE_Z_MIN`` = 5 and the one-sided normal quantile at 1 − 10⁻³/n for n such rows, so
   that an honest table of n Gaussian values trips it with probability ≤ 10⁻³ (a million rows:
   z_max ≈ 6.0). A value below zero *within* its noise is a measurement: a dark part after dark
   subtraction has many, and deleting them (or flagging only them dark) keeps the high draws
   and biases the fit high: kd +3.1 posterior sd on the dark table of
   tests/fitting/test_negative_values.py, +25 % on the larger one of issue 43's audit. Far
   below zero is a sign or offset error;
6. two rows share (θ_i, φ_i, θ_o, φ_o, channel) exactly — and, when the table has a
   ``capture_id`` column, the capture too: two captures of the same pose are repeated
   measurements, which a likelihood may use as they are, while the same row twice (a table
   concatenated with itself, an export run twice) counts its information double — unless
   ``merge_duplicates``, which
   replaces each group by one sample with the inverse-variance mean f = Σ(f/σ²)/Σ(1/σ²) and the
   combined σ = (Σ 1/σ²)^(−1/2). For a Gaussian likelihood that sample carries exactly the
   information of the group, so fits of the merged table equal fits of the group;
7. |f| or σ exceeds ``F_MAX_SR`` = 10⁸ sr⁻¹, beyond any measured BRDF: a unit or format error.

Tolerance: θ may exceed π/2 (or fall below 0) by ``ANGLE_SLACK_RAD`` = 1e-9 rad, room for the
rounding of an angle computed from a unit vector (≈1e-16 rad) with a wide margin, far below any
real pointing error.
"""

from __future__ import annotations

from statistics import NormalDist

import numpy as np

from brdfdata.samples.table import CENSORING, EXCLUDING, SamplesError, SampleTable

__all__ = [
    "GuardError",
    "ANGLE_SLACK_RAD",
    "NEGATIVE_Z_MIN",
    "check_samples",
    "merge_duplicates",
    "negative_limit_z",
]

ANGLE_SLACK_RAD = 1e-9
#: The largest |f| or σ a measured row may hold (guard 7): a mirror-like peak seen through a
#: lamp of a few mm at half a metre reads ~10³–10⁴ sr⁻¹; 10⁸ leaves four orders of margin and
#: keeps f² and the χ² sums far from overflow (1e308 was fitted).
F_MAX_SR = 1e8
NEGATIVE_Z_MIN = 5.0


def negative_limit_z(n: int) -> float:
    """z_max for ``n`` measured rows (module docstring, rule 5)."""
    # the standard library's normal quantile (Wichura's AS241, ~1e-16): importing scipy here
    # would cost every command that reads a samples file 0.1 s
    return max(NEGATIVE_Z_MIN, -NormalDist().inv_cdf(1e-3 / max(int(n), 1)))


_KEYS = ("theta_i", "phi_i", "theta_o", "phi_o")


class GuardError(SamplesError):
    """A samples table fails a unit or range guard (module docstring). One line."""


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_units(t: SampleTable, source: str) -> None:
    for name in ("theta_i", "theta_o"):
        v = getattr(t, name)
        v = v[np.isfinite(v)]
        big = int(np.sum(v > np.pi / 2 + ANGLE_SLACK_RAD))
        if v.size and big > v.size / 2:
            raise GuardError(
                f"{source}: column {name}: {big} of {v.size} values exceed π/2 (max {v.max():.4g})"
                " — looks like degrees; convert to radians (gonio import csv FILE --angles deg)"
            )
    for name in ("phi_i", "phi_o"):
        v = np.abs(getattr(t, name))
        v = v[np.isfinite(v)]
        big = int(np.sum(v > 2 * np.pi + ANGLE_SLACK_RAD))
        if v.size and big > v.size / 2:
            raise GuardError(
                f"{source}: column {name}: {big} of {v.size} values exceed 2π in magnitude "
                f"(max {v.max():.4g}) — looks like degrees; convert to radians "
                "(gonio import csv FILE --angles deg)"
            )


def _measured(t: SampleTable) -> np.ndarray:
    """Rows a fit takes as values: no excluding or censoring flag (FLAG_ROLES)."""
    return (np.asarray(t.flags, np.int64) & (EXCLUDING | CENSORING)) == 0


def _check_good_rows(t: SampleTable, source: str) -> None:
    good = _measured(t)
    for name in ("theta_i", "theta_o"):
        v = getattr(t, name)
        out = good & np.isfinite(v) & ((v < -ANGLE_SLACK_RAD) | (v > np.pi + ANGLE_SLACK_RAD))
        if out.any():
            raise GuardError(
                f"{source}: column {name}: {int(out.sum())} row(s) outside [0, π/2] rad "
                f"(first: row {_first(out)}, {v[_first(out)]:.6g}); a polar angle lies in [0, π/2]"
                " — fix the column or set those rows' flags"
            )
        below = good & (v > np.pi / 2 + ANGLE_SLACK_RAD)
        if below.any():
            raise GuardError(
                f"{source}: column {name}: {int(below.sum())} row(s) below the horizon "
                f"(θ > π/2; first: row {_first(below)}) with flags = 0; drop them or set flags "
                "bit 4 (below horizon)"
            )
    for name in ("f", "sigma", *_KEYS):
        bad = good & ~np.isfinite(getattr(t, name))
        if bad.any():
            raise GuardError(
                f"{source}: column {name}: {int(bad.sum())} row(s) with NaN or inf (first: row "
                f"{_first(bad)}) and flags = 0; drop them or set their flags (e.g. 8 = masked)"
            )
    for name in ("f", "sigma"):
        v = getattr(t, name)
        huge = good & (np.abs(v) > F_MAX_SR)
        if huge.any():
            i = _first(huge)
            raise GuardError(
                f"{source}: column {name}: {int(huge.sum())} row(s) beyond ±{F_MAX_SR:.0e} sr^-1 "
                f"(first: row {i}, {v[i]:.4g}), more than any measured BRDF holds: a unit or "
                "format error; fix the column or set those rows' flags (e.g. 8 = masked)"
            )
    bad = good & ~(t.sigma > 0)
    if bad.any():
        raise GuardError(
            f"{source}: column sigma: {int(bad.sum())} row(s) with σ ≤ 0 (first: row "
            f"{_first(bad)}) and flags = 0; give each sample a positive 1-σ uncertainty in sr^-1"
            " (or import with --sigma rel=0.02)"
        )
    z_max = negative_limit_z(int(good.sum()))
    neg = good & (t.f < -z_max * t.sigma)
    if neg.any():
        i = _first(neg)
        raise GuardError(
            f"{source}: column f: {int(neg.sum())} row(s) more than {z_max:.2g}σ below zero "
            f"(first: row {i}, f = {t.f[i]:.4g}, σ = {t.sigma[i]:.3g}), which no noise explains:"
            " a sign or offset error (dark subtraction?), or σ too small near zero; fix f or σ, "
            "or set flags bit 8 (masked) on rows that were not measured"
        )


def _duplicate_groups(t: SampleTable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices of good rows, group id per such row, group sizes).

    Rows are grouped by one lexicographic sort of the key columns (an int64 permutation, one
    sorted key column at a time) rather than ``np.unique(axis=0)`` of their n × 6 stack, which
    held several copies of it (issue 23: 0.44 KB per row at the read's peak). Angles compare as
    numbers, so −0.0 and 0.0 are one key."""
    idx = np.flatnonzero(_measured(t))
    every = idx.size == len(t)  # the usual table: no row flagged, so no column is copied

    def good(a: np.ndarray) -> np.ndarray:
        return a if every else a[idx]

    _, chan = np.unique(good(t.channel), return_inverse=True)
    keys = [*(good(getattr(t, k)) for k in _KEYS), chan.ravel()]
    if "capture_id" in t.extra:  # different captures of one pose are not duplicates
        keys.append(good(np.asarray(t.extra["capture_id"])))
    order = np.lexsort(keys[::-1])  # the last key is lexsort's primary one
    starts = np.zeros(idx.size, bool)
    starts[:1] = True
    for key in keys:
        ranked = key[order]
        starts[1:] |= ranked[1:] != ranked[:-1]
    group = np.empty(idx.size, np.int64)
    group[order] = np.cumsum(starts) - 1
    return idx, group, np.diff(np.append(np.flatnonzero(starts), idx.size))


def merge_duplicates(t: SampleTable) -> tuple[SampleTable, int]:
    """Each group of good rows sharing (θ_i, φ_i, θ_o, φ_o, channel) → one row (module docstring;
    other columns from the group's first row). Returns the table and the rows removed."""
    idx, group, counts = _duplicate_groups(t)
    if not np.any(counts > 1):
        return t, 0
    w = 1.0 / np.square(t.sigma[idx])
    w_sum = np.bincount(group, weights=w)
    f_mean = np.bincount(group, weights=w * t.f[idx]) / w_sum
    first = np.full(counts.size, idx.size, np.int64)
    np.minimum.at(first, group, np.arange(idx.size))
    keep_rows = idx[first]  # one representative (the first) row per group
    keep = np.zeros(len(t), bool)
    keep[keep_rows] = True
    merged = t.select(keep)  # copies, in table order
    pos = np.searchsorted(np.sort(keep_rows), keep_rows)  # group g's row in `merged`
    merged.f[pos] = f_mean
    merged.sigma[pos] = 1.0 / np.sqrt(w_sum)
    flagged = t.select(~_measured(t))
    out = _concat(merged, flagged)
    removed = len(t) - len(out)
    out.metadata["gonio.merged_duplicates"] = str(removed)
    return out, removed


def _concat(a: SampleTable, b: SampleTable) -> SampleTable:
    if len(b) == 0:
        return a
    cat = {k: np.concatenate([getattr(a, k), getattr(b, k)]) for k in (*_KEYS, "f", "sigma")}
    return SampleTable(
        **cat,
        channel=np.concatenate([a.channel, b.channel]),
        flags=np.concatenate([a.flags, b.flags]),
        extra={k: np.concatenate([a.extra[k], b.extra[k]]) for k in a.extra if k in b.extra},
        metadata=dict(a.metadata),
    )


def check_samples(
    table: SampleTable, source: str, *, merge_duplicates_rows: bool = False
) -> SampleTable:
    """Run the guards (module docstring) on ``table`` read from ``source`` (a path or a name for
    messages). Returns the table — with duplicates merged when ``merge_duplicates_rows`` —
    or raises GuardError."""
    _check_units(table, source)
    _check_good_rows(table, source)
    if merge_duplicates_rows:
        return merge_duplicates(table)[0]
    idx, group, counts = _duplicate_groups(table)
    dup = counts[group] > 1
    if dup.any():
        n_groups = int(np.sum(counts > 1))
        key = "channel, capture_id" if "capture_id" in table.extra else "channel"
        raise GuardError(
            f"{source}: {int(dup.sum())} row(s) in {n_groups} group(s) repeat the same (theta_i, "
            f"phi_i, theta_o, phi_o, {key}) (first: row {int(idx[dup][0])}); merge them into "
            "one sample each with --merge-duplicates, or drop the repeats"
        )
    return table
