"""The filter recursion: predict → reset → update → reset (Mueller, Hehn, D'Andrea 2017).

One sample (:func:`step`): the prediction with the gyroscope; when an update is due,
the zero-rate update at rest and the gravity update, the magnetometer's on its own
schedule, each followed by its reset; then the health check. Each rule is in one
module of :mod:`mavest.estimator`:

    frames          the nominal and its error, the reset, covariances between frames
    propagation     prediction, process noise, the pending transition, the schedule
    lowpass         the low-passed accelerometer, its errors, the velocity model
    gravity_update  the gravity update (iterated, sigma-point) and its robustness
    heading         the magnetometer's heading update and its field reference
    rest            rest detection, the zero-rate update of the bias
    alignment       the attitude from the accelerometer alone, the filters primed
    health          divergence and numerical checks, re-initialisation
    recursion       the step: its order, initialisation, the timeline, accel units

beside the measurement models (:mod:`~mavest.estimator.gravity`,
:mod:`~mavest.estimator.magnetic`) and the charts (:mod:`~mavest.estimator.charts`).

Every array the recursion touches lives in the state record ``s``; nothing is
allocated per sample. Its scratch buffers are each one module's own
(:data:`~mavest.estimator.layout.SCRATCH_OWNERS`).
"""

from __future__ import annotations

import math

import numpy as np

from mavest._jit import inplace_kernel
from mavest.estimator.alignment import (
    accel_usable_for_alignment,
    align,
    gyro_clipped,
    prime_filters,
    realign_when_calm,
)
from mavest.estimator.config import MAX_SPECIFIC_FORCE, STANDARD_GRAVITY
from mavest.estimator.frames import gyro_is_valid, vector_is_finite, within
from mavest.estimator.gravity_update import accel_update, clear_gravity_report
from mavest.estimator.heading import clear_heading_report, heading_variance, mag_update
from mavest.estimator.health import check_health
from mavest.estimator.layout import N_ERROR, CoefficientsRecord, StateRecord, StepFlags
from mavest.estimator.linalg import copy_into, symmetrise
from mavest.estimator.lowpass import accel_is_valid, take_accel
from mavest.estimator.propagation import flush_pending, predict, update_due
from mavest.estimator.rest import detect_rest, restart_rest_mean, zero_rate_update
from mavest.timeline import confirmations_kernel, far_off_kernel

_INITIALISED = StepFlags.INITIALISED
_NOT_INITIALISED = StepFlags.NOT_INITIALISED
_GYRO_INVALID = StepFlags.GYRO_INVALID
_ACCEL_INVALID = StepFlags.ACCEL_INVALID
_ACCEL_REJECTED_NORM = StepFlags.ACCEL_REJECTED_NORM
_TIME_NOT_INCREASING = StepFlags.TIME_NOT_INCREASING
_GAP_REALIGNED = StepFlags.GAP_REALIGNED
_GYRO_CLIPPED = StepFlags.GYRO_CLIPPED
_BETWEEN_UPDATES = StepFlags.BETWEEN_UPDATES
_MAG_SET_ASIDE = StepFlags.MAG_SET_ASIDE
_TIME_OFF_TIMELINE = StepFlags.TIME_OFF_TIMELINE
_TIME_RESTARTED = StepFlags.TIME_RESTARTED
_ACCEL_WRONG_UNIT = StepFlags.ACCEL_WRONG_UNIT

# The units other than m/s² that an accelerometer's readings come in, as (name, m/s²
# per unit): the g itself (norm ≈ 1), mg (≈ 1000, MAVLink's raw messages) and mm/s²
# (≈ 9807). Told by the norm of the first samples (StepFlags.ACCEL_WRONG_UNIT): the
# filter never aligns on them and would otherwise say nothing but NOT_INITIALISED.
ACCEL_UNITS = (
    ("g", STANDARD_GRAVITY),
    ("mg", STANDARD_GRAVITY / 1000.0),
    ("mm/s²", 0.001),
)
_UNIT_SCALES = (ACCEL_UNITS[0][1], ACCEL_UNITS[1][1], ACCEL_UNITS[2][1])
# A norm within this fraction of g in a unit is g in that unit (units 10³ apart; at rest
# an accelerometer's norm is within a few % of g, and in m/s² a norm of 1 ± 0.15 is a
# fall, not the hover or rest a stream starts in).
_UNIT_TOLERANCE = 0.15
# The verdict is on the first samples that do not align, over at least this long and
# this many: the unit is theirs when more than half of them are g in it, that is,
# when their median norm is.
_UNIT_WINDOW = 0.5  # s
_UNIT_MIN_SAMPLES = 5


