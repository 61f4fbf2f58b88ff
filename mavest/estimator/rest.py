"""Rest: detecting a vehicle at rest (VQF's criteria), and the zero-rate update of the
gyro's bias that rest allows.
"""

from __future__ import annotations

import numpy as np

from mavest._jit import inplace_kernel
from mavest.estimator.frames import EPS, apply_correction
from mavest.estimator.layout import CoefficientsRecord, StateRecord
from mavest.estimator.linalg import gain_update, inverse_3x3_into
from mavest.estimator.lowpass import accel_is_valid, step_coefficients
from mavest.estimator.propagation import flush_pending

# χ² (3 dof) at 99.9 %: a "rest" whose rate disagrees this much with the bias is motion.
_ZERO_RATE_GATE = 16.27


@inplace_kernel
def detect_rest(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, accel: np.ndarray, dt: float
) -> bool:
    """VQF's rest criteria: gyro and accel stay near their low-passes for rest_min_time.

    The gyro samples since the last update are summed while the criteria hold,
    for the zero-rate update to measure their mean.
    """
    if not (c.rest_detection and accel_is_valid(accel)):
        s.rest_time = 0.0
        restart_rest_mean(s)
        return False
    step_coefficients(s, c, dt)
    alpha = s.step_coefficients[7]
    dev_g = 0.0
    dev_a = 0.0
    for i in range(3):
        s.rest_gyro_lp[i] += alpha * (gyro[i] - s.rest_gyro_lp[i])
        s.rest_accel_lp[i] += alpha * (accel[i] - s.rest_accel_lp[i])
        dev_g += (gyro[i] - s.rest_gyro_lp[i]) ** 2
        dev_a += (accel[i] - s.rest_accel_lp[i]) ** 2
    still = (
        dev_g < c.rest_gyro_threshold * c.rest_gyro_threshold
        and dev_a < c.rest_accel_threshold * c.rest_accel_threshold
    )
    if still:
        s.rest_time += dt
        for i in range(3):
            s.rest_gyro_sum[i] += gyro[i]
        s.rest_samples += 1
        s.rest_sum_time += dt
    else:
        s.rest_time = 0.0
        restart_rest_mean(s)
    return s.rest_time >= c.rest_min_time


@inplace_kernel
def restart_rest_mean(s: StateRecord) -> None:
    for i in range(3):
        s.rest_gyro_sum[i] = 0.0
    s.rest_samples = 0
    s.rest_sum_time = 0.0


@inplace_kernel
def zero_rate_update(s: StateRecord, c: CoefficientsRecord) -> None:
    """At rest the gyro measures its bias: y = ω̄_m − b̄, H = [0 I 0], V = σ_g²/T + σ_rest²,
    ω̄_m the mean of the samples since the last update (over T), all at rest."""
    flush_pending(s, c)
    n = c.n_state
    var = c.gyro_var_density / s.rest_sum_time + c.rest_rate_var
    P = s.P
    S = s.w_rest_S
    for i in range(3):
        for j in range(3):
            S[i, j] = P[3 + i, 3 + j] + (var if i == j else 0.0)
    det = inverse_3x3_into(S, s.w_rest_S_inv)
    if not det > 0.0:
        return
    y = s.w_rest_y
    for i in range(3):
        y[i] = s.rest_gyro_sum[i] / s.rest_samples - s.b[i]
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += y[i] * s.w_rest_S_inv[i, j] * y[j]
    if not nis <= _ZERO_RATE_GATE:
        return
    K = s.w_rest_K
    C = s.w_rest_C  # P Hᵀ = P[:, b]
    for i in range(n):
        for j in range(3):
            C[i, j] = P[i, 3 + j]
        for j in range(3):
            acc = 0.0
            if i < EPS:  # the considered states get no gain
                for k in range(3):
                    acc += C[i, k] * s.w_rest_S_inv[k, j]
            K[i, j] = acc
    for i in range(n):
        s.w_rest_dx[i] = K[i, 0] * y[0] + K[i, 1] * y[1] + K[i, 2] * y[2]
    gain_update(P[:n, :n], K[:n], C[:n], S, 3)
    apply_correction(s, c, s.w_rest_dx)
    s.at_rest = 1
