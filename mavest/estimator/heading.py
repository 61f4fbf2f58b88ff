"""Heading from the magnetometer: the first field sample sets it, later ones are
scalar updates gated by the field's learned reference (the measurement, and why the
gain moves heading only: :mod:`mavest.estimator.magnetic`).
"""

from __future__ import annotations

import math

import numpy as np

from mavest._jit import inplace_kernel
from mavest.estimator import magnetic
from mavest.estimator.frames import (
    EPS,
    apply_correction,
    error_frame_from_world,
    set_attitude_covariance_world,
    vector_is_finite,
    vertical_in_body,
    vertical_in_error_frame,
)
from mavest.estimator.layout import CoefficientsRecord, StateRecord, StepFlags
from mavest.estimator.linalg import gain_update
from mavest.estimator.propagation import flush_pending, update_due

_MAG_INVALID = StepFlags.MAG_INVALID
_MAG_DISTURBED = StepFlags.MAG_DISTURBED
_MAG_REJECTED = StepFlags.MAG_REJECTED
_HEADING_ALIGNED = StepFlags.HEADING_ALIGNED
_MAG_REFERENCE_CHANGED = StepFlags.MAG_REFERENCE_CHANGED
_HEADING_REOPENED = StepFlags.HEADING_REOPENED
_MAG_BETWEEN_UPDATES = StepFlags.MAG_BETWEEN_UPDATES

# A magnetometer sample counts for at most this long of field (s), however long
# since the previous one: after a pause it is one noisy sample, not a long average.
_MAG_MAX_DT = 0.1
# Time constant of the norm and dip low-pass the disturbance check looks at (s;
# VQF's magCurrentTau).
_MAG_CHECK_TIME = 0.05
# A heading set from one sample is never claimed worse than this (rad²): beyond
# it the linearised heading update would mean little anyway.
_MAX_ALIGNED_HEADING_VAR = 1.0


@inplace_kernel
def _heading_step(s: StateRecord, c: CoefficientsRecord, psi: float) -> None:
    """w_heading_dx = the error-frame vector of a turn by ψ about the world vertical."""
    error_frame_from_world(s, c, s.w_heading_M)  # world → error frame
    for i in range(c.n_state):
        s.w_heading_dx[i] = 0.0
    for i in range(3):
        s.w_heading_dx[i] = s.w_heading_M[i, 2] * psi


@inplace_kernel
def heading_variance(s: StateRecord, c: CoefficientsRecord) -> float:
    """The variance of the attitude error about the world vertical (rad²): vᵀ P_θθ v
    with v the vertical in the error frame (P[2, 2] for the left error)."""
    v0, v1, v2 = vertical_in_error_frame(s, c)
    P = s.P
    return (
        v0 * (P[0, 0] * v0 + P[0, 1] * v1 + P[0, 2] * v2)
        + v1 * (P[1, 0] * v0 + P[1, 1] * v1 + P[1, 2] * v2)
        + v2 * (P[2, 0] * v0 + P[2, 1] * v1 + P[2, 2] * v2)
    )


@inplace_kernel
def _align_heading(s: StateRecord, c: CoefficientsRecord, azimuth: float, var: float) -> None:
    """Turn the estimate so that the field's azimuth is the declination.

    Heading then has the variance of this one sample, ``var`` (what a Kalman
    update from no prior would give), at most _MAX_ALIGNED_HEADING_VAR.
    """
    _heading_step(s, c, magnetic.wrap(c.mag_declination - azimuth))
    apply_correction(s, c, s.w_heading_dx)
    var = min(var, _MAX_ALIGNED_HEADING_VAR)
    set_attitude_covariance_world(s, c, 0.0, var, False, True)


