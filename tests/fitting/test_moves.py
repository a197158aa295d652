"""Every move set a fit may use samples the right posterior (issue 23, item 0): on a known
9-D correlated Gaussian, with the fit's default walker count, the sampled standard deviations
match the true ones within the Monte-Carlo error. emcee 3.1.6's own DE + snooker mix fails this
(sd ≈ 6 % small, see fitting/moves.py); these bounds would catch it."""

from __future__ import annotations

import emcee
import numpy as np
import pytest

from fitting.fit import FitOptions
from fitting.moves import MOVES, named_moves

NDIM = 9
STEPS = 6000
BURN = 1000


def _target() -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance: eigenvalues spread over two decades (sd 0.32–3.2) in a random
    rotation, so the sampler meets the correlations and scales of a real posterior."""
    rng = np.random.default_rng(23)
    rotation, _ = np.linalg.qr(rng.standard_normal((NDIM, NDIM)))
    cov = rotation @ np.diag(np.logspace(-1, 1, NDIM)) @ rotation.T
    return rng.standard_normal(NDIM), cov


@pytest.mark.parametrize("moves", MOVES)
def test_move_set_samples_the_gaussian_it_is_given(moves: str) -> None:
    mean, cov = _target()
    precision = np.linalg.inv(cov)
    chol = np.linalg.cholesky(cov)

    def log_prob(x: np.ndarray) -> np.ndarray:
        d = x - mean
        return -0.5 * np.einsum("wi,ij,wj->w", d, precision, d)

    walkers = FitOptions().mcmc.walkers
    rng = np.random.default_rng(5)
    sampler = emcee.EnsembleSampler(
        walkers, NDIM, log_prob, vectorize=True, moves=named_moves(moves)
    )
    sampler.random_state = np.random.RandomState(7).get_state()
    start = mean + 0.01 * rng.standard_normal((walkers, NDIM))  # a tight ball, as a fit starts
    sampler.run_mcmc(start, STEPS + BURN)
    chain = sampler.get_chain(discard=BURN)  # (steps, walkers, dim)
    # Whitened coordinates are independent with unit variance under the target.
    white = np.linalg.solve(chol, (chain.reshape(-1, NDIM) - mean).T).T
    tau = emcee.autocorr.integrated_time(
        np.linalg.solve(chol, (chain - mean)[..., None]).squeeze(-1), quiet=True
    )
    ess = chain.shape[0] * walkers / np.max(tau)
    ratio = white.std(axis=0, ddof=1)
    # For a Gaussian, var(s²) = 2σ⁴/n, so an sd estimated from ESS draws has relative error
    # 1/√(2 ESS); the mean of 9 independent ratios has 1/√(2 ESS·9). Four of those: a false
    # alarm about once in 16 000 runs, while a 6 % deficit is ≥ 10 of them at ESS ≥ 1 500.
    se_one = 1 / np.sqrt(2 * ess)
    print(f"{moves}: sd ratios {np.round(ratio, 3)}, ESS {ess:.0f}, max τ {np.max(tau):.1f}")
    assert ess >= 1500, f"{moves}: ESS {ess:.0f} too small to test the sds"
    assert abs(ratio.mean() - 1) <= 4 * se_one / np.sqrt(NDIM), (moves, ratio.mean(), se_one)
    # Each coordinate alone, at 4.5 se (nine chances of a false alarm, ~6e-5 together).
    assert np.all(np.abs(ratio - 1) <= 4.5 * se_one), (moves, ratio, se_one)
    assert np.allclose(white.mean(axis=0), 0, atol=4.5 * np.sqrt(1 / ess)), (moves, white.mean(0))
