"""The state and its error: the nominal, the reset that moves the error's mean into
it, and the maps between the attitude error's frame and the estimated world.

State X = [R, b] ∈ SO(3) × R³ held as a nominal (q, b) and a Gaussian error
δx = [δθ, δb] in the chosen chart (:mod:`mavest.estimator.charts`). After
every step the error mean is moved into the nominal (the reset), so it is zero
between samples and only the covariance travels with the nominal.

P's rows are δθ and δb, then the considered states of the low-passed accelerometer
(:mod:`mavest.estimator.lowpass`) from :data:`EPS`, :data:`RATE` and :data:`VEL`,
each along the world's x and y only. A reset moves them too: ε ← W_ψ ε, ḟ ← W_ψ ḟ,
v ← W_ψ v, with W_ψ the reset's turn about the vertical (:func:`world_move_into`).
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_inlined_kernel, inplace_kernel, kernel
from mavest.estimator.charts import reset_jacobian_into, retract_into
from mavest.estimator.config import MAX_ANGULAR_RATE
from mavest.estimator.layout import (
    ERROR_LEFT,
    N_AXES,
    N_ERROR,
    CoefficientsRecord,
    StateRecord,
    StepFlags,
)
from mavest.estimator.linalg import (
    copy_into,
    copy_matrix_into,
    left_multiply_rows2,
    left_multiply_rows3,
    right_multiply_cols2,
    right_multiply_cols3,
)

# The considered dimensions follow δθ and δb: ε (x, y), the error of the
# low-pass output the update measures, the low-pass's rate ḟ (x, y), and
# the vehicle's velocity v (x, y), world frame (layout.N_AXES).
EPS = N_ERROR
RATE = N_ERROR + N_AXES
VEL = N_ERROR + 2 * N_AXES


@inplace_kernel
def vector_is_finite(v: np.ndarray) -> bool:
    return math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])


@inplace_kernel
def within(v: np.ndarray, limit: float) -> bool:
    """Whether every axis is within ±``limit`` (a NaN fails every comparison: it is not)."""
    return abs(v[0]) <= limit and abs(v[1]) <= limit and abs(v[2]) <= limit


@inplace_kernel
def gyro_is_valid(gyro: np.ndarray) -> bool:
    """Whether a gyro sample is a measurement: finite and within any gyro's range
    (MAX_ANGULAR_RATE; StepFlags.GYRO_INVALID says a sample is not). A rate beyond it is a
    corrupt value, which integrated would turn the attitude by an arbitrary angle."""
    return within(gyro, MAX_ANGULAR_RATE)


@inplace_kernel
def set_identity(M: np.ndarray) -> None:
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            M[i, j] = 1.0 if i == j else 0.0


@inplace_kernel
def vertical_of(q: np.ndarray) -> tuple[float, float, float]:
    """Rᵀ e₃ for R = R(q): the world vertical in the body frame (the third row of R)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)


@inplace_kernel
def vertical_in_body(s: StateRecord) -> tuple[float, float, float]:
    """R̄ᵀ e₃: the world vertical in the body frame (the third row of R̄)."""
    return vertical_of(s.q)


@inplace_kernel
def add_alignment_into(q: np.ndarray, variance: float, right: bool, cov: np.ndarray) -> None:
    """The accelerometer's alignment added to an estimate's attitude covariance ``cov``
    (its δθ block, 3×3 at least): ``variance`` on each world horizontal axis, none on the
    vertical, whatever the attitude (docs/design.md#the-accelerometers-alignment).
    In the world frame (left error) diag(v, v, 0); in the body frame (right error)
    Rᵀ diag(v, v, 0) R = v (I − u uᵀ), u = Rᵀ e₃ the vertical in the body."""
    if variance == 0.0:
        return
    if not right:
        cov[0, 0] += variance
        cov[1, 1] += variance
        return
    u = vertical_of(q)
    for i in range(3):
        for j in range(3):
            cov[i, j] += variance * ((1.0 if i == j else 0.0) - u[i] * u[j])


