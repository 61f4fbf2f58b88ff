"""Allocation-free small dense linear algebra for the filter's hot path.

numpy's own routines allocate their results; at a few hundred flops per call
the allocation would cost more than the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np

from mavest._jit import inplace_inlined_kernel, inplace_kernel


@inplace_inlined_kernel
def copy_into(out: np.ndarray, v: np.ndarray) -> None:
    """out[:] = v, element by element: a slice assignment may copy v first, which
    needs numba's allocator, and the filter's kernels run without it."""
    for i in range(out.shape[0]):
        out[i] = v[i]


@inplace_inlined_kernel
def copy_matrix_into(out: np.ndarray, M: np.ndarray) -> None:
    """out[:, :] = M (see :func:`copy_into`)."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = M[i, j]


@inplace_inlined_kernel
def symmetrise(P: np.ndarray) -> None:
    """P ← (P + Pᵀ)/2, in place."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            m = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = m
            P[j, i] = m


@inplace_kernel
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


@inplace_kernel
def is_positive_definite(A: np.ndarray, work: np.ndarray) -> bool:
    """Whether the symmetric A (its lower triangle read) is positive definite.

    The pivots d_j of A = L D Lᵀ are all positive (a NaN fails). They are
    Cholesky's squared diagonal, so this decides as :func:`cholesky_into` does
    but for rounding at the edge of definiteness, without its n square roots
    and with one division per column instead of one per entry. ``work`` (n×n)
    is scratch: L D below the diagonal, L above it (transposed).
    """
    n = A.shape[0]
    for j in range(n):
        pivot = A[j, j]
        for k in range(j):
            pivot -= work[j, k] * work[k, j]
        if not pivot > 0.0:  # also catches NaN
            return False
        inverse = 1.0 / pivot
        for i in range(j + 1, n):
            acc = A[i, j]
            for k in range(j):
                acc -= work[i, k] * work[k, j]
            work[i, j] = acc  # (L D)[i, j]
            work[j, i] = acc * inverse  # L[i, j]
    return True


@inplace_kernel
def inverse_2x2_into(S: np.ndarray, out: np.ndarray) -> float:
    """out = S⁻¹ for a 2×2 matrix; returns det S (≤ 0 or NaN: not usable)."""
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    out[0, 0] = S[1, 1] / det
    out[1, 1] = S[0, 0] / det
    out[0, 1] = -S[0, 1] / det
    out[1, 0] = -S[1, 0] / det
    return det


@inplace_kernel
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


@inplace_inlined_kernel
def left_multiply_rows3(P: np.ndarray, r0: int, M: np.ndarray) -> None:
    """P[r0:r0+3, :] ← M P[r0:r0+3, :] for a 3×3 M, in place.

    Each column's three entries are read before any is written, so no scratch
    is needed; every entry is the same sum, in the same order, as a dense product.
    """
    m00, m01, m02 = M[0, 0], M[0, 1], M[0, 2]
    m10, m11, m12 = M[1, 0], M[1, 1], M[1, 2]
    m20, m21, m22 = M[2, 0], M[2, 1], M[2, 2]
    for j in range(P.shape[1]):
        p0, p1, p2 = P[r0, j], P[r0 + 1, j], P[r0 + 2, j]
        P[r0, j] = m00 * p0 + m01 * p1 + m02 * p2
        P[r0 + 1, j] = m10 * p0 + m11 * p1 + m12 * p2
        P[r0 + 2, j] = m20 * p0 + m21 * p1 + m22 * p2


@inplace_inlined_kernel
def right_multiply_cols3(P: np.ndarray, c0: int, M: np.ndarray) -> None:
    """P[:, c0:c0+3] ← P[:, c0:c0+3] Mᵀ for a 3×3 M, in place (as :func:`left_multiply_rows3`)."""
    m00, m01, m02 = M[0, 0], M[0, 1], M[0, 2]
    m10, m11, m12 = M[1, 0], M[1, 1], M[1, 2]
    m20, m21, m22 = M[2, 0], M[2, 1], M[2, 2]
    for i in range(P.shape[0]):
        p0, p1, p2 = P[i, c0], P[i, c0 + 1], P[i, c0 + 2]
        P[i, c0] = m00 * p0 + m01 * p1 + m02 * p2
        P[i, c0 + 1] = m10 * p0 + m11 * p1 + m12 * p2
        P[i, c0 + 2] = m20 * p0 + m21 * p1 + m22 * p2


@inplace_inlined_kernel
def left_multiply_rows2(P: np.ndarray, r0: int, M: np.ndarray) -> None:
    """P[r0:r0+2, :] ← M₂ P[r0:r0+2, :] for M₂ = M[:2, :2] (M 2×2 or larger), in place
    (as :func:`left_multiply_rows3`)."""
    m00, m01 = M[0, 0], M[0, 1]
    m10, m11 = M[1, 0], M[1, 1]
    for j in range(P.shape[1]):
        p0, p1 = P[r0, j], P[r0 + 1, j]
        P[r0, j] = m00 * p0 + m01 * p1
        P[r0 + 1, j] = m10 * p0 + m11 * p1


@inplace_inlined_kernel
def right_multiply_cols2(P: np.ndarray, c0: int, M: np.ndarray) -> None:
    """P[:, c0:c0+2] ← P[:, c0:c0+2] M₂ᵀ for M₂ = M[:2, :2], in place (as
    :func:`left_multiply_rows3`)."""
    m00, m01 = M[0, 0], M[0, 1]
    m10, m11 = M[1, 0], M[1, 1]
    for i in range(P.shape[0]):
        p0, p1 = P[i, c0], P[i, c0 + 1]
        P[i, c0] = m00 * p0 + m01 * p1
        P[i, c0 + 1] = m10 * p0 + m11 * p1


@inplace_inlined_kernel
def gain_update(P: np.ndarray, K: np.ndarray, C: np.ndarray, S: np.ndarray, m: int) -> None:
    """P ← P − K Cᵀ − C Kᵀ + K S Kᵀ: the covariance after a correction K·r with any gain.

    For a measurement r = H x + v with C = P Hᵀ and S = H P Hᵀ + V this is the
    Joseph form (I − K H) P (I − K H)ᵀ + K V Kᵀ expanded, at O(n² m) instead of
    O(n³); it holds for a suboptimal (e.g. Schmidt) gain as well. K, C: n×m, m ≤ 3.
    The lower triangle is computed, then mirrored.

    K S is formed once per row, and the trailing rows where K is zero (the
    considered states of a Schmidt gain) drop the products with that zero: a
    pair of such rows keeps P, a pair with one of them loses C Kᵀ's term only.
    Each entry is the same sum, in the same order, as the plain expansion (the
    dropped terms are exact zeros), so the result is the same to the bit, but
    for the sign of an exact zero.
    """
    if m > 3:
        raise ValueError("gain_update: at most 3 measurement dimensions")
    n = P.shape[0]
    gain_rows = n  # K[gain_rows:] is zero
    while gain_rows > 0:
        zero = True
        for a in range(m):
            if K[gain_rows - 1, a] != 0.0:
                zero = False
        if not zero:
            break
        gain_rows -= 1
    for i in range(n):
        # row i of K and C held in scalars (the loops below read them every j)
        k0, c0 = K[i, 0], C[i, 0]
        k1 = K[i, 1] if m > 1 else 0.0
        c1 = C[i, 1] if m > 1 else 0.0
        k2 = K[i, 2] if m > 2 else 0.0
        c2 = C[i, 2] if m > 2 else 0.0
        if i < gain_rows:
            # (K S)[i, a], each summed from 0 over b as in the plain expansion
            ks0 = 0.0
            ks1 = 0.0
            ks2 = 0.0
            for b in range(m):
                ks0 += K[i, b] * S[b, 0]
                if m > 1:
                    ks1 += K[i, b] * S[b, 1]
                if m > 2:
                    ks2 += K[i, b] * S[b, 2]
            for j in range(i + 1):
                acc = P[i, j]
                acc += -k0 * C[j, 0] - c0 * K[j, 0] + ks0 * K[j, 0]
                if m > 1:
                    acc += -k1 * C[j, 1] - c1 * K[j, 1] + ks1 * K[j, 1]
                if m > 2:
                    acc += -k2 * C[j, 2] - c2 * K[j, 2] + ks2 * K[j, 2]
                P[i, j] = acc
        else:  # K's row i is zero: −C Kᵀ's term alone, and nothing where K's row j is zero
            for j in range(gain_rows):
                acc = P[i, j]
                acc -= c0 * K[j, 0]
                if m > 1:
                    acc -= c1 * K[j, 1]
                if m > 2:
                    acc -= c2 * K[j, 2]
                P[i, j] = acc
    for i in range(n):
        for j in range(i):
            P[j, i] = P[i, j]
