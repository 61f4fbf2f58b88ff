"""The smoother's per-sample fusion, compiled (docs/design.md#smoothing).

One pass over a block of samples: the backward filter's prior at each sample (its
estimate one sample later, predicted one gyro step back, where it updated there),
then the Kalman update of the forward estimate by that prior's attitude, in the
left error's world frame and the heading-tilt chart. :mod:`mavest.estimator.smoother`
runs the passes and decides which samples are fused.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import kernel
from mavest.estimator.charts import chart_log_into, retract_into
from mavest.estimator.config import MAX_HEADING_VAR
from mavest.estimator.layout import CHART_HEADING_TILT, ERROR_LEFT

# What of the backward prior's attitude a sample fuses (fuse_block's ``heading``): its
# tilt alone, turned onto the forward heading (the passes do not both reference heading,
# or neither does); all of it (both do); all of it with the forward heading taken as
# free, of variance MAX_HEADING_VAR (only the backward pass references heading there:
# the forward one started afresh and has not met its magnetometer yet).
TILT = 0
TILT_AND_HEADING = 1
BACKWARD_HEADING = 2


@kernel
def _turn_covariance(
    q: np.ndarray, P: np.ndarray, to_world: bool, R: np.ndarray, A: np.ndarray, out: np.ndarray
) -> None:
    """out (6 × 6) = P with its attitude rows and columns turned: ``to_world``, a right
    (body-frame) error's covariance as the left error's (P_θθ ← R P_θθ Rᵀ, P_θb ← R P_θb);
    else back (Rᵀ in R's place). R is the attitude q's matrix; R and A are scratch."""
    so3.matrix_from_quat_into(q, R)
    if not to_world:
        for r in range(3):
            for c in range(r + 1, 3):
                R[r, c], R[c, r] = R[c, r], R[r, c]
    for r in range(6):
        for c in range(6):
            A[r, c] = P[r, c]
    for r in range(3):
        for c in range(6):
            total = 0.0
            for m in range(3):
                total += R[r, m] * P[m, c]
            A[r, c] = total
    for r in range(6):
        for c in range(3):
            total = 0.0
            for m in range(3):
                total += A[r, m] * R[c, m]
            out[r, c] = total
        for c in range(3, 6):
            out[r, c] = A[r, c]


@kernel
def _predicted_attitude(
    q: np.ndarray,
    bias: np.ndarray,
    P: np.ndarray,
    gyro: np.ndarray,
    dt: float,
    gyro_noise_density: float,
    gyro_scale_noise_density: float,
    gyro_bias_random_walk: float,
    q_out: np.ndarray,
    P_out: np.ndarray,
    work: np.ndarray,
) -> None:
    """The filter's prediction by one sample (docs/design.md#prediction), left error, of
    the attitude and its 3 × 3 covariance: q ⊗ Exp((ω − b) Δt) and, with
    G = −R J_l(φ) Δt, P_θθ + G P_bθ + P_θb Gᵀ + G P_bb Gᵀ + (σ² Δt + σ_b² Δt³/3) I,
    σ² = σ_g² + σ_s² |ω − b|² (the rate noise, its part ∝ the rate included)."""
    phi = work[0, :3]
    for i in range(3):
        phi[i] = (gyro[i] - bias[i]) * dt
    turn = work[1]
    J = work[5:8, :3]
    so3.quat_exp_and_jacobian_into(phi, turn, J, True)
    so3.quat_multiply_into(q, turn, q_out)
    so3.quat_normalize_into(q_out)
    R = work[2:5, :3]
    so3.matrix_from_quat_into(q, R)
    G = work[8:11, :3]
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += R[i, k] * J[k, j]
            G[i, j] = -total * dt
    # GP = G P_bθ (3 × 3)
    GP = work[11:14, :3]
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += G[i, k] * P[3 + k, j]
            GP[i, j] = total
    rate_sq = (phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]) / (dt * dt)
    var_g = gyro_noise_density**2 + gyro_scale_noise_density**2 * rate_sq
    noise = var_g * dt + gyro_bias_random_walk**2 * dt**3 / 3.0
    for i in range(3):
        for j in range(3):
            total = P[i, j] + GP[i, j] + GP[j, i]
            for k in range(3):
                for m in range(3):
                    total += G[i, k] * P[3 + k, 3 + m] * G[j, m]
            P_out[i, j] = total + (noise if i == j else 0.0)


@kernel
def fuse_block(
    q_f: np.ndarray,
    b_f: np.ndarray,
    P_f: np.ndarray,
    q_b: np.ndarray,
    b_b: np.ndarray,
    P_b: np.ndarray,
    q_after: np.ndarray,
    b_after: np.ndarray,
    P_after: np.ndarray,
    gyro_next: np.ndarray,
    dt: np.ndarray,
    fused: np.ndarray,
    measured: np.ndarray,
    heading: np.ndarray,
    right: bool,
    gyro_noise_density: float,
    gyro_scale_noise_density: float,
    gyro_bias_random_walk: float,
) -> None:
    """Smooth the forward estimates q_f, b_f, P_f (n samples, time order) in place.

    The backward pass's estimates q_b, b_b, P_b are in its own order (sample k of the
    block is its row n − 1 − k); its estimate at the sample after the block is q_after,
    b_after, P_after. Per sample k with ``fused[k]``: the backward prior is its
    estimate at k, or, where it ``measured`` at k, its estimate at k + 1 predicted back
    by ``gyro_next[k]`` (its gyro over (t_k, t_k+1]) and ``dt[k]``. Its attitude is a
    measurement of the forward error, d = chart⁻¹(q_b q_f⁻¹) in the heading-tilt chart:
    all three components where ``heading[k]`` is TILT_AND_HEADING or BACKWARD_HEADING
    (then the forward heading's variance raised by MAX_HEADING_VAR first), its tilt
    (τx, τy) with its covariance turned by Rz(−ψ) onto the forward heading where it is
    TILT. ``right``:
    the covariances are the right error's (body frame), as the filter's output then is.
    """
    n = q_f.shape[0]
    prior_q = np.empty(4)
    error = np.empty(4)
    conjugate = np.empty(4)
    work4 = np.empty(4)
    d = np.empty(3)
    x = np.empty(6)
    Pb = np.empty((3, 3))
    S = np.empty((3, 3))
    S_inverse = np.empty((3, 3))
    K = np.empty((6, 3))
    Pw = np.empty((6, 6))
    A = np.empty((6, 6))
    R = np.empty((3, 3))
    work = np.empty((14, 4))
    for k in range(n):
        if not fused[k]:
            continue
        j = n - 1 - k
        # the backward prior's attitude and its covariance (world frame)
        if measured[k]:
            if k + 1 < n:
                q_next, b_next, P_next = q_b[j - 1], b_b[j - 1], P_b[j - 1]
            else:
                q_next, b_next, P_next = q_after, b_after, P_after
            if right:  # to the left error
                _turn_covariance(q_next, P_next, True, R, A, Pw)
                P_next = Pw
            _predicted_attitude(
                q_next,
                b_next,
                P_next,
                gyro_next[k],
                dt[k],
                gyro_noise_density,
                gyro_scale_noise_density,
                gyro_bias_random_walk,
                prior_q,
                Pb,
                work,
            )
        else:
            for i in range(4):
                prior_q[i] = q_b[j, i]
            if right:  # (Pw is the forward covariance's only after this)
                _turn_covariance(q_b[j], P_b[j], True, R, A, Pw)
                for r in range(3):
                    for c in range(3):
                        Pb[r, c] = Pw[r, c]
            else:
                for r in range(3):
                    for c in range(3):
                        Pb[r, c] = P_b[j, r, c]
        # the forward covariance in the world frame
        if right:
            _turn_covariance(q_f[k], P_f[k], True, R, A, Pw)
        else:
            for r in range(6):
                for c in range(6):
                    Pw[r, c] = P_f[k, r, c]
        # d = chart⁻¹(q_b q_f⁻¹)
        so3.quat_conjugate_into(q_f[k], conjugate)
        so3.quat_multiply_into(prior_q, conjugate, error)
        chart_log_into(error, CHART_HEADING_TILT, d)
        if heading[k] != TILT:
            m = 3
            if heading[k] == BACKWARD_HEADING:  # (world axes: z is heading)
                Pw[2, 2] += MAX_HEADING_VAR
            for r in range(3):
                for c in range(3):
                    S[r, c] = Pw[r, c] + Pb[r, c]
        else:
            m = 2
            cz, sz = math.cos(d[2]), math.sin(d[2])
            xx, xy, yy = Pb[0, 0], Pb[0, 1], Pb[1, 1]
            S[0, 0] = Pw[0, 0] + cz * cz * xx + 2.0 * cz * sz * xy + sz * sz * yy
            S[1, 1] = Pw[1, 1] + sz * sz * xx - 2.0 * cz * sz * xy + cz * cz * yy
            S[0, 1] = Pw[0, 1] + (cz * cz - sz * sz) * xy + cz * sz * (yy - xx)
            S[1, 0] = S[0, 1]
        _symmetric_inverse(S, m, S_inverse)
        # K = P Hᵀ S⁻¹ (6 × m), x = K d, P ← P − K H P
        for r in range(6):
            for c in range(m):
                total = 0.0
                for i in range(m):
                    total += Pw[r, i] * S_inverse[i, c]
                K[r, c] = total
        for r in range(6):
            total = 0.0
            for c in range(m):
                total += K[r, c] * d[c]
            x[r] = total
        for r in range(6):
            for c in range(r, 6):
                total = 0.0
                for i in range(m):
                    total += K[r, i] * Pw[c, i]
                A[r, c] = total
        for r in range(6):
            for c in range(r, 6):
                value = 0.5 * ((Pw[r, c] - A[r, c]) + (Pw[c, r] - A[r, c]))
                Pw[r, c] = value
                Pw[c, r] = value
        # the fused error into the forward reference
        for i in range(4):
            prior_q[i] = q_f[k, i]
        retract_into(prior_q, x[:3], ERROR_LEFT, CHART_HEADING_TILT, q_f[k], work4)
        for i in range(3):
            b_f[k, i] += x[3 + i]
        if right:  # back to the body frame of the smoothed attitude: Rᵀ P_θθ R, Rᵀ P_θb
            _turn_covariance(q_f[k], Pw, False, R, A, P_f[k])
            for r in range(6):  # (symmetric to rounding; made exactly so)
                for c in range(r + 1, 6):
                    value = 0.5 * (P_f[k, r, c] + P_f[k, c, r])
                    P_f[k, r, c] = value
                    P_f[k, c, r] = value
        else:
            for r in range(6):
                for c in range(6):
                    P_f[k, r, c] = Pw[r, c]


@kernel
def _symmetric_inverse(S: np.ndarray, m: int, out: np.ndarray) -> None:
    """out[:m, :m] = S[:m, :m]⁻¹ for a symmetric positive definite 2 × 2 or 3 × 3."""
    if m == 2:
        det = S[0, 0] * S[1, 1] - S[0, 1] * S[0, 1]
        out[0, 0] = S[1, 1] / det
        out[1, 1] = S[0, 0] / det
        out[0, 1] = out[1, 0] = -S[0, 1] / det
        return
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    e, f, i = S[1, 1], S[1, 2], S[2, 2]
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    out[0, 0], out[1, 1], out[2, 2] = A / det, (a * i - c * c) / det, (a * e - b * b) / det
    out[0, 1] = out[1, 0] = B / det
    out[0, 2] = out[2, 0] = C / det
    out[1, 2] = out[2, 1] = (b * c - a * f) / det
