"""The gravity update: the accelerometer's direction (:mod:`mavest.estimator.gravity`)
corrects tilt and the bias, iterated or sigma-point, with its robustness checks.

Update (docs/design.md#iterated-update): the MAP cost ‖r(x)‖²_V + ‖x ⊟ x̄‖²_P minimised by
Gauss–Newton with the prior-correction term (Bell & Cathey 1993; on the
manifold as IKFoM). With d_i = x_i ⊟ x̄ and T_i the reset Jacobian at d_i, the
prior seen from the iterate is N(−T_i d_i, T_i P T_iᵀ), and

    δ_i = m_i − K_i (r_i + H_i m_i),   m_i = −T_i d_i,   x_{i+1} = x_i ⊞ δ_i

with K_i the Kalman gain for T_i P T_iᵀ. One iteration is the EKF; the fixed
point (reset ``full``) is the minimiser of the MAP cost. The covariance of the
last iterate is the Joseph form, moved onto x_{i+1} by the reset T(δ_i).

With the low-pass (:mod:`mavest.estimator.lowpass`) the update measures f̄, whose
error ε enters the residual linearly, r ≈ H δθ + H_ε ε with H_ε = (1/g) B_zᵀ R̄ᵀ [e₃]×;
ε is considered: its gain rows are zero.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3, sphere
from mavest._jit import inplace_kernel
from mavest.estimator import gravity
from mavest.estimator.charts import local_into, reset_jacobian_into, retract_into
from mavest.estimator.frames import (
    EPS,
    RATE,
    apply_correction,
    move_nominal,
    reset_covariance,
    set_attitude_covariance_world,
    transform_blocks,
    vector_is_finite,
    vertical_in_error_frame,
    world_move_into,
)
from mavest.estimator.layout import (
    N_ERROR,
    UPDATE_SIGMA_POINT,
    CoefficientsRecord,
    StateRecord,
    StepFlags,
)
from mavest.estimator.linalg import copy_into, copy_matrix_into, gain_update
from mavest.estimator.lowpass import take_accel
from mavest.estimator.propagation import flush_pending, sigma_points

_ACCEL_INVALID = StepFlags.ACCEL_INVALID
_ACCEL_REJECTED_NORM = StepFlags.ACCEL_REJECTED_NORM
_ACCEL_DISTURBED = StepFlags.ACCEL_DISTURBED
_TILT_REOPENED = StepFlags.TILT_REOPENED
_LOWPASS_RESTARTED = StepFlags.LOWPASS_RESTARTED
_ACCEL_DEFERRED = StepFlags.ACCEL_DEFERRED
_DIVERGED = StepFlags.DIVERGED

# Accelerometer readings below this fraction of g carry no usable direction.
MIN_ACCEL_FRACTION = 0.05
# A floor under the measurement variance, so that S stays invertible (the
# low-passed measurement's noise lives in ε).
_MIN_DIRECTION_VAR = 1e-14


@inplace_kernel
def _gravity_leaves_heading(s: StateRecord) -> bool:
    """Whether the gravity update considers heading (:func:`_drop_heading_gain`).

    With a magnetometer referencing heading, and no known acceleration in
    the sample. Without a magnetometer (6-D) heading is free, and the gain
    keeps the Kalman filter's own share: P's tilt–heading correlation is
    then the prediction's and the reset's alone.
    """
    return s.t_mag_used > -math.inf and not vector_is_finite(s.linear_accel)


@inplace_kernel
def _drop_heading_gain(s: StateRecord, c: CoefficientsRecord, K: np.ndarray, m: int) -> None:
    """K's attitude rows (n×m) lose their component about the world vertical.

    Called for the gravity update when :func:`_gravity_leaves_heading`: it
    then moves tilt and bias only, heading being *considered* in it
    (Schmidt), as tilt is in the magnetometer's. Gravity alone says nothing
    about heading; what it would move there comes only through P's
    tilt–heading correlation, which the magnetometer's honest covariance
    (:func:`~mavest.estimator.heading.mag_update`) makes large and which a
    disturbed or lagging field on fast rotations makes wrong. (With the
    acceleration known the sample does see heading, in turns —
    :mod:`~mavest.estimator.lowpass` — and the gain keeps it.) The covariance
    stays the Joseph form for the gain used (:func:`_joseph_update`,
    :func:`gain_update`).
    """
    v0, v1, v2 = vertical_in_error_frame(s, c)
    for a in range(m):
        along = v0 * K[0, a] + v1 * K[1, a] + v2 * K[2, a]
        K[0, a] -= v0 * along
        K[1, a] -= v1 * along
        K[2, a] -= v2 * along


@inplace_kernel
def _gravity_residual(s: StateRecord, q: np.ndarray, r: np.ndarray) -> None:
    gravity.residual_into(
        q,
        s.w_gravity_update_z,
        s.w_gravity_update_Bz,
        r,
        s.w_gravity_update_R,
        s.w_gravity_update_h,
        s.w_gravity_update_rho,
    )


@inplace_kernel
def _gravity_jacobian(s: StateRecord, c: CoefficientsRecord) -> None:
    """H (w_gravity_update_H) = [H_θ, 0, H_ε] at the point where
    :func:`_gravity_residual` left R̄ and h."""
    H = s.w_gravity_update_H
    R = s.w_gravity_update_R
    Bz = s.w_gravity_update_Bz
    gravity.jacobian_into(
        R,
        s.w_gravity_update_h,
        s.w_gravity_update_z,
        Bz,
        c.error,
        H,
        s.w_gravity_update_m33,
        s.w_gravity_update_n33,
    )
    if c.n_state == N_ERROR:
        return
    # H_ε = (1/g) B_zᵀ R̄ᵀ [e₃]×: R̄ᵀ[e₃]× e_x = R̄ᵀ e_y, e_y ↦ −R̄ᵀ e_x (e_z ↦ 0,
    # which is why ε_z is not carried); the low-pass's rate is not measured
    inv_g = 1.0 / c.gravity
    for k in range(2):
        for i in range(RATE, c.n_state):
            H[k, i] = 0.0
        H[k, EPS] = inv_g * (Bz[0, k] * R[1, 0] + Bz[1, k] * R[1, 1] + Bz[2, k] * R[1, 2])
        H[k, EPS + 1] = -inv_g * (Bz[0, k] * R[0, 0] + Bz[1, k] * R[0, 1] + Bz[2, k] * R[0, 2])


@inplace_kernel
def _solve_gain(s: StateRecord, c: CoefficientsRecord, Pi: np.ndarray, var: float) -> float:
    """C = Pi Hᵀ, S = H C + var I, K = C S⁻¹ (w_gravity_update_C, _S, _K); returns the
    NIS of the residual r (w_gravity_update_r).

    The gravity Jacobian (:func:`_gravity_jacobian`) is zero on the bias, ḟ and
    v: the sums run over its other columns only (δθ, ε_x, ε_y), in
    the order of the full sums, which the exact zeros left unchanged. K's
    considered rows are zero (Schmidt: ε's mean is never estimated).
    """
    n = c.n_state
    H = s.w_gravity_update_H
    C = s.w_gravity_update_C
    K = s.w_gravity_update_K
    S = s.w_gravity_update_S
    considered = n > N_ERROR
    for i in range(n):
        for k in range(2):
            acc = 0.0
            for j in range(3):
                acc += Pi[i, j] * H[k, j]
            if considered:
                acc += Pi[i, EPS] * H[k, EPS]
                acc += Pi[i, EPS + 1] * H[k, EPS + 1]
            C[i, k] = acc
    for a in range(2):
        for b in range(2):
            acc = var if a == b else 0.0
            for j in range(3):
                acc += H[a, j] * C[j, b]
            if considered:
                acc += H[a, EPS] * C[EPS, b]
                acc += H[a, EPS + 1] * C[EPS + 1, b]
            S[a, b] = acc
    s01 = 0.5 * (S[0, 1] + S[1, 0])
    S[0, 1] = s01
    S[1, 0] = s01
    s00, s11 = S[0, 0], S[1, 1]
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    for i in range(N_ERROR):
        K[i, 0] = C[i, 0] * i00 + C[i, 1] * i01
        K[i, 1] = C[i, 0] * i01 + C[i, 1] * i11
    for i in range(N_ERROR, n):
        K[i, 0] = 0.0
        K[i, 1] = 0.0
    if _gravity_leaves_heading(s):
        _drop_heading_gain(s, c, K, 2)
    r0, r1 = s.w_gravity_update_r[0], s.w_gravity_update_r[1]
    return r0 * r0 * i00 + 2.0 * r0 * r1 * i01 + r1 * r1 * i11


@inplace_kernel
def _joseph_update(s: StateRecord, c: CoefficientsRecord, Pi: np.ndarray, from_prior: bool) -> None:
    """P = (I − K H) Pi (I − K H)ᵀ + K V Kᵀ with the considered rows of K zero.

    The Joseph form is the covariance for any gain, so it stays exact for the
    Schmidt gain, which leaves ε's mean (and so its rows of K) alone. It is
    evaluated as the rank-2 update of Pi (:func:`gain_update`); ``from_prior``:
    Pi is P itself (a single iteration), which is then updated in place.
    """
    n = c.n_state
    P = s.P[:n, :n]
    if not from_prior:
        copy_matrix_into(P, Pi)
    gain_update(P, s.w_gravity_update_K[:n], s.w_gravity_update_C[:n], s.w_gravity_update_S, 2)


@inplace_kernel
def _iterated_update(s: StateRecord, c: CoefficientsRecord, var: float, gate: float) -> bool:
    """Gauss–Newton on the MAP cost (one iteration: the EKF). False if gated out.

    The considered ε stays at its mean 0 in every iterate: it enters the
    residual linearly, so the attitude and bias iterates do not depend on it
    (m_ε = −ε cancels H_ε ε in r + H m), and every linearisation point — the
    last one, whose Joseph form gives the covariance, included — is one where
    ε's estimate is what the Schmidt filter keeps, zero.
    """
    n = c.n_state
    prior_q = s.w_gravity_update_prior_q
    prior_b = s.w_gravity_update_prior_b
    copy_into(prior_q, s.q)
    copy_into(prior_b, s.b)
    # the prior seen from the iterate: P itself at the first (read only until
    # the Joseph form), its transport T P Tᵀ into w_gravity_update_A at later ones
    Pi = s.P[:n, :n]
    d = s.w_gravity_update_d
    m = s.w_gravity_update_m
    dx = s.w_gravity_update_dx
    H = s.w_gravity_update_H
    K = s.w_gravity_update_K
    r = s.w_gravity_update_r
    T = s.w_gravity_update_m33  # the reset Jacobian at the iterate
    W = s.w_gravity_update_W
    q4 = s.w_gravity_update_q4
    for it in range(c.max_iterations):
        if it == 0:
            for i in range(n):
                m[i] = 0.0
        else:
            local_into(s.q, prior_q, c.error, c.chart, d[:3], q4)
            for i in range(3):
                d[3 + i] = s.b[i] - prior_b[i]
            for i in range(EPS, n):
                d[i] = 0.0
            reset_jacobian_into(d[:3], c.error, c.chart, c.reset, T)
            world_move_into(s.q, prior_q, W, q4)
            Pi = s.w_gravity_update_A[:n, :n]
            copy_matrix_into(Pi, s.P[:n, :n])
            transform_blocks(s, c, Pi, T, W, True)
            # m = −T d: only δθ is transported (d's considered part is 0)
            for i in range(3):
                m[i] = -(T[i, 0] * d[0] + T[i, 1] * d[1] + T[i, 2] * d[2])
            for i in range(3, n):
                m[i] = -d[i]
        _gravity_residual(s, s.q, r)
        _gravity_jacobian(s, c)
        nis = _solve_gain(s, c, Pi, var)
        if it == 0:
            s.innovation[0] = r[0]
            s.innovation[1] = r[1]
            s.nis = nis
            if gate > 0.0 and not nis <= gate:
                return False
        # δ = m − K (r + H m), over H's non-zero columns (:func:`_solve_gain`)
        y0 = r[0]
        y1 = r[1]
        for j in range(3):
            y0 += H[0, j] * m[j]
            y1 += H[1, j] * m[j]
        if n > N_ERROR:
            for j in range(EPS, EPS + 2):
                y0 += H[0, j] * m[j]
                y1 += H[1, j] * m[j]
        for i in range(n):
            dx[i] = m[i] - K[i, 0] * y0 - K[i, 1] * y1
        # the step of the estimate (ε's is discarded), and of its attitude alone
        attitude_step2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
        step_norm2 = attitude_step2 + dx[3] * dx[3] + dx[4] * dx[4] + dx[5] * dx[5]
        move_nominal(s, c, dx)
        s.iterations = it + 1
        # Done when this step is below the tolerance, or when the next one will
        # be: Gauss–Newton converges quadratically here, the next step being
        # about the residual's curvature (order 1 per radian on S²) times
        # ‖Δθ‖². Most steps of a filter running at rate stop after one
        # iteration that way; it is the large corrections that iterate.
        tolerance = c.iteration_tolerance
        if step_norm2 <= tolerance * tolerance or attitude_step2 <= 0.1 * tolerance:
            break
    _joseph_update(s, c, Pi, s.iterations == 1)
    reset_covariance(s, c, dx)
    return True


@inplace_kernel
def _sigma_point_update(s: StateRecord, c: CoefficientsRecord, var: float, gate: float) -> bool:
    """Unscented update of the error about the nominal, then the measurement reset."""
    chi = s.w_gravity_update_sigma_chi
    if not sigma_points(s, c, chi):  # P lost definiteness: the linearised update still works
        return _iterated_update(s, c, var, gate)
    n = c.n_state
    n_sigma = 2 * n + 1
    rs = s.w_gravity_update_sigma_r
    H = s.w_gravity_update_H
    for k in range(n_sigma):
        qk = s.w_gravity_update_point_q  # the sigma point's attitude, one point at a time
        retract_into(s.q, chi[k, :3], c.error, c.chart, qk, s.w_gravity_update_q4)
        _gravity_residual(s, qk, rs[k])
        if n > N_ERROR:  # ε enters linearly: r + H_ε ε, H_ε at this point
            _gravity_jacobian(s, c)
            for i in range(EPS, n):
                rs[k, 0] += H[0, i] * chi[k, i]
                rs[k, 1] += H[1, i] * chi[k, i]
    rbar0 = c.sigma_w0_mean * rs[0, 0]
    rbar1 = c.sigma_w0_mean * rs[0, 1]
    for k in range(1, n_sigma):
        rbar0 += c.sigma_wi * rs[k, 0]
        rbar1 += c.sigma_wi * rs[k, 1]
    S = s.w_gravity_update_S
    C = s.w_gravity_update_C
    S[0, 0], S[0, 1], S[1, 0], S[1, 1] = var, 0.0, 0.0, var
    for i in range(n):
        C[i, 0] = 0.0
        C[i, 1] = 0.0
    for k in range(n_sigma):
        w = c.sigma_w0_cov if k == 0 else c.sigma_wi
        e0 = rs[k, 0] - rbar0
        e1 = rs[k, 1] - rbar1
        S[0, 0] += w * e0 * e0
        S[0, 1] += w * e0 * e1
        S[1, 1] += w * e1 * e1
        for i in range(n):  # the sigma set is symmetric about 0: E[χ] = 0, and C ≈ P Hᵀ
            C[i, 0] += w * chi[k, i] * e0
            C[i, 1] += w * chi[k, i] * e1
    S[1, 0] = S[0, 1]
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[0, 1]
    i00, i01, i11 = S[1, 1] / det, -S[0, 1] / det, S[0, 0] / det
    nis = rbar0 * rbar0 * i00 + 2.0 * rbar0 * rbar1 * i01 + rbar1 * rbar1 * i11
    s.innovation[0] = rbar0
    s.innovation[1] = rbar1
    s.nis = nis
    if gate > 0.0 and not nis <= gate:
        return False
    # K = C S⁻¹ with the considered rows zero (Schmidt); δ̂ = −K r̄ as in the EKF
    K = s.w_gravity_update_K
    for i in range(n):
        if i >= EPS:
            K[i, 0] = 0.0
            K[i, 1] = 0.0
        else:
            K[i, 0] = C[i, 0] * i00 + C[i, 1] * i01
            K[i, 1] = C[i, 0] * i01 + C[i, 1] * i11
    if _gravity_leaves_heading(s):
        _drop_heading_gain(s, c, K, 2)
    for i in range(n):
        s.w_gravity_update_dx[i] = -(K[i, 0] * rbar0 + K[i, 1] * rbar1)
    gain_update(s.P[:n, :n], K[:n], C[:n], S, 2)
    s.iterations = 1
    apply_correction(s, c, s.w_gravity_update_dx)
    return True


@inplace_kernel
def _reopen_tilt(s: StateRecord, c: CoefficientsRecord) -> None:
    """After rejecting the accelerometer too long: tilt variance back to its initial value.

    The next update then moves tilt most of the way to the accelerometer,
    while heading and bias keep what they know.
    """
    set_attitude_covariance_world(s, c, c.initial_tilt_var, c.initial_heading_var, True, False)


# The low-passed direction is used once f̄'s error σ_ε is below this fraction of g.
_LINEAR_LIMIT = 0.2
# A disturbance's extra variance fills ε's up to this fraction of that limit's.
_EPS_ROOM = 0.9


@inplace_kernel
def _linear_limit_variance(c: CoefficientsRecord) -> float:
    """(_LINEAR_LIMIT g)²: the variance of ε beyond which the low-passed direction waits."""
    return (_LINEAR_LIMIT * c.gravity) ** 2


@inplace_kernel
def _horizontal_eps_variance(s: StateRecord) -> float:
    """The larger of ε's horizontal variances, the ones the gravity update measures."""
    return max(s.P[EPS, EPS], s.P[EPS + 1, EPS + 1])


@inplace_kernel
def accel_update(
    s: StateRecord, c: CoefficientsRecord, t: float, accel: np.ndarray, dt: float
) -> None:
    """The sample into the low-pass, then the gravity-direction update with the
    robustness checks; sets the step's diagnostics."""
    if not take_accel(s, c, accel, dt):
        return
    flush_pending(s, c)
    lowpass = c.accel_lowpass_time > 0.0
    aided = vector_is_finite(s.linear_accel)
    q4 = s.w_gravity_update_q4
    f = s.w_gravity_update_f  # the specific force measured, body frame
    if lowpass:
        so3.quat_conjugate_into(s.q, q4)
        so3.quat_rotate_into(q4, s.accel_world_lp[0], f)  # R̄ᵀ f̄
    else:
        copy_into(f, accel)
        if aided:  # f − R̄ᵀa (its heading coupling is not modelled)
            so3.quat_conjugate_into(s.q, q4)
            so3.quat_rotate_into(q4, s.linear_accel, s.w_gravity_update_v3)
            for i in range(3):
                f[i] -= s.w_gravity_update_v3[i]
    norm = math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
    if not norm > MIN_ACCEL_FRACTION * c.gravity:
        s.flags |= _ACCEL_INVALID
        return
    for i in range(3):
        s.w_gravity_update_z[i] = -f[i] / norm
    sphere.tangent_basis_into(s.w_gravity_update_z, s.w_gravity_update_Bz)
    # The measurement model is first order in ε/g: while f̄'s error is a sizeable
    # fraction of g (one sample of a vehicle on the move) its direction says
    # little and not linearly; wait until it has averaged.
    if lowpass and _horizontal_eps_variance(s) > _linear_limit_variance(c):
        s.flags |= _ACCEL_DEFERRED
        return
    deviation = norm - c.gravity
    if abs(deviation) > c.accel_norm_tolerance:
        s.flags |= _ACCEL_REJECTED_NORM
        s.accel_rejections += 1
        _gravity_residual(s, s.q, s.innovation)  # still shown, not used
        return
    # direction variance: the sample's white noise σ_a²/Δt (unless it lives in ε)
    # plus what the norm deviation reveals of unmodelled acceleration, over g²
    # (not the measured ‖a‖², which the noise itself inflates: E‖a‖² = g² + 3σ²)
    inflation = c.accel_norm_inflation * deviation
    g2 = c.gravity * c.gravity
    white = 0.0 if lowpass else c.accel_var_density / dt  # with the low-pass it lives in ε
    var = max((white + inflation * inflation) / g2, _MIN_DIRECTION_VAR)
    gate = c.accel_gate
    if c.accel_max_disturbance_time > 0.0 and t - s.t_accel > c.accel_max_disturbance_time:
        # disturbed for too long: more likely the attitude is wrong than the
        # accelerometer, so tilt gets its initial uncertainty back
        if c.divergence_window > 0.0 and t - s.t_reopened < c.divergence_window:
            s.flags |= _DIVERGED  # again, soon: health.check_health re-initialises
            return
        _reopen_tilt(s, c)
        s.t_reopened = t
        gate = 0.0
        s.flags |= _TILT_REOPENED
    copy_into(s.w_gravity_update_q_before, s.q)
    if not _gravity_update(s, c, var, gate):
        # The innovation is beyond the χ² gate: more linear acceleration than the
        # model expects (a burst, a tap). Rather than drop the sample, the model
        # is told: ε's (or the sample's) variance grows by what the innovation
        # shows, a = rᵀr/2 − tr S/2 per axis, which brings its NIS to 2; the
        # sample then counts for correspondingly little, and with the low-pass
        # the extra variance leaves with the disturbance, through ε's dynamics.
        # ε takes it only up to just short of the linear limit (above): beyond
        # it every later update would be deferred until ε decays, and a tilt
        # error larger than ~16° (whose innovation puts ε there at once) could
        # then never be corrected; the rest stays with this sample.
        r0, r1 = s.innovation[0], s.innovation[1]
        S = s.w_gravity_update_S  # the gated update's
        extra = max(0.5 * (r0 * r0 + r1 * r1) - 0.5 * (S[0, 0] + S[1, 1]), 0.0)
        if lowpass:
            room = _EPS_ROOM * _linear_limit_variance(c) - _horizontal_eps_variance(s)
            into_eps = min(extra * g2, max(room, 0.0))
            for a in range(2):
                s.P[EPS + a, EPS + a] += into_eps
            var += extra - into_eps / g2
        else:
            var += extra
        nis = s.nis
        _gravity_update(s, c, var, 0.0)
        s.nis = nis  # report what the innovation was, not the matched 2
        s.flags |= _ACCEL_DISTURBED
        s.accel_disturbances += 1
    else:
        s.t_accel = t
    s.accel_used = 1
    if lowpass and c.lowpass_restart_angle > 0.0:
        # A large tilt correction means f̄ was gathered with the attitude
        # grossly wrong, where the linear model of its error is poor: start
        # it again from the next sample, whose noise is known exactly.
        so3.quat_divide_right_into(s.q, s.w_gravity_update_q_before, q4)  # the world-frame move
        cos_half_tilt = math.sqrt(min(q4[0] ** 2 + q4[3] ** 2, 1.0))
        if 2.0 * math.acos(cos_half_tilt) > c.lowpass_restart_angle:
            s.filters_primed = 0
            s.flags |= _LOWPASS_RESTARTED


@inplace_kernel
def _gravity_update(s: StateRecord, c: CoefficientsRecord, var: float, gate: float) -> bool:
    """The configured update (iterated or sigma-point); False if the gate stopped it."""
    if c.update == UPDATE_SIGMA_POINT:
        return _sigma_point_update(s, c, var, gate)
    return _iterated_update(s, c, var, gate)


@inplace_kernel
def clear_gravity_report(s: StateRecord) -> None:
    s.nis = math.nan
    s.innovation[0] = math.nan
    s.innovation[1] = math.nan
