"""The batched matrix exponential of the secondary-impact operators against scipy's, matrix by matrix."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from msmill.model.expected_value import expm_batched


def _generator_blocks(rng, n: int, nd: int, lam_max: float) -> np.ndarray:
    """SYNTHETIC blocks of the form the solver exponentiates: [[lam (S - I), 0], [I, 0]], S lower-triangular
    with non-negative entries and column sums <= 1 (survivors only gain damage), lam up to ``lam_max``."""
    S = np.tril(rng.random((n, nd, nd)))
    S /= S.sum(axis=1, keepdims=True) * rng.uniform(1.0, 1.5, (n, 1, nd))
    lam = rng.uniform(0.0, lam_max, n)[:, None, None]
    Z = np.zeros((n, 2 * nd, 2 * nd))
    Z[:, :nd, :nd] = lam * (S - np.eye(nd))
    Z[:, nd:, :nd] = np.eye(nd)
    return Z


@pytest.mark.parametrize("lam_max", [0.5, 30.0, 400.0])
def test_equals_scipy_expm_on_the_solver_blocks(lam_max):
    Z = _generator_blocks(np.random.default_rng(7), 60, 6, lam_max)
    want = np.stack([scipy.linalg.expm(z) for z in Z])
    got = expm_batched(Z)
    scale = np.abs(want).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(got - want) / scale) < 1e-12


def test_general_matrices_identity_and_empty():
    rng = np.random.default_rng(1)
    Z = rng.normal(0.0, 3.0, (40, 5, 5))
    want = np.stack([scipy.linalg.expm(z) for z in Z])
    np.testing.assert_allclose(expm_batched(Z), want, rtol=1e-11, atol=1e-11 * np.abs(want).max())
    np.testing.assert_allclose(expm_batched(np.zeros((3, 4, 4))), np.broadcast_to(np.eye(4), (3, 4, 4)), atol=1e-15)
    assert expm_batched(np.zeros((0, 4, 4))).shape == (0, 4, 4)
    # a nilpotent block: exp([[0, 1], [0, 0]]) = [[1, 1], [0, 1]] exactly
    np.testing.assert_allclose(expm_batched(np.array([[[0.0, 1.0], [0.0, 0.0]]]))[0], [[1, 1], [0, 1]], atol=1e-15)