@inplace_kernel
def turn_heading(s: StateRecord, c: CoefficientsRecord, psi: float) -> None:
    """Turn the estimate by ψ about the world vertical, keeping its uncertainty.

    For a heading the magnetometer has referenced when the declination it was
    referenced to changes by ψ (the vehicle's COMPASS_DEC arriving after the
    first field sample): the estimate's error then has mean ψ about the
    vertical and the same spread, so this is a correction by ψ and its reset.
    """
    flush_pending(s, c)
    _heading_step(s, c, psi)
    apply_correction(s, c, s.w_heading_dx)


@inplace_kernel
def _start_reference(
    s: StateRecord, c: CoefficientsRecord, norm: float, dip: float, learned: float
) -> None:
    """Heading has just been set: learn the reference field afresh from this sample.

    ``learned`` is how long this sample already counts for in the reference's
    running mean (0: the next learning step takes it in).
    """
    s.mag_state = 1
    s.mag_ref_norm = norm
    s.mag_ref_dip = dip
    s.mag_learn_time = learned
    s.mag_candidate_time = 0.0
    s.mag_lp_norm = norm
    s.mag_lp_dip = dip
    s.mag_clear_time = c.mag_recovery_time


@inplace_kernel
def _track_reference(
    s: StateRecord, c: CoefficientsRecord, norm: float, dip: float, dt: float
) -> bool:
    """Learn or follow the reference field; True if this field is disturbed.

    While learning (the first mag_reference_time after heading was set) the
    reference is the running mean of norm and dip, and nothing is disturbed.
    Then the field's norm and dip, low-passed over _MAG_CHECK_TIME so that
    noise neither hides nor fakes a disturbance, are checked against the
    reference. A disturbed field that stays steady (within the tolerances of
    its own running mean) for mag_new_reference_time becomes the reference:
    the vehicle moved somewhere else, the field did not pass by.
    """
    alpha = min(dt / _MAG_CHECK_TIME, 1.0)
    s.mag_lp_norm += alpha * (norm - s.mag_lp_norm)
    s.mag_lp_dip += alpha * (dip - s.mag_lp_dip)
    if s.mag_state == 1:
        weight = dt / (s.mag_learn_time + dt)
        s.mag_ref_norm += weight * (norm - s.mag_ref_norm)
        s.mag_ref_dip += weight * (dip - s.mag_ref_dip)
        s.mag_learn_time += dt
        if s.mag_learn_time >= c.mag_reference_time:
            s.mag_state = 2
        return False
    norm, dip = s.mag_lp_norm, s.mag_lp_dip
    tolerance = c.mag_norm_tolerance
    disturbed = (
        abs(norm - s.mag_ref_norm) > tolerance * s.mag_ref_norm
        or abs(dip - s.mag_ref_dip) > c.mag_dip_tolerance
    )
    if not disturbed:
        s.mag_candidate_time = 0.0
        if c.mag_reference_adapt_time > 0.0:
            alpha = min(dt / c.mag_reference_adapt_time, 1.0)
            s.mag_ref_norm += alpha * (norm - s.mag_ref_norm)
            s.mag_ref_dip += alpha * (dip - s.mag_ref_dip)
        return False
    steady = (
        s.mag_candidate_time > 0.0
        and abs(norm - s.mag_candidate_norm) <= tolerance * s.mag_candidate_norm
        and abs(dip - s.mag_candidate_dip) <= c.mag_dip_tolerance
    )
    if steady:
        weight = dt / (s.mag_candidate_time + dt)
        s.mag_candidate_norm += weight * (norm - s.mag_candidate_norm)
        s.mag_candidate_dip += weight * (dip - s.mag_candidate_dip)
        s.mag_candidate_time += dt
    else:
        s.mag_candidate_norm = norm
        s.mag_candidate_dip = dip
        s.mag_candidate_time = dt
    if s.mag_candidate_time >= c.mag_new_reference_time:
        s.mag_ref_norm = s.mag_candidate_norm
        s.mag_ref_dip = s.mag_candidate_dip
        s.mag_candidate_time = 0.0
        s.flags |= _MAG_REFERENCE_CHANGED
        return False
    return True


