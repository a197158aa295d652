"""Checks on the HTML report shared by the report tests and the demo's browser test."""

from __future__ import annotations

import re

__all__ = ["assert_uncertainty_visible"]


def assert_uncertainty_visible(html: str, fit: dict) -> None:
    """Each parameter's cell in the parameter table is 'value ± u' or 'value +u −d' with a
    non-zero u, one such cell per parameter (the 95 % column is an [lo, hi] interval, so two
    would be wrong). ``html`` is the file's text (single-quoted attributes) or the browser's
    serialised DOM (double-quoted)."""
    start = re.search(r"<table class=[\"']params[\"']>", html)
    assert start, "no parameter table"
    table = html[start.start() :]
    table = table[: table.index("</table>")]
    cells = re.findall(r"<td class=[\"']num[\"']>([^<]*(?:±|\+)[^<]*)</td>", table)
    assert len(cells) == len(fit["parameters"]), cells
    for cell in cells:
        ups = re.findall(r"(?:±|\+)\s?(\d+\.?\d*)", cell)
        assert ups and all(float(u) > 0 for u in ups), cell