@kernel
def add_alignment(q: np.ndarray, variance: float, right: bool, cov: np.ndarray) -> None:
    """:func:`add_alignment_into` for each estimate of a series: q (N, 4), cov (N, 6, 6)."""
    for k in range(q.shape[0]):
        add_alignment_into(q[k], variance, right, cov[k])


@inplace_kernel
def lead_into(
    q: np.ndarray, gyro: np.ndarray, b: np.ndarray, delay: float, out: np.ndarray
) -> None:
    """The attitude at a sample's time stamp of a filter's attitude q, which is the IMU's
    ``delay`` seconds earlier: q carried forward by the sample's rate, q ⊗ Exp((ω − b) τ)
    (docs/design.md#the-imus-delay), as an estimate of a step taken reports it
    (:func:`report_attitude_into`); τ < 0 takes it back. Without a delay, or without a
    rate to carry it by (:func:`gyro_is_valid`), q itself. ``out`` may not alias q."""
    if delay == 0.0 or not gyro_is_valid(gyro):
        copy_into(out, q)
        return
    _carry_into(q, gyro[0] - b[0], gyro[1] - b[1], gyro[2] - b[2], delay, out)


@inplace_kernel
def _carry_into(
    q: np.ndarray, wx: float, wy: float, wz: float, delay: float, out: np.ndarray
) -> None:
    """q ⊗ Exp(ω τ), on q's side of the double cover (a turn beyond π, fast enough a rate
    over a long enough delay, would otherwise flip the sign the filter's q keeps)."""
    so3.quat_times_exp_into(q, wx * delay, wy * delay, wz * delay, out)
    if out[0] * q[0] + out[1] * q[1] + out[2] * q[2] + out[3] * q[3] < 0.0:
        for i in range(4):
            out[i] = -out[i]


# Rows whose attitude is not a step's own: the placeholder before the filter starts, and
# the held estimate of a sample the step did not take.
_PLACEHOLDER = StepFlags.NOT_INITIALISED
_SKIPPED = StepFlags.SKIPPED


@inplace_kernel
def report_attitude_into(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, out: np.ndarray
) -> None:
    """The attitude the estimate after a step on ``gyro`` reports: the filter's, carried
    forward over ``c.imu_delay`` by the sample's rate (:func:`lead_into`). A sample the
    step skipped reports the estimate before it, carried by the rate that one was; the
    placeholder before the filter starts is reported as it is."""
    if c.imu_delay == 0.0 or s.flags & _PLACEHOLDER:
        copy_into(out, s.q)
        return
    if not s.flags & _SKIPPED:  # (a step taken: its gyro is a measurement)
        for i in range(3):
            s.reported_rate[i] = gyro[i] - s.b[i]
    r = s.reported_rate
    _carry_into(s.q, r[0], r[1], r[2], c.imu_delay, out)


@kernel
def lead(q: np.ndarray, gyro: np.ndarray, b: np.ndarray, delay: float) -> np.ndarray:
    """:func:`lead_into` for each estimate of a series: q (N, 4), gyro and b (N, 3)."""
    out = np.empty_like(q)
    for k in range(q.shape[0]):
        lead_into(q[k], gyro[k], b[k], delay, out[k])
    return out


@inplace_inlined_kernel
def add_reported_alignment(s: StateRecord, c: CoefficientsRecord, cov: np.ndarray) -> None:
    """The accelerometer's alignment (``c.alignment_var``) added to ``cov``, a copy of P's
    6×6 that an estimate reports: the filter leaves it out of its own P, as no update can
    remove it."""
    if c.alignment_var != 0.0:
        add_alignment_into(s.q, c.alignment_var, c.error != ERROR_LEFT, cov)


@inplace_kernel
def vertical_in_error_frame(s: StateRecord, c: CoefficientsRecord) -> tuple[float, float, float]:
    """The world vertical in the attitude error's frame: e₃ (left error), R̄ᵀ e₃ (right)."""
    if c.error == ERROR_LEFT:
        return 0.0, 0.0, 1.0
    return vertical_in_body(s)