@inplace_kernel
def mag_update(s: StateRecord, c: CoefficientsRecord, t: float, mag: np.ndarray, dt: float) -> None:
    """Heading from the magnetometer (:mod:`mavest.estimator.magnetic`); NaN mag: none.

    The first usable sample sets heading; later ones are scalar updates,
    gated by the field's norm and dip against the reference and by the
    innovation's χ², that move heading and the bias about the world vertical
    only. The gain comes from the heading term H_ψ with the tilt leak counted
    as noise (inflated for its slowness, ``mag_tilt_leak_time``); the
    covariance is the Joseph form for that gain with the full H, so it is the
    true covariance of the estimate the gain makes, leak included.
    """
    if not vector_is_finite(mag):
        if not (math.isnan(mag[0]) and math.isnan(mag[1]) and math.isnan(mag[2])):
            s.flags |= _MAG_INVALID  # a reading, but a corrupt one (inf, or NaN in part)
        return  # (all NaN: no magnetometer in this sample)
    if s.mag_state != 0 and not update_due(c, t - s.t_mag, dt):
        s.flags |= _MAG_BETWEEN_UPDATES  # (its own schedule: the field may come at its own rate)
        return
    clear_heading_report(s)
    flush_pending(s, c)
    m = s.w_heading_field
    magnetic.calibrate_into(mag, c.mag_offsets, c.mag_soft_iron, m)
    azimuth, dip, norm = magnetic.field_geometry(s.q, m, s.w_heading_world_field)
    if not (norm > 0.0 and math.isfinite(azimuth)):
        s.flags |= _MAG_INVALID
        return
    dt_mag = t - s.t_mag if s.t_mag > -math.inf else dt
    dt_mag = max(min(dt_mag, _MAG_MAX_DT), 1e-6)
    s.t_mag = t
    if s.mag_state == 0:
        _align_heading(s, c, azimuth, c.mag_heading_var_density / dt_mag)
        _start_reference(s, c, norm, dip, dt_mag)
        s.t_mag_used = t
        s.heading_innovation = magnetic.wrap(azimuth - c.mag_declination)
        s.mag_used = 1
        s.flags |= _HEADING_ALIGNED
        return
    if s.t_mag_used == -math.inf:  # heading given by initialise(): the first field seen
        _start_reference(s, c, norm, dip, 0.0)
        s.t_mag_used = t
    disturbed = _track_reference(s, c, norm, dip, dt_mag)
    s.mag_clear_time = 0.0 if disturbed else s.mag_clear_time + dt_mag
    disturbed = s.mag_clear_time < c.mag_recovery_time
    gate = c.mag_gate
    if c.mag_max_rejection_time > 0.0 and t - s.t_mag_used > c.mag_max_rejection_time:
        # rejected this long: more likely heading is off than the field; heading
        # gets its initial uncertainty (if it claims less) and the field is used
        s.flags |= _HEADING_REOPENED
        if heading_variance(s, c) < c.mag_reopened_heading_var:
            set_attitude_covariance_world(s, c, 0.0, c.mag_reopened_heading_var, False, True)
        s.mag_candidate_time = 0.0
        s.mag_clear_time = c.mag_recovery_time
        disturbed = False
        gate = 0.0
    nu = magnetic.wrap(azimuth - c.mag_declination)
    # The measurement: y = H δx + w, H = (H_τ, −1) in world axes, the tilt
    # error leaking into the azimuth through the dip (H_τ = tan(dip)·(cos d, sin d)).
    # H is taken at the reference field (its learned dip), the prediction, not
    # at this sample's dip: that carries the tilt error and the noise, and a
    # gain made from it grew with the very leak it discounts (mavest.estimator.magnetic).
    Hf = s.w_heading_H  # the full H (error frame)
    Hp = s.w_heading_H_psi  # its heading part H_ψ (the same at zero dip)
    magnetic.heading_jacobians_into(
        s.q, s.mag_ref_dip, c.mag_declination, c.error, s.w_heading_R, Hf, Hp
    )
    n = c.n_state
    P = s.P
    C = s.w_heading_C
    K = s.w_heading_K
    var_mag = c.mag_heading_var_density / dt_mag
    # The azimuth noise turns the horizontal field the tilt leaks along, by an
    # angle of variance var_mag: on average the leak is e^(−var_mag/2) H_τ τ
    # (the expected Jacobian), and the rest of its variance, (1 − e^(−var_mag))
    # of (H − H_ψ) P (H − H_ψ)ᵀ, is as white as that noise.
    along_noise = math.exp(-0.5 * var_mag)
    leak = 0.0
    for i in range(3):
        for j in range(3):
            leak += (Hf[i] - Hp[i]) * P[i, j] * (Hf[j] - Hp[j])
    var_mag += (1.0 - along_noise * along_noise) * leak
    leak *= along_noise * along_noise
    for i in range(3):
        Hf[i] = Hp[i] + along_noise * (Hf[i] - Hp[i])
    # The gain's innovation variance: heading's, the noise, and the mean leak
    # (H − H_ψ) P (H − H_ψ)ᵀ counted as noise — not through P's tilt–heading
    # correlation (see mavest.estimator.magnetic for why) — and, being a slowly
    # varying error (tilt corrects over ~mag_tilt_leak_time), as white noise
    # of the same low-frequency power: a sample counts the leak's variance ×
    # mag_tilt_leak_time/Δt.
    S = var_mag + leak * max(1.0, c.mag_tilt_leak_time / dt_mag)
    for i in range(n):
        C[i, 0] = P[i, 0] * Hp[0] + P[i, 1] * Hp[1] + P[i, 2] * Hp[2]
        if i < 3:
            S += Hp[i] * C[i, 0]
    nis = nu * nu / S
    s.heading_innovation = nu
    s.heading_nis = nis
    if disturbed:
        s.flags |= _MAG_DISTURBED
        s.mag_disturbances += 1
        return
    if gate > 0.0 and not nis <= gate:
        s.flags |= _MAG_REJECTED
        s.mag_disturbances += 1
        return
    # K = C / S moving heading and the bias about the world vertical only:
    # tilt and the horizontal bias are considered (a disturbed field must
    # never tilt the estimate, nor teach the bias what gravity corrects), as
    # are the low-pass states, as in every update
    v0, v1, v2 = vertical_in_error_frame(s, c)
    along = (v0 * C[0, 0] + v1 * C[1, 0] + v2 * C[2, 0]) / S
    K[0, 0], K[1, 0], K[2, 0] = v0 * along, v1 * along, v2 * along
    v0, v1, v2 = vertical_in_body(s)  # the bias is a body-frame vector
    along = (v0 * C[3, 0] + v1 * C[4, 0] + v2 * C[5, 0]) / S
    K[3, 0], K[4, 0], K[5, 0] = v0 * along, v1 * along, v2 * along
    for i in range(EPS, n):
        K[i, 0] = 0.0
    # The covariance for this gain and the real measurement: the Joseph form
    # with the full H, C = P Hᵀ, S = H P Hᵀ + R, so that what the leak and
    # the tilt–heading correlation do to the estimate is in P
    S_full = var_mag
    for i in range(n):
        C[i, 0] = P[i, 0] * Hf[0] + P[i, 1] * Hf[1] + P[i, 2] * Hf[2]
        if i < 3:
            S_full += Hf[i] * C[i, 0]
    s.w_heading_S[0, 0] = S_full
    gain_update(P[:n, :n], K[:n], C[:n], s.w_heading_S, 1)
    for i in range(n):
        s.w_heading_dx[i] = K[i, 0] * nu
    apply_correction(s, c, s.w_heading_dx)
    s.mag_used = 1
    s.t_mag_used = t


@inplace_kernel
def clear_heading_report(s: StateRecord) -> None:
    s.heading_innovation = math.nan
    s.heading_nis = math.nan
