"""R̂ and bulk / tail ESS of an ensemble's chain (fitting.convergence), against what is known
without it: independent draws (ESS = the number of draws), AR(1) walkers whose integrated
autocorrelation time is (1 + ρ)/(1 − ρ) exactly, and chains built to have not mixed (two
ensembles in different places, half the walkers elsewhere, a drift in time), which R̂ must flag.
The numbers themselves are ArviZ's (Vehtari et al. 2021's definitions); what is tested here is
that gonio hands it an ensemble so that they mean what the paper means."""

from __future__ import annotations

import numpy as np
import pytest

from fitting.convergence import ConvergenceTarget, diagnose, ensemble_draws


def _ar1(rho: float, steps: int, walkers: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.empty((steps, walkers, 1))
    x[0] = rng.standard_normal((walkers, 1))
    e = rng.standard_normal((steps, walkers, 1)) * np.sqrt(1.0 - rho**2)
    for t in range(1, steps):
        x[t] = rho * x[t - 1] + e[t]
    return x


def test_independent_draws_have_ess_equal_to_their_number_and_rhat_one() -> None:
    chain = np.random.default_rng(0).standard_normal((1000, 32, 3))
    d = diagnose([chain])
    # The ESS estimator's own spread on 32 000 iid draws is a few per cent (Geyer's truncation).
    assert d.ess_bulk == pytest.approx(32000, rel=0.06)
    assert d.ess_tail == pytest.approx(32000, rel=0.1)
    assert np.all(np.abs(d.rhat - 1.0) < 0.003)  # R̂ − 1 ~ 1/n_eff per chain ≈ 1e-4


def test_bulk_ess_of_ar1_walkers_is_steps_times_walkers_over_tau() -> None:
    """τ = (1 + ρ)/(1 − ρ) = 19 at ρ = 0.9: ESS = N·W/τ = 3368 for 2000 steps × 32 walkers. The
    estimate's sd over seeds is ~5 % at that length; 12 % is 2.4 sd."""
    chain = _ar1(0.9, 2000, 32, seed=1)
    d = diagnose([chain])
    assert d.ess_bulk[0] == pytest.approx(2000 * 32 / 19, rel=0.12)
    assert d.rhat[0] < 1.01


@pytest.mark.parametrize(
    "how",
    ["two ensembles apart", "half the walkers apart", "a drift in time"],
)
def test_rhat_flags_a_chain_that_has_not_mixed(how) -> None:
    x = _ar1(0.9, 2000, 32, seed=2)
    if how == "two ensembles apart":
        chains = [x, _ar1(0.9, 2000, 32, seed=3) + 0.3]
    elif how == "half the walkers apart":
        x[:, :16] += 0.3
        chains = [x]
    else:
        chains = [x + np.linspace(0.0, 1.0, 2000)[:, None, None]]  # 1 sd over the run
    assert diagnose(chains).rhat[0] > 1.01


def test_the_layout_splits_each_ensemble_in_time() -> None:
    """Each ensemble becomes two chains, its first and second halves in time, each its walkers'
    traces end to end."""
    chain = np.arange(8 * 3).reshape(8, 3, 1).astype(float)  # value = step·3 + walker
    draws = ensemble_draws([chain])
    assert draws.shape == (2, 12, 1)
    first = draws[0, :, 0]
    # walker 0's steps 0..3, then walker 1's, then walker 2's
    assert first.tolist() == [0, 3, 6, 9, 1, 4, 7, 10, 2, 5, 8, 11]
    assert draws[1, :4, 0].tolist() == [12, 15, 18, 21]


def test_steps_to_scales_with_the_missing_ess() -> None:
    d = diagnose([_ar1(0.9, 400, 8, seed=4)])  # ESS ≈ 400·8/19 ≈ 170 < 400
    need = d.steps_to(ConvergenceTarget(), 400)
    assert need is not None and 600 < need < 2000
