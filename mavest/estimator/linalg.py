"""Allocation-free small dense linear algebra for the filter's hot path.

numpy's own routines allocate their results; at a few hundred flops per call
the allocation would cost more than the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np

from mavest._jit import kernel


@kernel
def symmetrise(P: np.ndarray) -> None:
    """P ← (P + Pᵀ)/2, in place."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            m = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = m
            P[j, i] = m


@kernel
def cholesky_into(A: np.ndarray, L: np.ndarray) -> bool:
    """Lower-triangular L with L Lᵀ = A; False (L undefined) if A is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        acc = A[j, j]
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:  # also catches NaN
            return False
        d = math.sqrt(acc)
        L[j, j] = d
        for i in range(j + 1, n):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@kernel
def inverse_2x2_into(S: np.ndarray, out: np.ndarray) -> float:
    """out = S⁻¹ for a 2×2 matrix; returns det S (≤ 0 or NaN: not usable)."""
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    out[0, 0] = S[1, 1] / det
    out[1, 1] = S[0, 0] / det
    out[0, 1] = -S[0, 1] / det
    out[1, 0] = -S[1, 0] / det
    return det


@kernel
def inverse_3x3_into(S: np.ndarray, out: np.ndarray) -> float:
    """out = S⁻¹ by cofactors; returns det S (≤ 0 or NaN: not usable for an SPD S)."""
    c00 = S[1, 1] * S[2, 2] - S[1, 2] * S[2, 1]
    c01 = S[1, 2] * S[2, 0] - S[1, 0] * S[2, 2]
    c02 = S[1, 0] * S[2, 1] - S[1, 1] * S[2, 0]
    det = S[0, 0] * c00 + S[0, 1] * c01 + S[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (S[0, 2] * S[2, 1] - S[0, 1] * S[2, 2]) / det
    out[1, 1] = (S[0, 0] * S[2, 2] - S[0, 2] * S[2, 0]) / det
    out[2, 1] = (S[0, 1] * S[2, 0] - S[0, 0] * S[2, 1]) / det
    out[0, 2] = (S[0, 1] * S[1, 2] - S[0, 2] * S[1, 1]) / det
    out[1, 2] = (S[0, 2] * S[1, 0] - S[0, 0] * S[1, 2]) / det
    out[2, 2] = (S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]) / det
    return det


@kernel
def left_multiply_rows3(P: np.ndarray, r0: int, M: np.ndarray, work: np.ndarray) -> None:
    """P[r0:r0+3, :] ← M P[r0:r0+3, :] for a 3×3 M (``work``: 3×n scratch)."""
    n = P.shape[1]
    for a in range(3):
        for j in range(n):
            work[a, j] = M[a, 0] * P[r0, j] + M[a, 1] * P[r0 + 1, j] + M[a, 2] * P[r0 + 2, j]
    for a in range(3):
        for j in range(n):
            P[r0 + a, j] = work[a, j]


@kernel
def right_multiply_cols3(P: np.ndarray, c0: int, M: np.ndarray, work: np.ndarray) -> None:
    """P[:, c0:c0+3] ← P[:, c0:c0+3] Mᵀ for a 3×3 M (``work``: 3×n scratch)."""
    n = P.shape[0]
    for a in range(3):
        for i in range(n):
            work[a, i] = M[a, 0] * P[i, c0] + M[a, 1] * P[i, c0 + 1] + M[a, 2] * P[i, c0 + 2]
    for a in range(3):
        for i in range(n):
            P[i, c0 + a] = work[a, i]


@kernel
def gain_update(P: np.ndarray, K: np.ndarray, C: np.ndarray, S: np.ndarray, m: int) -> None:
    """P ← P − K Cᵀ − C Kᵀ + K S Kᵀ: the covariance after a correction K·r with any gain.

    For a measurement r = H x + v with C = P Hᵀ and S = H P Hᵀ + V this is the
    Joseph form (I − K H) P (I − K H)ᵀ + K V Kᵀ expanded, at O(n² m) instead of
    O(n³); it holds for a suboptimal (e.g. Schmidt) gain as well. K, C: n×m.
    """
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1):
            acc = P[i, j]
            for a in range(m):
                ks = 0.0
                for b in range(m):
                    ks += K[i, b] * S[b, a]
                acc += -K[i, a] * C[j, a] - C[i, a] * K[j, a] + ks * K[j, a]
            P[i, j] = acc
            P[j, i] = acc