@inplace_kernel
def transform_blocks(
    s: StateRecord,
    c: CoefficientsRecord,
    P: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    with_considered: bool,
) -> None:
    """P ← T P Tᵀ for T = blockdiag(A, I, W, W, W): A on δθ, W (2×2, from
    :func:`world_move_into`) on ε, ḟ and v (their x, y: the module docstring).

    T is block-diagonal, so each block is multiplied on its own: O(n) per
    block instead of the O(n³) of a dense product. With ``with_considered``
    false, the considered blocks are left alone (W = I).
    """
    left_multiply_rows3(P, 0, A)
    right_multiply_cols3(P, 0, A)
    if with_considered and c.n_state > N_ERROR:
        for block in (EPS, RATE, VEL):
            left_multiply_rows2(P, block, W)
            right_multiply_cols2(P, block, W)


@inplace_kernel
def world_move_into(q_new: np.ndarray, q_old: np.ndarray, W: np.ndarray, work4: np.ndarray) -> None:
    """W (2×2) = the turn about the vertical of q_new ⊗ q_old⁻¹, the move of the
    estimated world frame: what the considered states' horizontal errors take of it.

    The low-pass's vectors are rotated by the whole move R (they are world vectors
    of the estimated frame), and so, exactly, are their errors: ε' = R ε. Of R, only
    the turn about the vertical (the twist of a swing–twist split: the quaternion's
    w and z) maps the horizontal onto itself; its tilt would move the vertical
    components, which are not carried, into the horizontal. Their statistics are
    the horizontal ones' (the same low-pass, the same velocity model; only the
    attitude noise's share is horizontal alone), so the horizontal errors keep
    their variance through the tilt: the twist, not R's horizontal 2×2 block,
    which shrinks it by cos² of the tilt at every reset (with that block, a 60°
    start's ANEES was 28.9; with the twist 5.97, in band: tools/consistency.py).
    """
    so3.quat_divide_right_into(q_new, q_old, work4)
    w, z = work4[0], work4[3]
    norm2 = w * w + z * z
    if norm2 > 0.0:  # (0: a half turn about a horizontal axis, no twist to speak of)
        cos_psi = (w * w - z * z) / norm2
        sin_psi = 2.0 * w * z / norm2
    else:
        cos_psi, sin_psi = 1.0, 0.0
    W[0, 0] = cos_psi
    W[0, 1] = -sin_psi
    W[1, 0] = sin_psi
    W[1, 1] = cos_psi