@inplace_kernel
def step(
    s: StateRecord,
    c: CoefficientsRecord,
    t: float,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray,
    linear_accel: np.ndarray,
) -> None:
    """Process one IMU sample taken at time t (s): gyro (rad/s), accel (m/s²), mag (µT), FRD.

    ``linear_accel`` is the vehicle's acceleration relative to the Earth (m/s²,
    NED) when it is known at this sample (from GPS velocity), NaN when not.
    The gyro sample is held over (t_prev, t]; a NaN magnetometer means none in
    this sample. Samples that cannot be used are skipped and say why in
    ``s.flags``; the estimate stays finite throughout.
    """
    copy_into(s.linear_accel, linear_accel)
    if not within(linear_accel, MAX_SPECIFIC_FORCE):  # (also NaN: unknown)
        # beyond any vehicle's: a corrupt value, not knowledge of the acceleration
        s.linear_accel[0] = math.nan
    _step_sample(s, c, t, gyro, accel, mag)
    if s.initialised:
        check_health(s, c, accel)  # (its LDLᵀ reads one triangle)
    # The structured products round the two triangles differently: the whole P is
    # made symmetric at the updates, the estimate's own 6×6 at every sample.
    symmetrise(
        s.P[:N_ERROR, :N_ERROR] if s.flags & _BETWEEN_UPDATES else s.P[: c.n_state, : c.n_state]
    )


@inplace_kernel
def _set_aside_mag(s: StateRecord, mag: np.ndarray) -> None:
    """The sample's magnetometer reading, if it has one, is not looked at (the attitude
    it would correct is not known): say so."""
    if vector_is_finite(mag):
        s.flags |= _MAG_SET_ASIDE


@inplace_kernel
def _initialise(
    s: StateRecord,
    c: CoefficientsRecord,
    t: float,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray,
) -> None:
    """Not initialised: set the attitude from this sample's accelerometer if it can,
    else say why not."""
    if math.isfinite(t) and gyro_is_valid(gyro) and accel_usable_for_alignment(c, accel):
        align(s, c, accel, False, False)
        s.initialised = 1
        s.t = t
        s.t_accel = t
        s.samples += 1
        s.flags = _INITIALISED
        s.accel_used = 1
        mag_update(s, c, t, mag, 0.0)
    else:
        # why not: what a sample would be skipped for, or an accelerometer that is not
        # gravity (in another unit, or in motion)
        s.flags = _NOT_INITIALISED
        if not math.isfinite(t):
            s.flags |= _TIME_NOT_INCREASING
        if not gyro_is_valid(gyro):
            s.flags |= _GYRO_INVALID
        if not accel_is_valid(accel):
            s.flags |= _ACCEL_INVALID
        elif not accel_usable_for_alignment(c, accel):
            s.flags |= _ACCEL_REJECTED_NORM
        if s.samples == 0 and _judge_accel_unit(s, c, t, accel):
            s.flags |= _ACCEL_WRONG_UNIT


@inplace_kernel
def accel_unit_of(norm: float, gravity: float) -> int:
    """The index in ACCEL_UNITS of the unit in which an accelerometer's ``norm`` is one
    g (``gravity``, m/s²), within the tolerance; −1 for none (the units are 10³ apart:
    at most one is)."""
    for k in range(len(_UNIT_SCALES)):
        if abs(norm * _UNIT_SCALES[k] - gravity) <= _UNIT_TOLERANCE * gravity:
            return k
    return -1


@inplace_kernel
def _judge_accel_unit(s: StateRecord, c: CoefficientsRecord, t: float, accel: np.ndarray) -> bool:
    """Take a sample that did not align, before any did, into the verdict on the
    accelerometer's unit (ACCEL_UNITS); whether it is in one of those."""
    if s.accel_unit != 0:
        return s.accel_unit > 0
    norm = math.sqrt(accel[0] ** 2 + accel[1] ** 2 + accel[2] ** 2)
    if not (math.isfinite(t) and math.isfinite(norm) and norm > 0.0):
        return False
    if s.unit_samples == 0:
        s.unit_t0 = t
    s.unit_samples += 1
    k = accel_unit_of(norm, c.gravity)
    if k >= 0:
        s.unit_votes[k] += 1
        s.unit_norm_sum[k] += norm
    if s.unit_samples < _UNIT_MIN_SAMPLES or not t - s.unit_t0 >= _UNIT_WINDOW:
        return False
    s.accel_unit = -1
    for k in range(len(_UNIT_SCALES)):
        if 2 * s.unit_votes[k] > s.unit_samples:
            s.accel_unit = k + 1
    return s.accel_unit > 0


@inplace_kernel
def _new_timeline_confirmed(s: StateRecord, c: CoefficientsRecord, t: float) -> bool:
    """Count a sample far off the timeline towards a new one (mavest.timeline); True
    once it is confirmed. An infinite time never is, however few confirm."""
    if not math.isfinite(t):
        return False
    s.timeline_count = confirmations_kernel(s.timeline_count, t - s.t_timeline, c.timeline_max_step)
    s.t_timeline = t
    if s.timeline_count < c.timeline_confirm:
        return False
    s.timeline_count = 0
    return True


