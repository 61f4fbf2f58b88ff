"""Attitude error charts: how a 3-vector δθ names a rotation near the reference.

Three charts (docs/design.md#state-and-error; Mueller et al. 2017):

* left / exp:            R = Exp(δθ) R̄             (δθ in the world frame)
* right / exp:           R = R̄ Exp(δθ)             (δθ in the body frame)
* left / heading_tilt:   R = Rz(ψ) Exp([τx, τy, 0]) R̄,   δθ = (τx, τy, ψ)

All three agree to first order at δθ = 0, so a covariance means the same in
each; they differ in what a *finite* error is, which is what the reset and the
iterated update see. The heading-tilt chart separates rotation about the world
vertical exactly: left-multiplying by a heading rotation changes ψ and nothing
else. With gravity alone heading is unobservable, and the exponential chart's
reset then moves heading uncertainty into tilt (docs/design.md#heading-tilt-chart);
in this chart the reset Jacobian has no heading-to-tilt entries.

The reset (Mueller et al.): after a correction δ̂ the reference moves to
R̄⁺ = chart(δ̂) R̄ and the error becomes δ⁺ = chart⁻¹(chart(δ) chart(δ̂)⁻¹) (left)
or chart⁻¹(chart(δ̂)⁻¹ chart(δ)) (right); the covariance follows with
T = ∂δ⁺/∂δ at δ = δ̂: J_l(δ̂) (left/exp), J_r(δ̂) (right/exp), and for heading-tilt

    T = [[Rz₂(ψ̂) J_l(τ̂)[xy, xy], 0], [J_l(τ̂)[z, xy], 1]].
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_kernel
from mavest.estimator.layout import (
    CHART_EXP,
    ERROR_LEFT,
    RESET_FIRST_ORDER,
    RESET_NONE,
)


@inplace_kernel
def chart_quat_into(delta: np.ndarray, chart: int, out: np.ndarray) -> None:
    """The error rotation chart(δ) as a quaternion."""
    if chart == CHART_EXP:
        so3.quat_exp_into(delta, out)
        return
    # heading-tilt: qz(ψ) ⊗ q(τ), q(τ) = (c, a, b, 0) for the horizontal τ
    tx, ty, psi = delta[0], delta[1], delta[2]
    theta = math.sqrt(tx * tx + ty * ty)
    k = 0.5 * so3.sinc(0.5 * theta)
    c, a, b = math.cos(0.5 * theta), k * tx, k * ty
    cz, sz = math.cos(0.5 * psi), math.sin(0.5 * psi)
    out[0] = cz * c
    out[1] = cz * a - sz * b
    out[2] = cz * b + sz * a
    out[3] = sz * c


@inplace_kernel
def chart_log_into(e: np.ndarray, chart: int, out: np.ndarray) -> None:
    """chart⁻¹ of the error rotation e (a unit quaternion).

    Heading-tilt: writing e = qz(ψ) ⊗ (c, a, b, 0) gives e_w = cos(ψ/2) c and
    e_z = sin(ψ/2) c, so ψ/2 = atan2(e_z, e_w) and (a, b) is (e_x, e_y) turned
    back by ψ/2. Valid for tilt errors below π (c > 0).
    """
    if chart == CHART_EXP:
        so3.quat_log_into(e, out)
        return
    half = math.atan2(e[3], e[0])
    cz, sz = math.cos(half), math.sin(half)
    a = cz * e[1] + sz * e[2]
    b = -sz * e[1] + cz * e[2]
    c = math.hypot(e[0], e[3])
    so3.quat_log_components_into(c, a, b, 0.0, out)
    psi = 2.0 * half
    if psi > math.pi:
        psi -= 2.0 * math.pi
    elif psi <= -math.pi:
        psi += 2.0 * math.pi
    out[2] = psi


@inplace_kernel
def retract_into(
    q_ref: np.ndarray,
    delta: np.ndarray,
    error: int,
    chart: int,
    out: np.ndarray,
    work4: np.ndarray,
) -> None:
    """out = q_ref ⊞ δθ: the attitude at error δθ from the reference (normalised)."""
    chart_quat_into(delta, chart, work4)
    if error == ERROR_LEFT:
        so3.quat_multiply_into(work4, q_ref, out)
    else:
        so3.quat_multiply_into(q_ref, work4, out)
    so3.quat_normalize_into(out)


@inplace_kernel
def local_into(
    q: np.ndarray,
    q_ref: np.ndarray,
    error: int,
    chart: int,
    out: np.ndarray,
    work4: np.ndarray,
) -> None:
    """out = q ⊟ q_ref: the error δθ of q relative to the reference."""
    if error == ERROR_LEFT:
        so3.quat_divide_right_into(q, q_ref, work4)
    else:
        so3.quat_divide_left_into(q_ref, q, work4)
    chart_log_into(work4, chart, out)


@inplace_kernel
def reset_jacobian_into(
    delta: np.ndarray,
    error: int,
    chart: int,
    policy: int,
    out: np.ndarray,
) -> None:
    """T (3×3) = ∂δ⁺/∂δ of the reset by δ̂ = ``delta``, to the order the policy asks.

    ``none`` gives I (the MEKF), ``first_order`` the expansion to first order
    in δ̂ (Mueller et al.), ``full`` the exact Jacobian of the chart.
    """
    if policy == RESET_NONE:
        so3.skew_polynomial_into(delta, 0.0, 0.0, out)
        return
    if chart == CHART_EXP:
        sign = 1.0 if error == ERROR_LEFT else -1.0
        if policy == RESET_FIRST_ORDER:  # I ± ½[δ̂]×
            so3.skew_polynomial_into(delta, 0.5 * sign, 0.0, out)
        elif error == ERROR_LEFT:
            so3.left_jacobian_into(delta, out)
        else:
            so3.right_jacobian_into(delta, out)
        return
    # heading-tilt (left only)
    tx, ty, psi = delta[0], delta[1], delta[2]
    if policy == RESET_FIRST_ORDER:
        out[0, 0], out[0, 1], out[0, 2] = 1.0, -psi, 0.0
        out[1, 0], out[1, 1], out[1, 2] = psi, 1.0, 0.0
        out[2, 0], out[2, 1], out[2, 2] = -0.5 * ty, 0.5 * tx, 1.0
        return
    # J_l(τ̂) for τ̂ = (τx, τy, 0): I + B[τ̂]× + C[τ̂]×², with [τ̂]×² = τ̂τ̂ᵀ − θ²I
    b, c = so3.jacobian_coefficients(math.sqrt(tx * tx + ty * ty))
    j00, j01 = 1.0 - c * ty * ty, c * tx * ty
    j10, j11 = c * tx * ty, 1.0 - c * tx * tx
    cz, sz = math.cos(psi), math.sin(psi)
    out[0, 0], out[0, 1], out[0, 2] = cz * j00 - sz * j10, cz * j01 - sz * j11, 0.0
    out[1, 0], out[1, 1], out[1, 2] = sz * j00 + cz * j10, sz * j01 + cz * j11, 0.0
    out[2, 0], out[2, 1], out[2, 2] = -b * ty, b * tx, 1.0
