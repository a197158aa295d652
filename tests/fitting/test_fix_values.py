"""`--fix` values are checked, not only parsed (issue 22, item 3): a value outside the
parameter's own range, or not finite, is refused in one line before anything is fitted."""

from __future__ import annotations

import math

import pytest

from fitting import models
from fitting.priors import ParameterSpace, PriorsError


@pytest.mark.parametrize(
    ("fix", "words"),
    [
        ({"kd_R": 1.5}, "outside kd's range [0, 1]"),
        ({"kd": -0.1}, "outside kd's range"),
        ({"m": math.nan}, "outside m's range"),
        ({"ks_G": math.inf}, "outside ks's range"),
        ({"m": "rough"}, "not a number"),
        ({"discrepancy": -1.0}, "outside the discrepancy's range [0,"),
    ],
)
def test_out_of_range_fix_is_refused(fix, words) -> None:
    model = models.get("torrance-sparrow")
    with pytest.raises(PriorsError, match=words.replace("[", r"\[")):
        ParameterSpace.build(model, ["R", "G", "B"], fix=fix, discrepancy=True)


def test_in_range_fix_is_kept() -> None:
    model = models.get("torrance-sparrow")
    space = ParameterSpace.build(model, ["R", "G"], fix={"kd_R": 0.3, "m": 0.2})
    assert space.fixed == {"kd_R": 0.3, "m": 0.2}
    assert "kd_R" not in space.names and "kd_G" in space.names
