"""The attitude from the accelerometer alone: at the first usable sample, after a gap,
after a clipped gyro and after a re-initialisation; and the measurement filters primed
afresh.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_kernel
from mavest.estimator.frames import EPS, RATE, VEL, set_attitude_covariance_world
from mavest.estimator.gravity_update import MIN_ACCEL_FRACTION
from mavest.estimator.layout import N_AXES, N_ERROR, CoefficientsRecord, StateRecord, StepFlags
from mavest.estimator.linalg import copy_into
from mavest.estimator.lowpass import absorb_sample, reset_velocity_covariance
from mavest.estimator.propagation import flush_pending
from mavest.estimator.rest import restart_rest_mean

_CLIP_REALIGNED = StepFlags.CLIP_REALIGNED
_ACCEL_DEFERRED = StepFlags.ACCEL_DEFERRED


@inplace_kernel
def accel_usable_for_alignment(c: CoefficientsRecord, accel: np.ndarray) -> bool:
    norm = math.sqrt(accel[0] ** 2 + accel[1] ** 2 + accel[2] ** 2)
    return (
        math.isfinite(norm)
        and norm > MIN_ACCEL_FRACTION * c.gravity
        and abs(norm - c.gravity) <= max(c.accel_norm_tolerance, 0.0)
    )


@inplace_kernel
def align(
    s: StateRecord, c: CoefficientsRecord, accel: np.ndarray, keep_heading: bool, keep_bias: bool
) -> None:
    """Attitude from the accelerometer's gravity direction; heading kept or set to 0.

    At rest a = −g Rᵀe₃ with Rᵀe₃ = (−sin θ, sin φ cos θ, cos φ cos θ) for ZYX
    angles, hence roll φ = atan2(−a_y, −a_z), pitch θ = atan2(a_x, √(a_y² + a_z²)).
    """
    flush_pending(s, c)
    roll = math.atan2(-accel[1], -accel[2])
    pitch = math.atan2(accel[0], math.hypot(accel[1], accel[2]))
    yaw = 0.0
    if keep_heading:
        so3.euler_zyx_from_quat_into(s.q, s.w_alignment_euler)
        yaw = s.w_alignment_euler[2]
    so3.quat_from_euler_zyx_into(roll, pitch, yaw, s.q)
    so3.quat_normalize_into(s.q)
    n = c.n_state
    if not keep_bias:
        for i in range(n):
            for j in range(n):
                s.P[i, j] = 0.0
        for i in range(3):
            s.b[i] = c.initial_bias[i]
            s.P[3 + i, 3 + i] = c.initial_bias_var
    set_attitude_covariance_world(s, c, c.initial_tilt_var, c.initial_heading_var, True, True)
    reset_velocity_covariance(s, c)
    if not keep_heading:
        s.mag_state = 0  # the next magnetometer sample sets heading
    s.filters_primed = 0  # the low-passes start again with the next sample
    s.t_reopened = -math.inf


@inplace_kernel
def prime_filters(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, accel: np.ndarray, dt: float
) -> None:
    """Start the measurement low-passes again with this sample.

    Priming is the low-pass's step with no weight on its history (β = 0): f̄
    becomes this sample (ḟ = 0) and ε its error η + a, where a involves the
    velocity, which carries on with its correlations — it is the vehicle's,
    not the filter's.
    """
    flush_pending(s, c)
    copy_into(s.rest_gyro_lp, gyro)
    copy_into(s.rest_accel_lp, accel)
    s.rest_time = 0.0
    restart_rest_mean(s)
    s.filters_primed = 1
    n = c.n_state
    if n == N_ERROR:
        return
    for i in range(EPS, VEL):  # ε and ḟ start afresh
        for j in range(n):
            s.P[i, j] = 0.0
            s.P[j, i] = 0.0
    # (f̄ is cleared as well as ḟ: β = 0 weighs the old f̄ by zero, which keeps a NaN —
    # a broken attitude's — for ever)
    s.accel_world_lp[0, :] = 0.0
    s.accel_world_lp[1, :] = 0.0
    s.lowpass_time = 0.0
    absorb_sample(s, c, accel, dt, True)  # mean mode with nothing averaged yet: β = 0
    for a in range(N_AXES):  # ḟ is known to be zero; a hair keeps P definite
        s.P[RATE + a, RATE + a] = 1e-12 * s.P[EPS + a, EPS + a]


@inplace_kernel
def gyro_clipped(c: CoefficientsRecord, gyro: np.ndarray) -> bool:
    limit = c.gyro_clip
    return abs(gyro[0]) >= limit or abs(gyro[1]) >= limit or abs(gyro[2]) >= limit


# After a clipped gyro the vehicle is calm again once its rate stays under this
# (rad/s, bias removed) with ‖a‖ near g for _CALM_TIME (s): the accelerometer's
# direction is then gravity's, to within what a 30 °/s rotation adds.
_CALM_RATE = math.radians(30.0)
_CALM_TIME = 0.5


@inplace_kernel
def realign_when_calm(
    s: StateRecord,
    c: CoefficientsRecord,
    t: float,
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: float,
) -> None:
    """After a clipped gyro: wait for calm, then tilt from the accelerometer.

    The rotation the clipped samples missed is unknown, so what the filter
    believes of tilt (and its covariance) means nothing; the accelerometer of a
    tumbling vehicle means little either. Its samples (and the magnetometer's)
    are set aside until the vehicle has been calm for _CALM_TIME; that sample
    then sets tilt with its initial uncertainty, bias kept, and heading kept
    (6-D) or set again by the next magnetometer sample (9-D).
    """
    s.flags |= _ACCEL_DEFERRED
    rate2 = 0.0
    for i in range(3):
        rate2 += (gyro[i] - s.b[i]) ** 2
    if rate2 < _CALM_RATE * _CALM_RATE and accel_usable_for_alignment(c, accel):
        s.clip_calm_time += dt
    else:
        s.clip_calm_time = 0.0
    if s.clip_calm_time < _CALM_TIME:
        return
    heading_from_mag = s.mag_state != 0
    align(s, c, accel, True, True)
    if heading_from_mag:
        s.mag_state = 0  # the next field sample sets heading
    s.clip_calm_time = -1.0
    s.t_accel = t
    s.accel_used = 1
    s.flags = (s.flags & ~_ACCEL_DEFERRED) | _CLIP_REALIGNED
