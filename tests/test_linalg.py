"""The hot path's small dense kernels (mavest.estimator.linalg) against dense NumPy."""

from __future__ import annotations

import numpy as np
import pytest

from mavest.estimator.linalg import gain_update, left_multiply_rows3, right_multiply_cols3


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize("zero_rows", [(), (0, 1), (6, 7, 8, 9, 10, 11, 12, 13, 14)])
def test_gain_update_is_the_joseph_form_for_any_gain(m: int, zero_rows: tuple[int, ...]) -> None:
    """P − K Cᵀ − C Kᵀ + K S Kᵀ equals (I − K H) P (I − K H)ᵀ + K V Kᵀ, also for a
    Schmidt gain whose rows are zero (leading, as the magnetometer's tilt rows,
    or trailing, as the considered states: the rows the kernel skips)."""
    rng = np.random.default_rng(m + len(zero_rows))
    n = 15
    P = _spd(rng, n)
    H = rng.normal(size=(m, n))
    V = _spd(rng, m)
    C = P @ H.T
    S = H @ C + V
    K = C @ np.linalg.inv(S)
    K[list(zero_rows), :] = 0.0
    I_KH = np.eye(n) - K @ H
    expected = I_KH @ P @ I_KH.T + K @ V @ K.T
    out = P.copy()
    gain_update(out, K, C, S, m)
    np.testing.assert_allclose(out, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())
    np.testing.assert_array_equal(out, out.T)


def test_gain_update_refuses_more_than_three_dimensions() -> None:
    P = np.eye(6)
    with pytest.raises(ValueError):
        gain_update(P, np.zeros((6, 4)), np.zeros((6, 4)), np.eye(4), 4)


def test_block_products_are_the_dense_products() -> None:
    rng = np.random.default_rng(7)
    P = rng.normal(size=(15, 15))
    M = rng.normal(size=(3, 3))
    T = np.eye(15)
    T[6:9, 6:9] = M
    left = P.copy()
    left_multiply_rows3(left, 6, M)
    np.testing.assert_allclose(left, T @ P, rtol=1e-13, atol=1e-13)
    right = P.copy()
    right_multiply_cols3(right, 6, M)
    np.testing.assert_allclose(right, P @ T.T, rtol=1e-13, atol=1e-13)
