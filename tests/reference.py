"""Independent reference implementations for the tests, written with scipy only.

Nothing here calls mavest: charts, the S² residual, Jacobians by finite
differences and a textbook EKF, so that a mistake in mavest's kernels cannot
also be in the reference.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg import null_space
from scipy.spatial.transform import Rotation

E3 = np.array([0.0, 0.0, 1.0])
CHARTS = [("left", "exp"), ("right", "exp"), ("left", "heading_tilt")]


def rz(psi: float) -> Rotation:
    return Rotation.from_rotvec([0.0, 0.0, psi])


def chart(delta: np.ndarray, chart_name: str) -> Rotation:
    """The error rotation named by δθ."""
    if chart_name == "exp":
        return Rotation.from_rotvec(delta)
    return rz(delta[2]) * Rotation.from_rotvec([delta[0], delta[1], 0.0])


def chart_inverse(error: Rotation, chart_name: str) -> np.ndarray:
    if chart_name == "exp":
        return error.as_rotvec()
    # E = Rz(ψ) Exp(τ): Eᵀe₃ = Exp(−τ) e₃ fixes τ (horizontal axis), then Rz(ψ) = E Exp(τ)⁻¹
    d = error.inv().apply(E3)
    axis = np.cross(E3, d)
    s = np.linalg.norm(axis)
    angle = np.arctan2(s, E3 @ d)
    tau = -angle * axis / s if s > 0 else np.zeros(3)
    heading = error * Rotation.from_rotvec(tau).inv()
    return np.array([tau[0], tau[1], heading.as_rotvec()[2]])


def retract(R_ref: Rotation, delta: np.ndarray, side: str, chart_name: str) -> Rotation:
    e = chart(delta, chart_name)
    return e * R_ref if side == "left" else R_ref * e


def local(R: Rotation, R_ref: Rotation, side: str, chart_name: str) -> np.ndarray:
    e = R * R_ref.inv() if side == "left" else R_ref.inv() * R
    return chart_inverse(e, chart_name)


def numeric_jacobian(
    f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, step: float = 1e-6
) -> np.ndarray:
    fx = np.asarray(f(x))
    out = np.empty((fx.size, x.size))
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = step
        out[:, j] = (np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * step)
    return out


def reset_jacobian(delta_hat: np.ndarray, side: str, chart_name: str) -> np.ndarray:
    """∂δ⁺/∂δ at δ̂ of the exact reset map, by finite differences."""
    ref = Rotation.identity()
    new_ref = retract(ref, delta_hat, side, chart_name)
    return numeric_jacobian(
        lambda d: local(retract(ref, d, side, chart_name), new_ref, side, chart_name), delta_hat
    )


def gravity_residual(R: Rotation, accel: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """2-D geodesic residual from the predicted down direction Rᵀe₃ to −a/‖a‖."""
    z = -accel / np.linalg.norm(accel)
    h = R.inv().apply(E3)
    w = np.cross(h, z)
    s = np.linalg.norm(w)
    rho = np.arctan2(s, h @ z) * w / s if s > 0 else np.zeros(3)
    return basis.T @ rho


def measurement_basis(accel: np.ndarray) -> np.ndarray:
    """Any orthonormal basis of the plane ⊥ z (the update cannot depend on which)."""
    return null_space((accel / np.linalg.norm(accel))[None, :])


def ekf_update(
    R: Rotation,
    b: np.ndarray,
    P: np.ndarray,
    accel: np.ndarray,
    var: float,
    side: str,
    chart_name: str,
) -> tuple[Rotation, np.ndarray, np.ndarray]:
    """Textbook EKF with a finite-difference Jacobian, then the exact (full) reset."""
    basis = measurement_basis(accel)

    def residual(dx: np.ndarray) -> np.ndarray:
        return gravity_residual(retract(R, dx[:3], side, chart_name), accel, basis)

    H = numeric_jacobian(residual, np.zeros(6))
    r = residual(np.zeros(6))
    V = var * np.eye(2)
    S = H @ P @ H.T + V
    K = P @ H.T @ np.linalg.inv(S)
    dx = -K @ r
    A = np.eye(6) - K @ H
    P_post = A @ P @ A.T + K @ V @ K.T
    T = np.eye(6)
    T[:3, :3] = reset_jacobian(dx[:3], side, chart_name)
    return retract(R, dx[:3], side, chart_name), b + dx[3:], T @ P_post @ T.T


def random_covariance(
    rng: np.random.Generator, attitude_sigma: float, bias_sigma: float
) -> np.ndarray:
    """An SPD 6×6 covariance with correlations between all components."""
    scale = np.diag([attitude_sigma] * 3 + [bias_sigma] * 3)
    A = rng.normal(size=(6, 6))
    C = A @ A.T + 3.0 * np.eye(6)
    d = np.sqrt(np.diag(C))
    return scale @ (C / np.outer(d, d)) @ scale
