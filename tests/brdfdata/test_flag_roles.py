"""One meaning per flag bit (issue 43 item 6): brdfdata.samples.FLAG_ROLES is the table the
likelihood, the binned path, the report and the guards read, and docs/formats.md prints it.

Before this, bit 16 (a value published below zero) was kept by the likelihood, dropped by the
binned path and said in the docs to "never enter a fit": one table gave two answers.
"""

from __future__ import annotations

import re

import numpy as np

from brdfdata.samples import FLAG_ROLES, Flags, SampleTable, row_kinds
from fitting import models
from fitting.binning import BinOptions, bin_table
from fitting.likelihood import Likelihood
from fitting.priors import ParameterSpace
from tests.support.paths import REPO


def test_docs_print_the_flag_table() -> None:
    text = (REPO / "docs" / "formats.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| (\d+) \| ([^|]+) \| (\w+) \| ([^|]+) \|$", text, re.MULTILINE)
    printed = {int(b): (n.strip(), r, m.strip()) for b, n, r, m in rows}
    assert printed == FLAG_ROLES


def _table() -> SampleTable:
    """One row per flag value 0…31 (every combination of the five bits), distinct directions."""
    n = 32
    rng = np.random.default_rng(1)
    theta_o = np.linspace(0.1, 1.3, n)
    return SampleTable(
        theta_i=np.full(n, 0.3),
        phi_i=np.zeros(n),
        theta_o=theta_o,
        phi_o=np.full(n, np.pi),
        channel=np.full(n, "Y"),
        f=0.1 + 0.01 * rng.standard_normal(n),
        sigma=np.full(n, 0.01),
        flags=np.arange(n, dtype=np.int32),
    )


def test_likelihood_and_binned_path_take_the_same_rows_in_the_same_roles() -> None:
    table = _table()
    kinds = row_kinds(table)
    flags = table.flags
    # the table's rule, written out: exclude beats censor beats keep; saturated beats dark
    excluded = (flags & (Flags.BELOW_HORIZON | Flags.MASKED)) != 0
    np.testing.assert_array_equal(kinds.usable, ~excluded)
    np.testing.assert_array_equal(kinds.saturated, (flags & Flags.SATURATED) != 0)
    np.testing.assert_array_equal(kinds.dark, ((flags & Flags.DARK) != 0) & ~kinds.saturated)
    assert kinds.measured[Flags.NEGATIVE] and kinds.measured[0]  # 16 keeps its row
    # the likelihood
    model = models.get("lambert")
    space = ParameterSpace.build(model, ["Y"])
    lik = Likelihood(model, table, space, channels=["Y"])
    assert lik.n == int(kinds.usable.sum())
    assert lik.n_exact == int(kinds.measured.sum())
    assert lik.n_saturated == int((kinds.usable & kinds.saturated).sum())
    assert lik.n_dark == int((kinds.usable & kinds.dark).sum())
    # the binned path (bins far narrower than the rows' spacing: one row per bin)
    binned, member = bin_table(table, BinOptions(width_deg=0.05), members=True)
    np.testing.assert_array_equal(member >= 0, kinds.usable)
    assert len(binned) == int(kinds.usable.sum())
    binned_kinds = row_kinds(binned)
    assert int(binned_kinds.measured.sum()) == int(kinds.measured.sum())
    assert int(binned_kinds.dark.sum()) == int((kinds.usable & kinds.dark).sum())
    # the report's "good" rows are the ones fitted as values
    assert len(table.good()) == int(kinds.measured.sum())
