"""The accelerometer as a measurement of the gravity direction on S².

At rest the accelerometer reads the specific force a ≈ −g Rᵀe₃ (FRD body, NED
world), so z = −a/‖a‖ measures h(R) = Rᵀe₃, the world's "down" seen from the
body. Its magnitude carries no attitude information and its rotation about
itself is unobservable: a 2-D measurement (docs/design.md#gravity-update).

Residual: r = B_zᵀ ρ(h, z) (see :mod:`mavest.sphere`); Jacobian with respect to
the attitude error at the linearisation point,

    left error  R = chart(δ) R̄:   ∂h/∂δ = R̄ᵀ[e₃]×   (third column zero: no heading)
    right error R = R̄ Exp(δ):     ∂h/∂δ = [h]×

so that H = B_zᵀ (∂ρ/∂h)(∂h/∂δ), and Hᵀ V⁻¹ H for the left error has e₃ in its
null space: a gravity update never adds information about heading.
"""

from __future__ import annotations

import numpy as np

from mavest import so3, sphere
from mavest._jit import inplace_kernel
from mavest.estimator.layout import ERROR_LEFT


@inplace_kernel
def residual_into(
    q: np.ndarray,
    z: np.ndarray,
    Bz: np.ndarray,
    r: np.ndarray,
    R: np.ndarray,
    h: np.ndarray,
    rho: np.ndarray,
) -> None:
    """r = B_zᵀ ρ(Rᵀe₃, z) at the attitude q. R, h, ρ are scratch (left filled)."""
    so3.matrix_from_quat_into(q, R)
    h[0], h[1], h[2] = R[2, 0], R[2, 1], R[2, 2]
    sphere.log_into(h, z, rho)
    r[0] = Bz[0, 0] * rho[0] + Bz[1, 0] * rho[1] + Bz[2, 0] * rho[2]
    r[1] = Bz[0, 1] * rho[0] + Bz[1, 1] * rho[1] + Bz[2, 1] * rho[2]


@inplace_kernel
def jacobian_into(
    R: np.ndarray,
    h: np.ndarray,
    z: np.ndarray,
    Bz: np.ndarray,
    error: int,
    H: np.ndarray,
    J: np.ndarray,
    D: np.ndarray,
) -> None:
    """H (2×6) at the point where :func:`residual_into` left R and h. J, D are 3×3 scratch."""
    sphere.log_jacobian_into(h, z, J)
    # D = ∂h/∂δ
    if error == ERROR_LEFT:
        # R̄ᵀ[e₃]× = [R̄ᵀe₂, −R̄ᵀe₁, 0]: columns are rows of R̄
        for i in range(3):
            D[i, 0] = R[1, i]
            D[i, 1] = -R[0, i]
            D[i, 2] = 0.0
    else:
        so3.hat_into(h, D)
    for k in range(2):
        # (B_zᵀ J)[k, :], then (B_zᵀ J D)[k, j] summed over i as a dense product would
        bj0 = Bz[0, k] * J[0, 0] + Bz[1, k] * J[1, 0] + Bz[2, k] * J[2, 0]
        bj1 = Bz[0, k] * J[0, 1] + Bz[1, k] * J[1, 1] + Bz[2, k] * J[2, 1]
        bj2 = Bz[0, k] * J[0, 2] + Bz[1, k] * J[1, 2] + Bz[2, k] * J[2, 2]
        for j in range(3):
            acc = 0.0
            acc += bj0 * D[0, j]
            acc += bj1 * D[1, j]
            acc += bj2 * D[2, j]
            H[k, j] = acc
            H[k, j + 3] = 0.0