@inplace_kernel
def reset_covariance(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """P ← T P Tᵀ, T = blockdiag(T_θ(δ̂θ), I, W, W, W): the reset of the covariance.

    Called right after :func:`move_nominal` moved the reference from w_frames_q_from
    to q: the low-pass's errors turn with the world-frame move's turn about the
    vertical (W, :func:`world_move_into`); its vectors turned with the whole move.
    """
    reset_jacobian_into(dx[:3], c.error, c.chart, c.reset, s.w_frames_m33)
    world_move_into(s.q, s.w_frames_q_from, s.w_frames_W, s.w_frames_q4)
    n = c.n_state
    transform_blocks(s, c, s.P[:n, :n], s.w_frames_m33, s.w_frames_W, True)


@inplace_kernel
def move_nominal(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """x ← x ⊞ δx (attitude through the chart, bias additively).

    The estimated world frame moves with the attitude (by q⁺ ⊗ q⁻¹), so the
    world-frame low-pass of the specific force is rotated along.
    """
    copy_into(s.w_frames_q_from, s.q)
    retract_into(s.w_frames_q_from, dx[:3], c.error, c.chart, s.q, s.w_frames_q4)
    for i in range(3):
        s.b[i] += dx[3 + i]
    if c.accel_lowpass_time > 0.0:
        so3.quat_divide_right_into(s.q, s.w_frames_q_from, s.w_frames_q4)
        for stage in range(2):
            so3.quat_rotate_into(s.w_frames_q4, s.accel_world_lp[stage], s.accel_world_lp[stage])
        # the motion's velocity is a world vector too; only its horizontal part is kept
        so3.quat_rotate_into(s.w_frames_q4, s.motion_velocity, s.motion_velocity)
        s.motion_velocity[2] = 0.0


@inplace_kernel
def apply_correction(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """The reset step: move the error mean δ̂ into the nominal and transform P."""
    move_nominal(s, c, dx)
    reset_covariance(s, c, dx)


@inplace_kernel
def error_frame_from_world(s: StateRecord, c: CoefficientsRecord, M: np.ndarray) -> None:
    """M (3×3) = the matrix taking a world-frame rotation vector to the error's frame."""
    if c.error == ERROR_LEFT:
        set_identity(M)
    else:
        so3.matrix_from_quat_into(s.q, s.w_frames_R)
        for i in range(3):
            for j in range(3):
                M[i, j] = s.w_frames_R[j, i]  # Rᵀ: world → body


@inplace_kernel
def set_attitude_covariance_world(
    s: StateRecord,
    c: CoefficientsRecord,
    tilt_var: float,
    heading_var: float,
    set_tilt: bool,
    set_heading: bool,
) -> None:
    """Set the tilt and/or heading variances of P as seen in the world frame.

    Tilt is rotation about the two horizontal world axes, heading about the
    vertical. What is set loses its cross-covariances with everything else;
    what is kept keeps its variance and its covariances.
    """
    n = c.n_state
    attitude_covariance_to_world(s, c)
    for i in range(3):
        if (i < 2 and set_tilt) or (i == 2 and set_heading):
            for j in range(n):
                s.P[i, j] = 0.0
                s.P[j, i] = 0.0
            s.P[i, i] = tilt_var if i < 2 else heading_var
    attitude_covariance_from_world(s, c)


@inplace_kernel
def attitude_covariance_to_world(s: StateRecord, c: CoefficientsRecord) -> None:
    """P's δθ rows and columns in world axes (a change of coordinates, not a move of
    the reference); leaves M (world → error frame) in w_frames_m33 for the way back."""
    error_frame_from_world(s, c, s.w_frames_m33)
    for i in range(3):
        for j in range(3):
            s.w_frames_n33[i, j] = s.w_frames_m33[j, i]  # Mᵀ: error frame → world
    n = c.n_state
    transform_blocks(s, c, s.P[:n, :n], s.w_frames_n33, s.w_frames_W, False)


@inplace_kernel
def attitude_covariance_from_world(s: StateRecord, c: CoefficientsRecord) -> None:
    """Undo :func:`attitude_covariance_to_world` (M still in w_frames_m33)."""
    n = c.n_state
    transform_blocks(s, c, s.P[:n, :n], s.w_frames_m33, s.w_frames_W, False)


@inplace_kernel
def horizontal_times(
    M: np.ndarray, skew: bool, p0: float, p1: float, p2: float
) -> tuple[float, float]:
    """The x, y rows of M (p0, p1, p2) for a 3×3 M (its z row is not carried:
    layout.N_AXES); a skew M's zero diagonal is left out (its products are exact
    zeros, so every sum keeps its value and order)."""
    if skew:
        return M[0, 1] * p1 + M[0, 2] * p2, M[1, 0] * p0 + M[1, 2] * p2
    return (
        M[0, 0] * p0 + M[0, 1] * p1 + M[0, 2] * p2,
        M[1, 0] * p0 + M[1, 1] * p1 + M[1, 2] * p2,
    )


@inplace_kernel
def aided_coupling(s: StateRecord, c: CoefficientsRecord, M: np.ndarray) -> None:
    """M (3×3) = [a]× W: how the attitude error moves an aided sample (in the world)."""
    so3.hat_into(s.linear_accel, M)
    if c.error != ERROR_LEFT:
        R = s.w_frames_R
        so3.matrix_from_quat_into(s.q, R)
        for i in range(3):
            r0, r1, r2 = M[i, 0], M[i, 1], M[i, 2]
            for j in range(3):
                s.w_frames_m33[i, j] = r0 * R[0, j] + r1 * R[1, j] + r2 * R[2, j]
        copy_matrix_into(M, s.w_frames_m33)