@inplace_kernel
def _restart_timeline(s: StateRecord, c: CoefficientsRecord) -> None:
    """Time went back and stayed back: forget what happened at times on the old
    timeline, as a fresh estimator would not know it; the next alignment starts
    again (bias from its prior, heading from the next magnetometer sample)."""
    flush_pending(s, c)
    s.initialised = 0
    s.t = -math.inf
    s.t_accel = -math.inf
    s.t_update = -math.inf
    s.t_mag = -math.inf
    s.t_mag_used = -math.inf
    s.t_reopened = -math.inf
    s.clip_calm_time = -1.0
    s.mag_state = 0


@inplace_kernel
def _step_sample(
    s: StateRecord,
    c: CoefficientsRecord,
    t: float,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray,
) -> None:
    s.flags = 0
    s.accel_used = 0
    s.mag_used = 0
    s.iterations = 0
    s.at_rest = 0
    if not s.initialised:
        clear_gravity_report(s)
        clear_heading_report(s)
        _initialise(s, c, t, gyro, accel, mag)
        return
    dt = t - s.t
    if gyro_is_valid(gyro) and far_off_kernel(dt, c.reorder_window, c.max_jump):
        if not _new_timeline_confirmed(s, c, t):
            s.flags = _TIME_OFF_TIMELINE
            clear_gravity_report(s)
            clear_heading_report(s)
            return
        if not dt > 0.0:  # time went back and stayed: the clock restarted
            _restart_timeline(s, c)
            _initialise(s, c, t, gyro, accel, mag)
            s.flags |= _TIME_RESTARTED
            return
        # forward, and it stayed: a gap (below)
    if not dt > 0.0 or not gyro_is_valid(gyro):  # (also NaN)
        s.flags = _TIME_NOT_INCREASING if not dt > 0.0 else _GYRO_INVALID
        clear_gravity_report(s)
        clear_heading_report(s)
        return
    s.timeline_count = 0  # on the timeline: a far-off sample before was a corrupted one
    s.samples += 1
    if dt > c.max_dt:
        clear_gravity_report(s)
        clear_heading_report(s)
        flush_pending(s, c)
        # Nothing is known of the motion in the gap: re-align tilt from this
        # sample's accelerometer, keep heading and bias (which drift slowly).
        if accel_usable_for_alignment(c, accel):
            for i in range(3):
                # known no worse than before any data: a clock that jumped by years and
                # stayed (boot time turned Unix time) would grow it past the health
                # check's bound, and the bias learned would be thrown away
                grown = s.P[3 + i, 3 + i] + c.bias_var_density * dt
                s.P[3 + i, 3 + i] = max(s.P[3 + i, 3 + i], min(grown, c.initial_bias_var))
            align(s, c, accel, True, True)
            s.t = t
            s.t_accel = t
            s.flags = _GAP_REALIGNED
            s.accel_used = 1
        else:
            s.initialised = 0
            s.flags = _GAP_REALIGNED | _NOT_INITIALISED
        _set_aside_mag(s, mag)
        return
    predict(s, c, gyro, dt)
    s.t = t
    if gyro_clipped(c, gyro):
        s.clip_calm_time = 0.0
        s.flags |= _GYRO_CLIPPED
    if vector_is_finite(s.linear_accel) and heading_variance(s, c) > c.aided_max_heading_var:
        # The known acceleration is known in the world frame: with heading this
        # uncertain, turning it into the body would be a guess, and the linear
        # model of that guess's error meaningless. Unaided until heading is known.
        s.linear_accel[0] = math.nan
    if not s.filters_primed and accel_is_valid(accel):
        prime_filters(s, c, gyro, accel, dt)
        s.filters_primed = 2  # tells accel_update the low-pass already holds this sample
    if s.clip_calm_time >= 0.0:  # nothing corrects an attitude that is not known
        clear_gravity_report(s)
        clear_heading_report(s)
        realign_when_calm(s, c, t, gyro, accel, dt)
        _set_aside_mag(s, mag)
        return
    at_rest = detect_rest(s, c, gyro, accel, dt)
    if not update_due(c, t - s.t_update, dt):
        # not due: the sample is predicted (above) and its accelerometer averaged
        # into the low-pass, whose error the covariance carries to the next update;
        # what the last update measured is still reported
        s.flags |= _BETWEEN_UPDATES
        take_accel(s, c, accel, dt)
        mag_update(s, c, t, mag, dt)
        return
    s.t_update = t
    clear_gravity_report(s)
    if at_rest:
        zero_rate_update(s, c)
    restart_rest_mean(s)
    accel_update(s, c, t, accel, dt)
    mag_update(s, c, t, mag, dt)
