"""The hot path's small dense kernels (mavest.estimator.linalg) against dense NumPy."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from mavest.estimator.linalg import (
    cholesky_into,
    gain_update,
    is_positive_definite,
    left_multiply_rows2,
    left_multiply_rows3,
    right_multiply_cols2,
    right_multiply_cols3,
)


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


@pytest.mark.parametrize(
    "size, left_multiply, right_multiply",
    [
        (3, left_multiply_rows3, right_multiply_cols3),
        (2, left_multiply_rows2, right_multiply_cols2),
    ],
)
def test_block_products_are_the_dense_products(
    size: int, left_multiply: Callable[..., None], right_multiply: Callable[..., None]
) -> None:
    """The 3-row kernels with a 3×3 M; the 2-row ones with M's leading 2×2."""
    rng = np.random.default_rng(7)
    P = rng.normal(size=(15, 15))
    M = rng.normal(size=(3, 3))
    T = np.eye(15)
    T[6 : 6 + size, 6 : 6 + size] = M[:size, :size]
    left = P.copy()
    left_multiply(left, 6, M)
    np.testing.assert_allclose(left, T @ P, rtol=1e-13, atol=1e-13)
    right = P.copy()
    right_multiply(right, 6, M)
    np.testing.assert_allclose(right, P @ T.T, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("n", [1, 6, 15])
def test_is_positive_definite_decides_as_cholesky(n: int) -> None:
    """Definite, semi-definite (a zero row, as ε's before the low-pass is primed),
    indefinite and NaN matrices: the LDLᵀ pivots' answer is cholesky_into's."""
    rng = np.random.default_rng(n)
    definite = _spd(rng, n)
    semi_definite = _spd(rng, n)
    semi_definite[n - 1, :] = 0.0
    semi_definite[:, n - 1] = 0.0
    indefinite = _spd(rng, n)
    indefinite[n - 1, n - 1] = -1.0
    nan = _spd(rng, n)
    nan[0, 0] = np.nan
    badly_conditioned = np.diag(np.linspace(1e-12, 1.0, n))
    cases = [
        (definite, True),
        (semi_definite, False),
        (indefinite, False),
        (nan, False),
        (badly_conditioned, True),
    ]
    for M, expected in cases:
        assert is_positive_definite(M, np.full((n, n), np.nan)) == expected
        assert cholesky_into(M, np.zeros((n, n))) == expected


def test_is_positive_definite_factors_the_matrix() -> None:
    """work holds L D below the diagonal and L above it: L D Lᵀ rebuilds A."""
    rng = np.random.default_rng(3)
    n = 15
    A = _spd(rng, n)
    work = np.zeros((n, n))
    assert is_positive_definite(A, work)
    L = np.triu(work, 1).T + np.eye(n)
    LD = np.tril(work, -1)
    pivots = np.array([A[j, j] - LD[j, :j] @ L[j, :j] for j in range(n)])
    np.testing.assert_allclose(LD, np.tril(L * pivots, -1), rtol=1e-12)
    np.testing.assert_allclose(
        L @ np.diag(pivots) @ L.T, A, rtol=1e-12, atol=1e-12 * np.abs(A).max()
    )


def test_the_compiled_cache_is_keyed_on_every_module_that_compiles_kernels() -> None:
    """numba keys a kernel's cache on its own file only; mavest names the cache after
    a hash of every module with kernels (C callbacks too), found by their import of the
    decorators. A module that compiles kernels and is not found would keep stale callees."""
    import importlib
    import pkgutil
    from pathlib import Path
    from types import ModuleType

    from numba.core.registry import CPUDispatcher

    import mavest
    from mavest import _jit

    def compiled_in(module: ModuleType, value: object) -> bool:
        if isinstance(value, _jit.CallbackKernel):
            value = value.function
        elif not isinstance(value, CPUDispatcher):
            return False
        return value.__module__ == module.__name__

    checked = 0
    callbacks = 0
    for info in pkgutil.walk_packages(mavest.__path__, "mavest."):
        module = importlib.import_module(info.name)
        compiled = [name for name, value in vars(module).items() if compiled_in(module, value)]
        callbacks += sum(isinstance(vars(module)[name], _jit.CallbackKernel) for name in compiled)
        if compiled:
            checked += 1
            source = Path(module.__file__).read_bytes()
            assert _jit.compiles_kernels(source), (info.name, compiled)
    assert checked >= 10 and callbacks >= 1
    assert not _jit.compiles_kernels(b"from mavest._jit import cache_is_warm\n")
    assert _jit.compiles_kernels(b"from mavest._jit import callback_kernel\n")
    assert _jit.compiles_kernels(b"from mavest._jit import inplace_inlined_kernel\n")
    assert _jit.compiles_kernels(b"from mavest._jit import inplace_kernel\n")
    assert _jit.compiles_kernels(b"from mavest._jit import inplace_exact_kernel\n")


def test_an_inplace_kernel_cannot_allocate() -> None:
    """The filter's kernels run without numba's runtime (``inplace_kernel``): what
    allocates there must fail to compile, not run with a reference count missing."""
    import numba

    from mavest._jit import inplace_kernel

    if numba.config.DISABLE_JIT:
        pytest.skip("NUMBA_DISABLE_JIT: nothing is compiled")

    @inplace_kernel
    def fills(out: np.ndarray) -> None:
        for i in range(out.shape[0]):
            out[i] = 1.0

    @inplace_kernel
    def allocates(n: int) -> float:
        return np.zeros(n).sum()

    out = np.zeros(3)
    fills(out)
    assert out.tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(numba.core.errors.TypingError):
        allocates(3)
