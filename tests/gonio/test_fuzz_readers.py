"""A short run of the readers' mutation fuzz (tools/fuzz_readers.py, issue 47): 150 mutants of
each reader's valid file — flipped bytes, truncations, deleted, duplicated and swapped runs,
inserted tokens (1e308, NaN, NUL, 200 brackets, bytes that are not UTF-8) — and every one either
reads or is refused in one line: no internal error, no hang. The acceptance run (10⁴ mutants a
reader) is in docs/reliability.md; this one keeps the suite honest about regressions. Real files
and real readers; nothing is stubbed."""

from __future__ import annotations

import pytest

from tools.fuzz_readers import fuzz, readers


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy on mutated values
@pytest.mark.parametrize("name", sorted(readers()))
def test_no_mutant_reaches_an_internal_error_or_a_hang(name: str) -> None:
    # a MERL mutant is MERL's whole 33 MB grid: 20 of them (~5 s), not 150
    counts, examples = fuzz(name, 20 if name == "merl" else 150)
    assert counts["internal error"] == 0 and counts["hang"] == 0, examples
    assert counts["one line"] > 0  # the mutants are bad enough to be refused
