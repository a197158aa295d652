"""docs/config-ranges.md is generated from the config models (tools/config_ranges.py): the ranges
are stated once, on the fields, and the page must say what the code checks (issue 47)."""

from __future__ import annotations

from tools.config_ranges import DOC, table


def test_the_config_ranges_page_is_current() -> None:
    assert DOC.read_text() == table(), "run: python tools/config_ranges.py --write"
    assert "`axes[].gear_ratio` | ≥ 0.01, ≤ 1000" in DOC.read_text()
