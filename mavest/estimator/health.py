"""The filter's health: after every step a diverged or numerically broken state is
re-initialised, and heading's variance is capped.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_kernel
from mavest.estimator.alignment import accel_usable_for_alignment, align
from mavest.estimator.config import (
    MAX_ATTITUDE_VAR,
    MAX_CONSIDERED_VAR,
    MAX_GYRO_BIAS,
    MAX_HEADING_VAR,
)
from mavest.estimator.frames import (
    attitude_covariance_from_world,
    attitude_covariance_to_world,
    vector_is_finite,
)
from mavest.estimator.heading import heading_variance
from mavest.estimator.layout import N_ERROR, CoefficientsRecord, StateRecord, StepFlags
from mavest.estimator.linalg import is_positive_definite
from mavest.estimator.lowpass import restart_motion
from mavest.estimator.propagation import flush_pending

_NOT_INITIALISED = StepFlags.NOT_INITIALISED
_UNHEALTHY_RESET = StepFlags.UNHEALTHY_RESET
_DIVERGED = StepFlags.DIVERGED
_BETWEEN_UPDATES = StepFlags.BETWEEN_UPDATES

# Beyond MAX_GYRO_BIAS, MAX_ATTITUDE_VAR (any δθ axis; heading is capped at
# MAX_HEADING_VAR) and MAX_CONSIDERED_VAR the state is a numerical accident, not an
# estimate (the configuration keeps its initial state within them).
_FULL_CHECK_EVERY = 64  # checks


@inplace_kernel
def _cap_heading_variance(s: StateRecord, c: CoefficientsRecord) -> None:
    """Heading's variance at most MAX_HEADING_VAR: its row and column in world axes
    scaled by f (P ← D P D, D = diag(1, 1, f) on δθ: a congruence, so P stays definite)."""
    var = heading_variance(s, c)
    if not var > MAX_HEADING_VAR:
        return
    flush_pending(s, c)
    f = math.sqrt(MAX_HEADING_VAR / var)
    attitude_covariance_to_world(s, c)
    for j in range(c.n_state):
        s.P[2, j] *= f
        s.P[j, 2] *= f
    attitude_covariance_from_world(s, c)


@inplace_kernel
def state_is_plausible(s: StateRecord, c: CoefficientsRecord) -> bool:
    """Nominal finite and a unit quaternion, bias plausible, every variance within its
    bound (NaN fails every test): what a sample between updates is checked for. (There,
    with the transition pending, the considered rows are not written: the estimate's
    own variances are what can have changed.)"""
    q_norm2 = s.q[0] ** 2 + s.q[1] ** 2 + s.q[2] ** 2 + s.q[3] ** 2
    if not abs(q_norm2 - 1.0) < 1e-6:  # also NaN
        return False
    for i in range(3):
        if not abs(s.b[i]) <= MAX_GYRO_BIAS:
            return False
    n = N_ERROR if s.pending_steps > 0 else c.n_state
    for i in range(n):
        bound = MAX_CONSIDERED_VAR
        if i < N_ERROR:
            bound = MAX_ATTITUDE_VAR if i < 3 else MAX_GYRO_BIAS**2
        if not 0.0 <= s.P[i, i] <= bound:
            return False
    return True


@inplace_kernel
def state_is_healthy(s: StateRecord, c: CoefficientsRecord) -> bool:
    """:func:`state_is_plausible`, and P positive definite (LDLᵀ pivots; P is
    symmetric by construction, symmetrise runs at every update)."""
    if not state_is_plausible(s, c):
        return False
    n = c.n_state
    # The estimate's own 6×6 at every check; the whole, with the considered states, every
    # _FULL_CHECK_EVERY checks: its factorisation would add a fifth to a step. (ε and ḟ
    # are exactly zero until the low-pass holds a sample: semi-definite then.)
    s.health_checks += 1
    m = n if s.filters_primed and s.health_checks % _FULL_CHECK_EVERY == 0 else N_ERROR
    if m > N_ERROR:
        flush_pending(s, c)
    return is_positive_definite(s.P[:m, :m], s.w_health_T[:m, :m])


@inplace_kernel
def _reinitialise(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray) -> None:
    """Start again from this sample's accelerometer, keeping heading if it is finite
    (what else knows it, in 6-D?); the bias starts again from its prior, as it may
    be what went wrong. Without a usable accelerometer: uninitialised, and the
    next usable sample initialises."""
    keep_heading = vector_is_finite(s.q[1:]) and math.isfinite(s.q[0])
    restart_motion(s, c)  # (measured with the broken attitude, it may be what broke)
    if keep_heading:
        so3.quat_normalize_into(s.q)
    else:
        s.q[0] = 1.0
        for i in range(1, 4):
            s.q[i] = 0.0
    if accel_usable_for_alignment(c, accel):
        align(s, c, accel, keep_heading, False)
        s.t_accel = s.t
    else:
        level = s.w_health_level_accel  # a placeholder attitude with a valid covariance:
        level[0] = 0.0  # what a level accelerometer at rest reads
        level[1] = 0.0
        level[2] = -c.gravity
        align(s, c, level, keep_heading, False)
        s.initialised = 0
        s.flags |= _NOT_INITIALISED


@inplace_kernel
def check_health(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray) -> None:
    """After every step: re-initialise a diverged or numerically broken filter.

    P's definiteness is checked at the update samples: between them P is only
    predicted, by congruences with noise added, which keep it definite (a NaN
    spreads to a variance, which every sample's check catches).
    """
    if s.flags & _DIVERGED:
        _reinitialise(s, c, accel)
        s.divergence_resets += 1
        return
    _cap_heading_variance(s, c)
    if s.flags & _BETWEEN_UPDATES:
        healthy = state_is_plausible(s, c)
    else:
        healthy = state_is_healthy(s, c)
    if not healthy:
        _reinitialise(s, c, accel)
        s.flags |= _UNHEALTHY_RESET
        s.unhealthy_resets += 1
