"""The filter recursion: predict → reset → update → reset (Mueller, Hehn, D'Andrea 2017).

State X = [R, b] ∈ SO(3) × R³ held as a nominal (q, b) and a Gaussian error
δx = [δθ, δb] in the chosen chart (:mod:`mavest.estimator.charts`). After
every step the error mean is moved into the nominal (the reset), so it is zero
between samples and only the covariance travels with the nominal.

Prediction (docs/design.md#prediction), ω̂ = ω_m − b̄, φ = ω̂ Δt, each sample's own Δt:

    R̄ ← R̄ Exp(φ)                                       (exact for constant rate)
    Φ = [[I, −R̄ J_l(φ) Δt], [0, I]]                     (left error)
    Φ = [[Exp(−φ), −J_r(φ) Δt], [0, I]]                 (right error)
    Q = [[(σ_g²Δt + σ_b²Δt³/3) I, −σ_b²Δt²/2 M], [·, σ_b²Δt I]]

with M = R̄ (left) or Exp(−φ) (right, its adjoint image).

Update (docs/design.md#iterated-update): the MAP cost ‖r(x)‖²_V + ‖x ⊟ x̄‖²_P minimised by
Gauss–Newton with the prior-correction term (Bell & Cathey 1993; on the
manifold as IKFoM). With d_i = x_i ⊟ x̄ and T_i the reset Jacobian at d_i, the
prior seen from the iterate is N(−T_i d_i, T_i P T_iᵀ), and

    δ_i = m_i − K_i (r_i + H_i m_i),   m_i = −T_i d_i,   x_{i+1} = x_i ⊞ δ_i

with K_i the Kalman gain for T_i P T_iᵀ. One iteration is the EKF; the fixed
point (reset ``full``) is the minimiser of the MAP cost. The covariance of the
last iterate is the Joseph form, moved onto x_{i+1} by the reset T(δ_i).

The low-passed accelerometer (``accel_lowpass_time`` τ > 0). The filter then
measures gravity with f̄, a second-order low-pass (state f̄ and its rate ḟ,
natural frequency √2/τ, damping ζ; Butterworth at ζ = 1/√2 like VQF's) of the
specific force in the estimated world frame: linear acceleration integrates to
a bounded velocity change and averages out, gravity stays (VQF's idea). The
low-pass's errors ε = f̄ − Exp(−δθ)(−g e₃) and ḟ are correlated from sample to
sample, so they are carried as covariance dimensions (world components) with
exact dynamics:

    prediction:          ε ← ε + g E W Δθ            (the attitude error moves, f̄ does not)
    absorbing a sample:  [ε; ḟ] ← Φ [ε; ḟ] + Γ (η + a)  (the low-pass's own step, exact for Δt)
    measurement:         r ≈ H δθ + H_ε ε,  H_ε = (1/g) B_zᵀ R̄ᵀ [e₃]×
    moving the reference (a reset):  ε ← W_ψ ε,  ḟ ← W_ψ ḟ,  v ← W_ψ v

(η the sample's noise; E = the x, y rows of [e₃]×; W = I for the left error,
R̄ for the right, as Δθ must be taken in the world frame; W_ψ the reset's turn
about the vertical, :func:`_world_move_into`.) The vertical ε is invisible to
the measurement and to the lag, and with the reset's turn about the vertical
alone nothing moves it into the horizontal: ε, ḟ and v are carried along the
world's x and y only (:data:`~mavest.estimator.layout.N_AXES`).

Linear acceleration a is what the low-pass is for, and what makes its error
coloured: it is the derivative of a bounded velocity. The vehicle's velocity
v is modelled as Gauss–Markov (σ_v, T_v) and carried too, a held over each
sample: v ← γ v + ξ, a = ((γ − 1) v + ξ)/Δt, γ = e^(−Δt/T_v). The low-pass
averages such an a away (its integral stays bounded), which this model lets
the filter know, and its covariance then honestly holds what is left.
ε, ḟ and v are
*considered* states (Schmidt): their covariance and correlations shape the
gain and are updated with their gain rows set to zero, but their means are
never estimated. Estimating them would turn the filter back into the
raw-accelerometer filter; considering them keeps the low-pass — what makes
the estimate robust to linear acceleration — and keeps the covariance the true
covariance of that estimator.

Every array the recursion touches lives in the state record ``s``; nothing is
allocated per sample.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3, sphere
from mavest._jit import inplace_inlined_kernel, inplace_kernel
from mavest.estimator import gravity, magnetic
from mavest.estimator.charts import local_into, reset_jacobian_into, retract_into
from mavest.estimator.config import STANDARD_GRAVITY
from mavest.estimator.layout import (
    ERROR_LEFT,
    N_AXES,
    N_CONSIDER,
    N_ERROR,
    N_STATE_MAX,
    UPDATE_SIGMA_POINT,
    CoefficientsRecord,
    StateRecord,
    StepFlags,
)
from mavest.estimator.linalg import (
    cholesky_into,
    copy_into,
    copy_matrix_into,
    gain_update,
    inverse_3x3_into,
    is_positive_definite,
    left_multiply_rows2,
    left_multiply_rows3,
    right_multiply_cols2,
    right_multiply_cols3,
    symmetrise,
)
from mavest.timeline import confirmations_kernel, far_off_kernel

# Accelerometer readings below this fraction of g carry no usable direction.
_MIN_ACCEL_FRACTION = 0.05
# The considered dimensions follow δθ and δb: ε (x, y), the error of the
# low-pass output the update measures, the low-pass's rate ḟ (x, y), and
# the vehicle's velocity v (x, y), world frame (layout.N_AXES).
_EPS = N_ERROR
_RATE = N_ERROR + N_AXES
_VEL = N_ERROR + 2 * N_AXES
N_STATE = N_STATE_MAX  # with the low-pass: what the pending transition carries
# A floor under the measurement variance, so that S stays invertible (the
# low-passed measurement's noise lives in ε).
_MIN_DIRECTION_VAR = 1e-14

_INITIALISED = StepFlags.INITIALISED
_NOT_INITIALISED = StepFlags.NOT_INITIALISED
_ACCEL_INVALID = StepFlags.ACCEL_INVALID
_ACCEL_REJECTED_NORM = StepFlags.ACCEL_REJECTED_NORM
_ACCEL_DISTURBED = StepFlags.ACCEL_DISTURBED
_GYRO_INVALID = StepFlags.GYRO_INVALID
_TIME_NOT_INCREASING = StepFlags.TIME_NOT_INCREASING
_GAP_REALIGNED = StepFlags.GAP_REALIGNED
_GYRO_CLIPPED = StepFlags.GYRO_CLIPPED
_CLIP_REALIGNED = StepFlags.CLIP_REALIGNED
_TILT_REOPENED = StepFlags.TILT_REOPENED
_LOWPASS_RESTARTED = StepFlags.LOWPASS_RESTARTED
_ACCEL_DEFERRED = StepFlags.ACCEL_DEFERRED
_MAG_INVALID = StepFlags.MAG_INVALID
_MAG_DISTURBED = StepFlags.MAG_DISTURBED
_MAG_REJECTED = StepFlags.MAG_REJECTED
_HEADING_ALIGNED = StepFlags.HEADING_ALIGNED
_MAG_REFERENCE_CHANGED = StepFlags.MAG_REFERENCE_CHANGED
_HEADING_REOPENED = StepFlags.HEADING_REOPENED
_ACCEL_AIDED = StepFlags.ACCEL_AIDED
_UNHEALTHY_RESET = StepFlags.UNHEALTHY_RESET
_DIVERGED = StepFlags.DIVERGED
_BETWEEN_UPDATES = StepFlags.BETWEEN_UPDATES
_MAG_BETWEEN_UPDATES = StepFlags.MAG_BETWEEN_UPDATES
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


# --------------------------------------------------------------------------
# Small helpers on the state record
# --------------------------------------------------------------------------


@inplace_kernel
def _vector_is_finite(v: np.ndarray) -> bool:
    return math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])


@inplace_kernel
def _set_identity(M: np.ndarray) -> None:
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            M[i, j] = 1.0 if i == j else 0.0


@inplace_kernel
def _vertical_in_body(s: StateRecord) -> tuple[float, float, float]:
    """R̄ᵀ e₃: the world vertical in the body frame (the third row of R̄)."""
    w, x, y, z = s.q[0], s.q[1], s.q[2], s.q[3]
    return 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)


@inplace_kernel
def _vertical_in_error_frame(s: StateRecord, c: CoefficientsRecord) -> tuple[float, float, float]:
    """The world vertical in the attitude error's frame: e₃ (left error), R̄ᵀ e₃ (right)."""
    if c.error == ERROR_LEFT:
        return 0.0, 0.0, 1.0
    return _vertical_in_body(s)


@inplace_kernel
def _gravity_leaves_heading(s: StateRecord) -> bool:
    """Whether the gravity update considers heading (:func:`_drop_heading_gain`).

    With a magnetometer referencing heading, and no known acceleration in
    the sample. Without a magnetometer (6-D) heading is free, and the gain
    keeps the Kalman filter's own share: P's tilt–heading correlation is
    then the prediction's and the reset's alone.
    """
    return s.t_mag_used > -math.inf and not _vector_is_finite(s.linear_accel)


@inplace_kernel
def _drop_heading_gain(s: StateRecord, c: CoefficientsRecord, K: np.ndarray, m: int) -> None:
    """K's attitude rows (n×m) lose their component about the world vertical.

    Called for the gravity update when :func:`_gravity_leaves_heading`: it
    then moves tilt and bias only, heading being *considered* in it
    (Schmidt), as tilt is in the magnetometer's. Gravity alone says nothing
    about heading; what it would move there comes only through P's
    tilt–heading correlation, which the magnetometer's honest covariance
    (:func:`mag_update`) makes large and which a disturbed or lagging field
    on fast rotations makes wrong. (With the acceleration known the sample
    does see heading, in turns — :func:`_couple_aided_sample` — and the gain
    keeps it.) The covariance stays the Joseph form for the gain used
    (:func:`_joseph_update`, :func:`gain_update`).
    """
    v0, v1, v2 = _vertical_in_error_frame(s, c)
    for a in range(m):
        along = v0 * K[0, a] + v1 * K[1, a] + v2 * K[2, a]
        K[0, a] -= v0 * along
        K[1, a] -= v1 * along
        K[2, a] -= v2 * along


@inplace_kernel
def _transform_blocks(
    s: StateRecord,
    c: CoefficientsRecord,
    P: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    with_considered: bool,
) -> None:
    """P ← T P Tᵀ for T = blockdiag(A, I, W, W, W): A on δθ, W (2×2, from
    :func:`_world_move_into`) on ε, ḟ and v (their x, y: the module docstring).

    T is block-diagonal, so each block is multiplied on its own: O(n) per
    block instead of the O(n³) of a dense product. With ``with_considered``
    false, the considered blocks are left alone (W = I).
    """
    left_multiply_rows3(P, 0, A)
    right_multiply_cols3(P, 0, A)
    if with_considered and c.n_state > N_ERROR:
        for block in (_EPS, _RATE, _VEL):
            left_multiply_rows2(P, block, W)
            right_multiply_cols2(P, block, W)


@inplace_kernel
def _world_move_into(
    q_new: np.ndarray, q_old: np.ndarray, W: np.ndarray, work4: np.ndarray
) -> None:
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
def _reset_covariance(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """P ← T P Tᵀ, T = blockdiag(T_θ(δ̂θ), I, W, W, W): the reset of the covariance.

    Called right after :func:`_move_nominal` moved the reference from w_p4 to
    q: the low-pass's errors turn with the world-frame move's turn about the
    vertical (W, :func:`_world_move_into`); its vectors turned with the whole move.
    """
    reset_jacobian_into(dx[:3], c.error, c.chart, c.reset, s.w_m33)
    _world_move_into(s.q, s.w_p4, s.w_W, s.w_q4)
    n = c.n_state
    _transform_blocks(s, c, s.P[:n, :n], s.w_m33, s.w_W, True)


@inplace_kernel
def _move_nominal(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """x ← x ⊞ δx (attitude through the chart, bias additively).

    The estimated world frame moves with the attitude (by q⁺ ⊗ q⁻¹), so the
    world-frame low-pass of the specific force is rotated along.
    """
    copy_into(s.w_p4, s.q)
    retract_into(s.w_p4, dx[:3], c.error, c.chart, s.q, s.w_q4)
    for i in range(3):
        s.b[i] += dx[3 + i]
    if c.accel_lowpass_time > 0.0:
        so3.quat_divide_right_into(s.q, s.w_p4, s.w_q4)
        for stage in range(2):
            so3.quat_rotate_into(s.w_q4, s.accel_world_lp[stage], s.accel_world_lp[stage])
        # the motion's velocity is a world vector too; only its horizontal part is kept
        so3.quat_rotate_into(s.w_q4, s.motion_velocity, s.motion_velocity)
        s.motion_velocity[2] = 0.0


@inplace_kernel
def _apply_correction(s: StateRecord, c: CoefficientsRecord, dx: np.ndarray) -> None:
    """The reset step: move the error mean δ̂ into the nominal and transform P."""
    _move_nominal(s, c, dx)
    _reset_covariance(s, c, dx)


@inplace_kernel
def _error_frame_from_world(s: StateRecord, c: CoefficientsRecord) -> None:
    """w_m33 = the matrix taking a world-frame rotation vector to the error's frame."""
    if c.error == ERROR_LEFT:
        _set_identity(s.w_m33)
    else:
        so3.matrix_from_quat_into(s.q, s.w_R)
        for i in range(3):
            for j in range(3):
                s.w_m33[i, j] = s.w_R[j, i]  # Rᵀ: world → body


@inplace_kernel
def _set_attitude_covariance_world(
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
    _attitude_covariance_to_world(s, c)
    for i in range(3):
        if (i < 2 and set_tilt) or (i == 2 and set_heading):
            for j in range(n):
                s.P[i, j] = 0.0
                s.P[j, i] = 0.0
            s.P[i, i] = tilt_var if i < 2 else heading_var
    _attitude_covariance_from_world(s, c)


@inplace_kernel
def _attitude_covariance_to_world(s: StateRecord, c: CoefficientsRecord) -> None:
    """P's δθ rows and columns in world axes (a change of coordinates, not a move of
    the reference); leaves M (world → error frame) in w_m33 for the way back."""
    _error_frame_from_world(s, c)
    for i in range(3):
        for j in range(3):
            s.w_n33[i, j] = s.w_m33[j, i]  # Mᵀ: error frame → world
    n = c.n_state
    _transform_blocks(s, c, s.P[:n, :n], s.w_n33, s.w_W, False)


@inplace_kernel
def _attitude_covariance_from_world(s: StateRecord, c: CoefficientsRecord) -> None:
    """Undo :func:`_attitude_covariance_to_world` (M still in w_m33)."""
    n = c.n_state
    _transform_blocks(s, c, s.P[:n, :n], s.w_m33, s.w_W, False)


@inplace_kernel
def _align(
    s: StateRecord, c: CoefficientsRecord, accel: np.ndarray, keep_heading: bool, keep_bias: bool
) -> None:
    """Attitude from the accelerometer's gravity direction; heading kept or set to 0.

    At rest a = −g Rᵀe₃ with Rᵀe₃ = (−sin θ, sin φ cos θ, cos φ cos θ) for ZYX
    angles, hence roll φ = atan2(−a_y, −a_z), pitch θ = atan2(a_x, √(a_y² + a_z²)).
    """
    _flush_pending(s, c)
    roll = math.atan2(-accel[1], -accel[2])
    pitch = math.atan2(accel[0], math.hypot(accel[1], accel[2]))
    yaw = 0.0
    if keep_heading:
        so3.euler_zyx_from_quat_into(s.q, s.w_v3)
        yaw = s.w_v3[2]
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
    _set_attitude_covariance_world(s, c, c.initial_tilt_var, c.initial_heading_var, True, True)
    _reset_velocity_covariance(s, c)
    if not keep_heading:
        s.mag_state = 0  # the next magnetometer sample sets heading
    s.filters_primed = 0  # the low-passes start again with the next sample
    s.t_reopened = -math.inf


@inplace_kernel
def _prime_filters(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, accel: np.ndarray, dt: float
) -> None:
    """Start the measurement low-passes again with this sample.

    Priming is the low-pass's step with no weight on its history (β = 0): f̄
    becomes this sample (ḟ = 0) and ε its error η + a, where a involves the
    velocity, which carries on with its correlations — it is the vehicle's,
    not the filter's.
    """
    _flush_pending(s, c)
    copy_into(s.rest_gyro_lp, gyro)
    copy_into(s.rest_accel_lp, accel)
    s.rest_time = 0.0
    _restart_rest_mean(s)
    s.filters_primed = 1
    n = c.n_state
    if n == N_ERROR:
        return
    for i in range(_EPS, _VEL):  # ε and ḟ start afresh
        for j in range(n):
            s.P[i, j] = 0.0
            s.P[j, i] = 0.0
    # (f̄ is cleared as well as ḟ: β = 0 weighs the old f̄ by zero, which keeps a NaN —
    # a broken attitude's — for ever)
    s.accel_world_lp[0, :] = 0.0
    s.accel_world_lp[1, :] = 0.0
    s.lowpass_time = 0.0
    _absorb_sample(s, c, accel, dt, True)  # mean mode with nothing averaged yet: β = 0
    for a in range(N_AXES):  # ḟ is known to be zero; a hair keeps P definite
        s.P[_RATE + a, _RATE + a] = 1e-12 * s.P[_EPS + a, _EPS + a]


@inplace_kernel
def _reset_velocity_covariance(s: StateRecord, c: CoefficientsRecord) -> None:
    """Nothing known of the vehicle's velocity: its stationary variance, uncorrelated."""
    n = c.n_state
    if n == N_ERROR:
        return
    for i in range(_VEL, n):
        for j in range(n):
            s.P[i, j] = 0.0
            s.P[j, i] = 0.0
        s.P[i, i] = _velocity_variance(s, c)


@inplace_kernel
def _velocity_variance(s: StateRecord, c: CoefficientsRecord) -> float:
    """σ_v² of the unaided velocity model: configured, or measured (_track_motion)."""
    if c.velocity_adapt_time > 0.0:
        return max(s.motion_var, c.velocity_var_min)
    return c.velocity_var


@inplace_kernel
def _restart_motion(s: StateRecord, c: CoefficientsRecord) -> None:
    """The motion level back to the one assumed before any data."""
    for i in range(3):
        s.motion_velocity[i] = 0.0
    s.motion_var = c.velocity_var


@inplace_kernel
def _track_motion(s: StateRecord, c: CoefficientsRecord, gamma: float, dt: float) -> None:
    """The vehicle's motion level from this sample (``s.w_v3``: R̄ a, before the
    low-pass takes it), as σ_v² of the velocity model.

    The sample's horizontal departure from the low-pass f̄ is the linear
    acceleration without its slow part; integrated with the velocity model's γ it
    is the velocity's fast part, ṽ ← γ ṽ + (R̄ a − f̄) Δt. Its mean square over
    ``velocity_adapt_time`` (an exponential average), times the gain, is σ_v²:
    for the model's own Gauss–Markov velocity the high-pass keeps 1/1.71 of the
    variance (τ = 3 s, T_v = 1 s), and the default gain 2 errs on the safe side.
    f̄ turns with every correction of the attitude, so a tilt error's share of
    gravity, which R̄ a and f̄ hold alike, stays out of the difference: a large
    initial error does not read as motion.
    """
    if c.velocity_adapt_time <= 0.0:
        return
    square = 0.0
    for i in range(N_AXES):
        v = gamma * s.motion_velocity[i] + (s.w_v3[i] - s.accel_world_lp[0, i]) * dt
        s.motion_velocity[i] = v
        square += v * v
    alpha = dt / (c.velocity_adapt_time + dt)
    s.motion_var += alpha * (c.velocity_adapt_gain * square / N_AXES - s.motion_var)


# --------------------------------------------------------------------------
# Prediction
# --------------------------------------------------------------------------


@inplace_kernel
def _process_noise_rotation(s: StateRecord, c: CoefficientsRecord, phi: np.ndarray) -> None:
    """The rotation M in Q's cross term: R̄ before the step for the left error, which
    w_R must hold already; for the right error Exp(−φ), into w_n33, its image under
    the adjoint, so that left and right filters stay the same filter (with the full
    reset they give the same estimate: docs/design.md#recursion-and-reset)."""
    if c.error != ERROR_LEFT:
        so3.exp_into(phi, s.w_m33)
        for i in range(3):
            for j in range(3):
                s.w_n33[i, j] = s.w_m33[j, i]  # Exp(−φ) = Exp(φ)ᵀ


@inplace_kernel
def _world_tilt_rows(s: StateRecord, c: CoefficientsRecord, out: np.ndarray) -> None:
    """out (2×3) = g E W: how a change of δθ (error frame) moves ε.

    E = the x, y rows of [e₃]× (so E v = (−v_y, v_x)), W = the error frame's
    map to the world: I for the left error, R̄ (after the step) for the right.
    """
    g = c.gravity
    if c.error == ERROR_LEFT:
        for j in range(3):
            out[0, j] = 0.0
            out[1, j] = 0.0
        out[0, 1] = -g
        out[1, 0] = g
    else:
        R = s.w_R_tilt
        so3.matrix_from_quat_into(s.q, R)
        for j in range(3):
            out[0, j] = -g * R[1, j]
            out[1, j] = g * R[0, j]


@inplace_kernel
def _add_process_noise(
    s: StateRecord, c: CoefficientsRecord, dt: float, n: int, rate_sq: float
) -> None:
    """P[:n, :n] += Q_d (Van Loan, with the cross term's rotation M, w_R or w_n33:
    :func:`_process_noise_rotation`). ``rate_sq``: the step's |ω|², which the
    gyro's scale and alignment errors are proportional to.

    With the considered ε (n > 6), its rows receive G = g E W times the
    attitude noise: the same noise moves δθ and, through it, ε.
    """
    var_g = c.gyro_var_density + c.gyro_scale_var_density * rate_sq
    var_b = c.bias_var_density
    q_aa = var_g * dt + var_b * dt * dt * dt / 3.0
    q_ab = -0.5 * var_b * dt * dt
    q_bb = var_b * dt
    P = s.P
    M = s.w_R if c.error == ERROR_LEFT else s.w_n33
    for i in range(3):
        P[i, i] += q_aa
        P[3 + i, 3 + i] += q_bb
        for j in range(3):
            v = q_ab * M[i, j]
            P[i, 3 + j] += v
            P[3 + j, i] += v
    if n == N_ERROR:
        return
    G = s.w_H  # 2×3 scratch (the update rewrites it)
    _world_tilt_rows(s, c, G)
    # ε receives G Δθ; the low-pass's rate ḟ does not
    for a in range(2):
        for j in range(3):
            # Q_εθ = G Q_θθ = q_aa G ;  Q_εb = G Q_θb = q_ab G M
            cross_b = 0.0
            for k in range(3):
                cross_b += G[a, k] * M[k, j]
            P[_EPS + a, j] += q_aa * G[a, j]
            P[j, _EPS + a] += q_aa * G[a, j]
            P[_EPS + a, 3 + j] += q_ab * cross_b
            P[3 + j, _EPS + a] += q_ab * cross_b
        for b in range(2):  # Q_εε = q_aa G Gᵀ
            acc = 0.0
            for k in range(3):
                acc += G[a, k] * G[b, k]
            P[_EPS + a, _EPS + b] += q_aa * acc


@inplace_kernel
def _rate_squared(phi: np.ndarray, dt: float) -> float:
    """|ω|² of a step's rotation φ = ω Δt."""
    return (phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]) / (dt * dt)


@inplace_kernel
def _predict_linear(s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, dt: float) -> None:
    """EKF prediction: exact nominal, P ← Φ P Φᵀ + Q_d.

    Φ differs from I only in the δθ rows (Φ_θθ, Φ_θb) and, with the low-pass,
    the ε x, y rows (G Φ_θb); those rows and columns are all that change.
    Between updates (``c.accumulate``) only P's 6×6 is propagated here, and Φ
    joins the pending transition of the considered rows (:func:`_flush_pending`).
    """
    if c.accumulate:  # (before P's 6×6 moves: the interval starts from it)
        _open_pending(s)
    n = N_ERROR if c.accumulate else c.n_state
    phi = s.w_v3
    for i in range(3):
        phi[i] = (gyro[i] - s.b[i]) * dt
    so3.matrix_from_quat_into(s.q, s.w_R)
    _process_noise_rotation(s, c, phi)  # w_n33: also Φ_θθ = Exp(−φ) for the right error
    F = s.w_m33  # Φ_θb
    if c.error == ERROR_LEFT:
        so3.left_jacobian_into(phi, s.w_T[:3, :3])
        for i in range(3):
            for j in range(3):
                F[i, j] = -dt * (
                    s.w_R[i, 0] * s.w_T[0, j]
                    + s.w_R[i, 1] * s.w_T[1, j]
                    + s.w_R[i, 2] * s.w_T[2, j]
                )
    else:
        so3.right_jacobian_into(phi, F)
        for i in range(3):
            for j in range(3):
                F[i, j] *= -dt
    so3.quat_exp_into(phi, s.w_q4)
    copy_into(s.w_p4, s.q)
    so3.quat_multiply_into(s.w_p4, s.w_q4, s.q)
    so3.quat_normalize_into(s.q)
    G = s.w_G  # ε x, y rows of Φ: G Φ_θb, with G = g E W after the step
    if c.n_state > N_ERROR:
        _world_tilt_rows(s, c, s.w_H)
        for a in range(2):
            for j in range(3):
                G[a, j] = s.w_H[a, 0] * F[0, j] + s.w_H[a, 1] * F[1, j] + s.w_H[a, 2] * F[2, j]
    right = c.error != ERROR_LEFT
    E = s.w_n33
    P = s.P
    for j in range(n):  # rows: Φ P
        t0, t1, t2 = P[0, j], P[1, j], P[2, j]
        b0, b1, b2 = P[3, j], P[4, j], P[5, j]
        if right:
            t0, t1, t2 = (
                E[0, 0] * t0 + E[0, 1] * t1 + E[0, 2] * t2,
                E[1, 0] * t0 + E[1, 1] * t1 + E[1, 2] * t2,
                E[2, 0] * t0 + E[2, 1] * t1 + E[2, 2] * t2,
            )
        P[0, j] = t0 + F[0, 0] * b0 + F[0, 1] * b1 + F[0, 2] * b2
        P[1, j] = t1 + F[1, 0] * b0 + F[1, 1] * b1 + F[1, 2] * b2
        P[2, j] = t2 + F[2, 0] * b0 + F[2, 1] * b1 + F[2, 2] * b2
        if n > N_ERROR:
            P[_EPS, j] += G[0, 0] * b0 + G[0, 1] * b1 + G[0, 2] * b2
            P[_EPS + 1, j] += G[1, 0] * b0 + G[1, 1] * b1 + G[1, 2] * b2
    for i in range(n):  # columns: (Φ P) Φᵀ
        t0, t1, t2 = P[i, 0], P[i, 1], P[i, 2]
        b0, b1, b2 = P[i, 3], P[i, 4], P[i, 5]
        if right:
            t0, t1, t2 = (
                E[0, 0] * t0 + E[0, 1] * t1 + E[0, 2] * t2,
                E[1, 0] * t0 + E[1, 1] * t1 + E[1, 2] * t2,
                E[2, 0] * t0 + E[2, 1] * t1 + E[2, 2] * t2,
            )
        P[i, 0] = t0 + F[0, 0] * b0 + F[0, 1] * b1 + F[0, 2] * b2
        P[i, 1] = t1 + F[1, 0] * b0 + F[1, 1] * b1 + F[1, 2] * b2
        P[i, 2] = t2 + F[2, 0] * b0 + F[2, 1] * b1 + F[2, 2] * b2
        if n > N_ERROR:
            P[i, _EPS] += G[0, 0] * b0 + G[0, 1] * b1 + G[0, 2] * b2
            P[i, _EPS + 1] += G[1, 0] * b0 + G[1, 1] * b1 + G[1, 2] * b2
    _add_process_noise(s, c, dt, n, _rate_squared(phi, dt))
    if c.accumulate:
        _accumulate_prediction(s, c)


# --------------------------------------------------------------------------
# The pending transition: between updates only P's 6×6 follows every sample
# --------------------------------------------------------------------------
#
# Between two updates nothing reads P's considered rows (ε, ḟ, v): only the
# predictions and the low-pass's steps change them, and those are linear maps
# of the error, so their product is accumulated per sample (3×3 and 6×6 blocks,
# a few dozen products) and applied once, at the next update or whatever else
# needs the whole P (:func:`_flush_pending`). P's 6×6, what the estimate shows,
# is propagated every sample as before.
#
# Exact but for one thing: the attitude noise a prediction adds reaches ε too
# (ε moves with δθ, G Δθ), and the accumulated transition carries that as if it
# came at the flush: the low-pass's dynamics over the rest of the interval (ωΔT
# with ω = √2/τ: 1.2 % at 40 Hz for τ = 3 s) and an aided sample's share of it are
# left out of that part of the noise. The low-pass's own noise (η, ξ) is
# accumulated exactly.


@inplace_kernel
def _open_pending(s: StateRecord) -> None:
    """Another transition joins the pending one; the first after a flush starts a new
    interval: P's 6×6 as it stands, the identity transition, no noise."""
    s.pending_steps += 1
    if s.pending_steps > 1:
        return
    copy_matrix_into(s.pending_P6, s.P[:N_ERROR, :N_ERROR])
    _set_identity(s.pending_theta)
    _set_identity(s.pending_stage)
    for i in range(3):
        for j in range(3):
            s.pending_bias[i, j] = 0.0
            s.pending_noise[i, j] = 0.0
    for i in range(N_CONSIDER):
        for j in range(N_ERROR):
            s.pending_U[i, j] = 0.0
    s.pending_aided = 0


@inplace_kernel
def _accumulate_prediction(s: StateRecord, c: CoefficientsRecord) -> None:
    """The prediction :func:`_predict_linear` just made (Φ_θθ in w_n33 for the right
    error, Φ_θb in w_m33, G Φ_θb in w_G) after the pending transition."""
    F = s.w_m33
    theta = s.pending_theta
    bias = s.pending_bias
    if c.error != ERROR_LEFT:  # Θθ ← E Θθ, Θb ← E Θb (E = Exp(−φ))
        E = s.w_n33
        for M in (theta, bias):
            for j in range(3):
                m0, m1, m2 = M[0, j], M[1, j], M[2, j]
                for i in range(3):
                    M[i, j] = E[i, 0] * m0 + E[i, 1] * m1 + E[i, 2] * m2
    for i in range(3):
        for j in range(3):
            bias[i, j] += F[i, j]
    if c.n_state > N_ERROR:  # ε x, y ← ε + G Φ_θb δb
        for a in range(2):
            for j in range(3):
                s.pending_U[a, 3 + j] += s.w_G[a, j]


@inplace_kernel
def _accumulate_absorb(
    s: StateRecord,
    c: CoefficientsRecord,
    A: tuple[float, float, float, float, float, float, float],
    noise: tuple[float, float, float, float, float, float],
    g0: float,
    g1: float,
    aided: bool,
) -> None:
    """The low-pass's step (:func:`_absorb_sample`) after the pending transition: u ←
    (A ⊗ I₂) u with A = [[a00, a01, a02], [a10, a11, a12], [0, 0, γ]] (``A`` those seven),
    its noise (``noise``: N's upper triangle) added, and with a known acceleration
    :func:`_couple_aided_sample`'s [ε; ḟ] += [Γ₀; Γ₁] M δθ."""
    _open_pending(s)  # (a flush may have come between the prediction and this)
    a00, a01, a02, a10, a11, a12, gamma = A
    U = s.pending_U
    first = 0 if s.pending_aided else 3  # U's δθ columns are zero until an aided sample
    for axis in range(N_AXES):
        e, d, v = axis, N_AXES + axis, 2 * N_AXES + axis
        for j in range(first, N_ERROR):
            pe, pd, pv = U[e, j], U[d, j], U[v, j]
            U[e, j] = a00 * pe + a01 * pd + a02 * pv
            U[d, j] = a10 * pe + a11 * pd + a12 * pv
            U[v, j] = gamma * pv
    S = s.pending_stage
    for j in range(3):
        pe, pd, pv = S[0, j], S[1, j], S[2, j]
        S[0, j] = a00 * pe + a01 * pd + a02 * pv
        S[1, j] = a10 * pe + a11 * pd + a12 * pv
        S[2, j] = gamma * pv
    N = s.pending_noise  # A N Aᵀ + the step's own
    for j in range(3):
        pe, pd, pv = N[0, j], N[1, j], N[2, j]
        N[0, j] = a00 * pe + a01 * pd + a02 * pv
        N[1, j] = a10 * pe + a11 * pd + a12 * pv
        N[2, j] = gamma * pv
    for i in range(3):
        pe, pd, pv = N[i, 0], N[i, 1], N[i, 2]
        N[i, 0] = a00 * pe + a01 * pd + a02 * pv
        N[i, 1] = a10 * pe + a11 * pd + a12 * pv
        N[i, 2] = gamma * pv
    n00, n01, n02, n11, n12, n22 = noise
    N[0, 0] += n00
    N[0, 1] += n01
    N[1, 0] += n01
    N[0, 2] += n02
    N[2, 0] += n02
    N[1, 1] += n11
    N[1, 2] += n12
    N[2, 1] += n12
    N[2, 2] += n22
    if not aided:
        return
    _aided_coupling(s, c)  # the current δθ is Θθ δθ₀ + Θb δb₀
    M = s.w_aid
    s.pending_aided = 1
    skew = c.error == ERROR_LEFT  # M = [a]×
    for j in range(N_ERROR):
        T = s.pending_theta if j < 3 else s.pending_bias
        k = j % 3
        m0, m1 = _horizontal_times(M, skew, T[0, k], T[1, k], T[2, k])
        U[0, j] += g0 * m0
        U[1, j] += g0 * m1
        U[N_AXES, j] += g1 * m0
        U[N_AXES + 1, j] += g1 * m1


@inplace_inlined_kernel
def _along_stages(S: np.ndarray, stage: int, M: np.ndarray, row: int, j: int) -> float:
    """(S ⊗ I₂) applied to column j of the considered rows of M, its entry (stage, axis)
    with ``row`` = N_ERROR + axis: the considered rows are ε, ḟ, v of each axis."""
    return (
        S[stage, 0] * M[row, j]
        + S[stage, 1] * M[row + N_AXES, j]
        + S[stage, 2] * M[row + 2 * N_AXES, j]
    )


@inplace_inlined_kernel
def _row_times_column(A: np.ndarray, i: int, B: np.ndarray, j: int) -> float:
    """(A B)[i, j] for A with three columns."""
    return A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@inplace_kernel
def _flush_pending(s: StateRecord, c: CoefficientsRecord) -> None:
    """Bring P's considered rows up to date: apply the pending transition (with x₆ =
    [δθ, δb], X = P's u rows' x₆ part and Y its u part at the interval's start,
    P₆ = pending_P6, Φ₆ = [[Θθ, Θb], [0, I]], Λ = A ⊗ I₂):

        P_u6 ← (Λ X + U P₆) Φ₆ᵀ + Q_u6,
        P_uu ← Λ Y Λᵀ + (Λ X + U P₆) Uᵀ + U (Λ X)ᵀ + I₂ ⊗ N + Q_uu.

    P's 6×6 is already the interval's end; what its prediction noise added,
    Q₆ = P_6 − Φ₆ P₆ Φ₆ᵀ, reaches ε through G = g E W as each prediction's did:
    Q_ε6 = G Q₆'s δθ rows, Q_εε = G Q₆θθ Gᵀ (see the section's comment).
    U's v rows are zero (nothing reaches v but its own noise), and its δθ columns
    until an aided sample: the sums skip them.
    """
    if s.pending_steps == 0:
        return
    s.pending_steps = 0
    P = s.P
    P6 = s.pending_P6
    U = s.pending_U
    S = s.pending_stage
    theta = s.pending_theta
    bias = s.pending_bias
    first = 0 if s.pending_aided else 3  # U's first non-zero column
    live = 0  # U's non-zero rows, as bits (ε and ḟ at most; unaided: ε only)
    for r in range(2 * N_AXES):
        for k in range(first, N_ERROR):
            if U[r, k] != 0.0:
                live |= 1 << r
    # Q₆'s δθ rows (all that reaches ε) into w_B[:3, :6], via Φ₆'s δθ rows times P₆
    PhiP = s.w_A
    for i in range(3):
        for j in range(N_ERROR):
            acc = 0.0
            for k in range(3):
                acc += theta[i, k] * P6[k, j] + bias[i, k] * P6[3 + k, j]
            PhiP[i, j] = acc
    Q = s.w_B
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += PhiP[i, k] * theta[j, k] + PhiP[i, 3 + k] * bias[j, k]
            Q[i, j] = P[i, j] - acc
            Q[i, 3 + j] = P[i, 3 + j] - PhiP[i, 3 + j]
    G = s.w_H  # 2×3 scratch (the update rewrites it)
    _world_tilt_rows(s, c, G)
    GQ = s.w_C  # G Q₆'s δθ rows (2×6) into w_C[:6, :2] (transposed), G Q₆θθ Gᵀ below
    for a in range(2):
        for j in range(N_ERROR):
            GQ[j, a] = _row_times_column(G, a, Q, j)
    # V = Λ X into w_A[6:, :6]; Z = V + U P₆ into w_B[6:, :6]
    V = s.w_A
    Z = s.w_B
    for stage in range(3):
        for axis in range(N_AXES):
            r = N_ERROR + N_AXES * stage + axis
            for j in range(N_ERROR):
                V[r, j] = _along_stages(S, stage, P, N_ERROR + axis, j)
                acc = V[r, j]
                if live >> (r - N_ERROR) & 1:
                    for k in range(first, N_ERROR):
                        acc += U[r - N_ERROR, k] * P6[k, j]
                Z[r, j] = acc
    # Λ Y's rows into w_T[6:, 6:], then the new P_uu (lower triangle, mirrored)
    LY = s.w_T
    for stage in range(3):
        for axis in range(N_AXES):
            r = N_ERROR + N_AXES * stage + axis
            for j in range(N_ERROR, N_STATE):
                LY[r, j] = _along_stages(S, stage, P, N_ERROR + axis, j)
    N = s.pending_noise
    for r in range(N_ERROR, N_STATE):
        stage_r, axis_r = (r - N_ERROR) // N_AXES, (r - N_ERROR) % N_AXES
        live_r = live >> (r - N_ERROR) & 1
        for q in range(N_ERROR, r + 1):
            stage_q, axis_q = (q - N_ERROR) // N_AXES, (q - N_ERROR) % N_AXES
            acc = (
                LY[r, N_ERROR + axis_q] * S[stage_q, 0]
                + LY[r, N_ERROR + N_AXES + axis_q] * S[stage_q, 1]
                + LY[r, N_ERROR + 2 * N_AXES + axis_q] * S[stage_q, 2]
            )
            if live >> (q - N_ERROR) & 1:  # Z Uᵀ
                for k in range(first, N_ERROR):
                    acc += Z[r, k] * U[q - N_ERROR, k]
            if live_r:  # U Vᵀ
                for k in range(first, N_ERROR):
                    acc += U[r - N_ERROR, k] * V[q, k]
            if axis_r == axis_q:
                acc += N[stage_r, stage_q]
            if r < _RATE and q < _RATE:  # Q_εε = G Q₆θθ Gᵀ
                a = q - _EPS
                acc += GQ[0, r - _EPS] * G[a, 0] + GQ[1, r - _EPS] * G[a, 1]
                acc += GQ[2, r - _EPS] * G[a, 2]
            P[r, q] = acc
            P[q, r] = acc
    # the new P_u6 = Z Φ₆ᵀ + Q_u6 last: Z and V were made from the old one
    for r in range(N_ERROR, N_STATE):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += Z[r, k] * theta[j, k] + Z[r, 3 + k] * bias[j, k]
            if r < _RATE:  # Q_ε6 = G Q₆'s δθ rows
                acc += GQ[j, r - _EPS]
            P[r, j] = acc
            P[j, r] = acc
            acc = Z[r, 3 + j]
            if r < _RATE:
                acc += GQ[3 + j, r - _EPS]
            P[r, 3 + j] = acc
            P[3 + j, r] = acc


@inplace_kernel
def _sigma_points(s: StateRecord, c: CoefficientsRecord) -> bool:
    """w_sigma_chi = 0, ±columns of √((n + λ) P) (Cholesky). False if P is not PD."""
    n = c.n_state
    A = s.w_B[:n, :n]
    L = s.w_A[:n, :n]
    for i in range(n):
        for j in range(n):
            A[i, j] = c.sigma_spread * s.P[i, j]
    if not cholesky_into(A, L):
        return False
    chi = s.w_sigma_chi
    for i in range(n):
        chi[0, i] = 0.0
        for j in range(n):
            chi[1 + j, i] = L[i, j]
            chi[1 + n + j, i] = -L[i, j]
    return True


@inplace_kernel
def _weighted_mean_and_covariance_of_chi(
    s: StateRecord, c: CoefficientsRecord, mean: np.ndarray
) -> None:
    """mean = Σ wᵢ χᵢ and P = Σ wᵢᶜ (χᵢ − mean)(χᵢ − mean)ᵀ over w_sigma_chi."""
    n = c.n_state
    chi = s.w_sigma_chi
    for i in range(n):
        acc = c.sigma_w0_mean * chi[0, i]
        for k in range(1, 2 * n + 1):
            acc += c.sigma_wi * chi[k, i]
        mean[i] = acc
    for i in range(n):
        for j in range(i + 1):
            acc = c.sigma_w0_cov * (chi[0, i] - mean[i]) * (chi[0, j] - mean[j])
            for k in range(1, 2 * n + 1):
                acc += c.sigma_wi * (chi[k, i] - mean[i]) * (chi[k, j] - mean[j])
            s.P[i, j] = acc
            s.P[j, i] = acc


@inplace_kernel
def _predict_sigma_point(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, dt: float
) -> bool:
    """Unscented prediction through the exact dynamics, then the prediction reset.

    Each sigma point is a full state [chart(χθ) R̄, b̄ + χb] propagated with its
    own bias; the propagated points are read back as errors about the
    propagated nominal, and their mean (non-zero in general) is reset into it.
    A considered ε follows its point's attitude error: ε' = ε + g E (W'χθ' − Wχθ).
    """
    if not _sigma_points(s, c):
        return False
    n = c.n_state
    so3.matrix_from_quat_into(s.q, s.w_R)  # R̄ before the step, for Q_d
    phi = s.w_v3
    for i in range(3):
        phi[i] = (gyro[i] - s.b[i]) * dt
    rate_sq = _rate_squared(phi, dt)
    _process_noise_rotation(s, c, phi)
    # the new reference: the nominal propagated with the nominal bias
    so3.quat_exp_into(phi, s.w_q4)
    so3.quat_multiply_into(s.q, s.w_q4, s.w_prior_q)
    so3.quat_normalize_into(s.w_prior_q)
    chi = s.w_sigma_chi
    G_before = s.w_K  # ε rows before the step (W = R̄): reuse 2 columns of scratch
    if n > N_ERROR:
        _world_tilt_rows(s, c, s.w_H)
        for a in range(2):
            for j in range(3):
                G_before[j, a] = s.w_H[a, j]
    for k in range(2 * n + 1):
        qk = s.w_sigma_q[k]
        retract_into(s.q, chi[k, :3], c.error, c.chart, qk, s.w_q4)
        for i in range(3):
            phi[i] = (gyro[i] - s.b[i] - chi[k, 3 + i]) * dt
        so3.quat_exp_into(phi, s.w_q4)
        copy_into(s.w_p4, qk)
        so3.quat_multiply_into(s.w_p4, s.w_q4, qk)
        if n > N_ERROR:
            for a in range(2):
                acc = 0.0
                for j in range(3):
                    acc += G_before[j, a] * chi[k, j]
                chi[k, _EPS + a] -= acc
        local_into(qk, s.w_prior_q, c.error, c.chart, chi[k, :3], s.w_q4)
    copy_into(s.q, s.w_prior_q)
    if n > N_ERROR:
        _world_tilt_rows(s, c, s.w_H)  # W' = R̄ after the step
        for k in range(2 * n + 1):
            for a in range(2):
                acc = 0.0
                for j in range(3):
                    acc += s.w_H[a, j] * chi[k, j]
                chi[k, _EPS + a] += acc
    _weighted_mean_and_covariance_of_chi(s, c, s.w_dx)
    for i in range(_EPS, n):  # ε is considered: its mean stays zero
        s.w_dx[i] = 0.0
    _add_process_noise(s, c, dt, n, rate_sq)
    _apply_correction(s, c, s.w_dx)
    return True


@inplace_kernel
def predict(s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, dt: float) -> None:
    """Propagate nominal and covariance over Δt with the gyroscope sample."""
    if c.update == UPDATE_SIGMA_POINT and _predict_sigma_point(s, c, gyro, dt):
        return
    _predict_linear(s, c, gyro, dt)


# --------------------------------------------------------------------------
# Gravity update
# --------------------------------------------------------------------------


@inplace_kernel
def _gravity_residual(s: StateRecord, q: np.ndarray, r: np.ndarray) -> None:
    gravity.residual_into(q, s.w_z, s.w_Bz, r, s.w_R, s.w_h, s.w_u3)


@inplace_kernel
def _gravity_jacobian(s: StateRecord, c: CoefficientsRecord) -> None:
    """w_H = [H_θ, 0, H_ε] at the point where :func:`_gravity_residual` left w_R, w_h."""
    gravity.jacobian_into(s.w_R, s.w_h, s.w_z, s.w_Bz, c.error, s.w_H, s.w_m33, s.w_n33)
    if c.n_state == N_ERROR:
        return
    # H_ε = (1/g) B_zᵀ R̄ᵀ [e₃]×: R̄ᵀ[e₃]× e_x = R̄ᵀ e_y, e_y ↦ −R̄ᵀ e_x (e_z ↦ 0,
    # which is why ε_z is not carried); the low-pass's rate is not measured
    inv_g = 1.0 / c.gravity
    for k in range(2):
        for i in range(_RATE, c.n_state):
            s.w_H[k, i] = 0.0
        s.w_H[k, _EPS] = inv_g * (
            s.w_Bz[0, k] * s.w_R[1, 0] + s.w_Bz[1, k] * s.w_R[1, 1] + s.w_Bz[2, k] * s.w_R[1, 2]
        )
        s.w_H[k, _EPS + 1] = -inv_g * (
            s.w_Bz[0, k] * s.w_R[0, 0] + s.w_Bz[1, k] * s.w_R[0, 1] + s.w_Bz[2, k] * s.w_R[0, 2]
        )


@inplace_kernel
def _solve_gain(s: StateRecord, c: CoefficientsRecord, Pi: np.ndarray, var: float) -> float:
    """C = Pi Hᵀ (w_C), S = H C + var I (w_S), K = C S⁻¹ (w_K); returns the NIS of w_r.

    The gravity Jacobian (:func:`_gravity_jacobian`) is zero on the bias, ḟ and
    v: the sums run over its other columns only (δθ, ε_x, ε_y), in
    the order of the full sums, which the exact zeros left unchanged. K's
    considered rows are zero (Schmidt: ε's mean is never estimated).
    """
    n = c.n_state
    H = s.w_H
    C = s.w_C
    K = s.w_K
    considered = n > N_ERROR
    for i in range(n):
        for k in range(2):
            acc = 0.0
            for j in range(3):
                acc += Pi[i, j] * H[k, j]
            if considered:
                acc += Pi[i, _EPS] * H[k, _EPS]
                acc += Pi[i, _EPS + 1] * H[k, _EPS + 1]
            C[i, k] = acc
    for a in range(2):
        for b in range(2):
            acc = var if a == b else 0.0
            for j in range(3):
                acc += H[a, j] * C[j, b]
            if considered:
                acc += H[a, _EPS] * C[_EPS, b]
                acc += H[a, _EPS + 1] * C[_EPS + 1, b]
            s.w_S[a, b] = acc
    s01 = 0.5 * (s.w_S[0, 1] + s.w_S[1, 0])
    s.w_S[0, 1] = s01
    s.w_S[1, 0] = s01
    s00, s11 = s.w_S[0, 0], s.w_S[1, 1]
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
    r0, r1 = s.w_r[0], s.w_r[1]
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
    gain_update(P, s.w_K[:n], s.w_C[:n], s.w_S, 2)


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
    copy_into(s.w_prior_q, s.q)
    copy_into(s.w_prior_b, s.b)
    # the prior seen from the iterate: P itself at the first (read only until
    # the Joseph form), its transport T P Tᵀ into w_A at later ones
    Pi = s.P[:n, :n]
    d = s.w_d
    m = s.w_m
    dx = s.w_dx
    H = s.w_H
    K = s.w_K
    r = s.w_r
    for it in range(c.max_iterations):
        if it == 0:
            for i in range(n):
                m[i] = 0.0
        else:
            local_into(s.q, s.w_prior_q, c.error, c.chart, d[:3], s.w_q4)
            for i in range(3):
                d[3 + i] = s.b[i] - s.w_prior_b[i]
            for i in range(_EPS, n):
                d[i] = 0.0
            reset_jacobian_into(d[:3], c.error, c.chart, c.reset, s.w_m33)
            _world_move_into(s.q, s.w_prior_q, s.w_W, s.w_q4)
            Pi = s.w_A[:n, :n]
            copy_matrix_into(Pi, s.P[:n, :n])
            _transform_blocks(s, c, Pi, s.w_m33, s.w_W, True)
            T = s.w_m33  # m = −T d: only δθ is transported (d's considered part is 0)
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
            for j in range(_EPS, _EPS + 2):
                y0 += H[0, j] * m[j]
                y1 += H[1, j] * m[j]
        for i in range(n):
            dx[i] = m[i] - K[i, 0] * y0 - K[i, 1] * y1
        # the step of the estimate (ε's is discarded), and of its attitude alone
        attitude_step2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
        step_norm2 = attitude_step2 + dx[3] * dx[3] + dx[4] * dx[4] + dx[5] * dx[5]
        _move_nominal(s, c, dx)
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
    _reset_covariance(s, c, dx)
    return True


@inplace_kernel
def _sigma_point_update(s: StateRecord, c: CoefficientsRecord, var: float, gate: float) -> bool:
    """Unscented update of the error about the nominal, then the measurement reset."""
    if not _sigma_points(s, c):  # P lost definiteness: the linearised update still works
        return _iterated_update(s, c, var, gate)
    n = c.n_state
    n_sigma = 2 * n + 1
    chi = s.w_sigma_chi
    rs = s.w_sigma_r
    H = s.w_H
    for k in range(n_sigma):
        retract_into(s.q, chi[k, :3], c.error, c.chart, s.w_sigma_q[k], s.w_q4)
        _gravity_residual(s, s.w_sigma_q[k], rs[k])
        if n > N_ERROR:  # ε enters linearly: r + H_ε ε, H_ε at this point
            _gravity_jacobian(s, c)
            for i in range(_EPS, n):
                rs[k, 0] += H[0, i] * chi[k, i]
                rs[k, 1] += H[1, i] * chi[k, i]
    rbar0 = c.sigma_w0_mean * rs[0, 0]
    rbar1 = c.sigma_w0_mean * rs[0, 1]
    for k in range(1, n_sigma):
        rbar0 += c.sigma_wi * rs[k, 0]
        rbar1 += c.sigma_wi * rs[k, 1]
    S = s.w_S
    C = s.w_C
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
    K = s.w_K
    for i in range(n):
        if i >= _EPS:
            K[i, 0] = 0.0
            K[i, 1] = 0.0
        else:
            K[i, 0] = C[i, 0] * i00 + C[i, 1] * i01
            K[i, 1] = C[i, 0] * i01 + C[i, 1] * i11
    if _gravity_leaves_heading(s):
        _drop_heading_gain(s, c, K, 2)
    for i in range(n):
        s.w_dx[i] = -(K[i, 0] * rbar0 + K[i, 1] * rbar1)
    gain_update(s.P[:n, :n], K[:n], C[:n], S, 2)
    s.iterations = 1
    _apply_correction(s, c, s.w_dx)
    return True


@inplace_kernel
def _reopen_tilt(s: StateRecord, c: CoefficientsRecord) -> None:
    """After rejecting the accelerometer too long: tilt variance back to its initial value.

    The next update then moves tilt most of the way to the accelerometer,
    while heading and bias keep what they know.
    """
    _set_attitude_covariance_world(s, c, c.initial_tilt_var, c.initial_heading_var, True, False)


@inplace_kernel
def _gyro_clipped(c: CoefficientsRecord, gyro: np.ndarray) -> bool:
    limit = c.gyro_clip
    return abs(gyro[0]) >= limit or abs(gyro[1]) >= limit or abs(gyro[2]) >= limit


# After a clipped gyro the vehicle is calm again once its rate stays under this
# (rad/s, bias removed) with ‖a‖ near g for _CALM_TIME (s): the accelerometer's
# direction is then gravity's, to within what a 30 °/s rotation adds.
_CALM_RATE = math.radians(30.0)
_CALM_TIME = 0.5


@inplace_kernel
def _realign_when_calm(
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
    if rate2 < _CALM_RATE * _CALM_RATE and _accel_usable_for_alignment(c, accel):
        s.clip_calm_time += dt
    else:
        s.clip_calm_time = 0.0
    if s.clip_calm_time < _CALM_TIME:
        return
    heading_from_mag = s.mag_state != 0
    _align(s, c, accel, True, True)
    if heading_from_mag:
        s.mag_state = 0  # the next field sample sets heading
    s.clip_calm_time = -1.0
    s.t_accel = t
    s.accel_used = 1
    s.flags = (s.flags & ~_ACCEL_DEFERRED) | _CLIP_REALIGNED


@inplace_kernel
def _lowpass_step(
    c: CoefficientsRecord, dt: float
) -> tuple[float, float, float, float, float, float]:
    """Φ (2×2) and Γ (2) of the second-order low-pass over Δt, input held constant.

    ÿ + 2ζω ẏ + ω² y = ω² u with ω = √2/τ; for ζ < 1, with σ = ζω and
    ω_d = ω √(1 − ζ²), Φ = e^(−σΔt) [[cos + (σ/ω_d) sin, sin/ω_d],
    [−ω² sin/ω_d, cos − (σ/ω_d) sin]] and Γ = [1 − Φ₀₀, −Φ₁₀] (unit DC gain);
    sin/ω_d is written Δt·sinc(ω_d Δt) so that ζ = 1 is its limit.
    """
    w = math.sqrt(2.0) / c.accel_lowpass_time
    zeta = c.accel_lowpass_damping
    sigma = zeta * w
    wd = w * math.sqrt(max(1.0 - zeta * zeta, 0.0))
    decay = math.exp(-sigma * dt)
    cosine = math.cos(wd * dt)
    sin_over_wd = dt * so3.sinc(wd * dt)
    p00 = decay * (cosine + sigma * sin_over_wd)
    p01 = decay * sin_over_wd
    p10 = -decay * w * w * sin_over_wd
    p11 = decay * (cosine - sigma * sin_over_wd)
    return p00, p01, p10, p11, 1.0 - p00, -p10


# Two Δt within this (relative) share one set of step coefficients. Timestamps
# differenced in floating point jitter in their last bits (k/1000 − (k−1)/1000
# takes 15 values over a minute), and an exact cache missed two samples in three;
# the coefficients' own change over 1e-9 of Δt is far below anything physical.
_SAME_DT = 1e-9


# The updates' schedule: an update is due at the sample nearest to update_interval
# after the last one. A tie (100 Hz samples with 40 Hz updates: 2.5 samples apart)
# goes to the earlier sample; this slack (s) keeps the timestamps' last-bit jitter
# from deciding it, which would make the schedule irregular.
_SCHEDULE_SLACK = 1e-9


@inplace_kernel
def _update_due(c: CoefficientsRecord, elapsed: float, dt: float) -> bool:
    """Whether ``elapsed`` since the last update reaches the sample (Δt = ``dt``) nearest
    to the update interval (a NaN, none yet, is due)."""
    return not elapsed < c.update_interval - 0.5 * dt - _SCHEDULE_SLACK


@inplace_kernel
def _step_coefficients(s: StateRecord, c: CoefficientsRecord, dt: float) -> None:
    """The coefficients that depend on Δt alone into ``s.step_coefficients``, computed
    again only when Δt changes: a steady rate computes them once."""
    out = s.step_coefficients
    if not abs(dt - s.step_coefficients_dt) <= _SAME_DT * dt:  # (also NaN: the first)
        if c.accel_lowpass_time > 0.0:
            out[0], out[1], out[2], out[3], out[4], out[5] = _lowpass_step(c, dt)
            out[6] = math.exp(-dt / c.velocity_time)
        out[7] = 1.0 - math.exp(-dt / c.rest_filter_time)
        s.step_coefficients_dt = dt


@inplace_kernel
def _absorb_sample(
    s: StateRecord, c: CoefficientsRecord, accel: np.ndarray, dt: float, direct: bool
) -> None:
    """The low-pass takes the sample; its errors and the velocity follow.

    For the first τ after priming, f̄ is the time-weighted running mean of R̄a
    (VQF's mean-initialised low-pass): f̄ ← β f̄ + (1 − β) R̄a with β = T/(T + Δt),
    T the time averaged so far, so its noise falls as σ_a²/T instead of lingering
    for τ; ḟ stays 0. Then the second-order step [f̄; ḟ] ← Φ [f̄; ḟ] + Γ R̄a.
    Per axis the errors take the same step with the sample's error η + a in
    place of R̄a, a = ((γ − 1) v + ξ)/Δt: with u = [ε, ḟ, v],

        u ← A u + b_η η + b_ξ ξ,   A = [[Φ₀₀, Φ₀₁, Γ₀ c], [Φ₁₀, Φ₁₁, Γ₁ c], [0, 0, γ]],
        b_η = [Γ₀, Γ₁, 0],  b_ξ = [Γ₀/Δt, Γ₁/Δt, 1],  c = (γ − 1)/Δt,

    var η = σ_a²/Δt, var ξ = σ_v² (1 − γ²).
    """
    so3.quat_rotate_into(s.q, accel, s.w_v3)  # R̄ a
    aided = _vector_is_finite(s.linear_accel)
    if aided:
        for i in range(3):
            s.w_v3[i] -= s.linear_accel[i]
    lp = s.accel_world_lp
    _step_coefficients(s, c, dt)
    step = s.step_coefficients
    primed = s.lowpass_time > 0.0  # f̄ holds a sample: the motion is measured against it
    if s.lowpass_time < c.accel_lowpass_time:
        beta = s.lowpass_time / (s.lowpass_time + dt)
        p00, p01, p10, p11, g0, g1 = beta, 0.0, 0.0, 1.0, 1.0 - beta, 0.0
        s.lowpass_time += dt
    else:
        p00, p01, p10, p11, g0, g1 = step[0], step[1], step[2], step[3], step[4], step[5]
    if primed and not aided:
        _track_motion(s, c, step[6], dt)
    for i in range(3):
        y, rate = lp[0, i], lp[1, i]
        lp[0, i] = p00 * y + p01 * rate + g0 * s.w_v3[i]
        lp[1, i] = p10 * y + p11 * rate + g1 * s.w_v3[i]
    gamma = step[6]
    cv = (gamma - 1.0) / dt
    a02, a12 = g0 * cv, g1 * cv
    var_eta = c.accel_var_density / dt
    var_xi = (c.aided_velocity_var if aided else _velocity_variance(s, c)) * (1.0 - gamma * gamma)
    b0, b1 = g0 / dt, g1 / dt
    # the step's own noise b_η b_ηᵀ var η + b_ξ b_ξᵀ var ξ on (ε, ḟ, v): its upper triangle
    n00 = g0 * g0 * var_eta + b0 * b0 * var_xi
    n01 = g0 * g1 * var_eta + b0 * b1 * var_xi
    n02 = b0 * var_xi
    n11 = g1 * g1 * var_eta + b1 * b1 * var_xi
    n12 = b1 * var_xi
    if c.accumulate and not direct:  # between updates (``direct``: P is up to date)
        noise = (n00, n01, n02, n11, n12, var_xi)
        _accumulate_absorb(s, c, (p00, p01, a02, p10, p11, a12, gamma), noise, g0, g1, aided)
        return
    n = c.n_state
    P = s.P
    for axis in range(N_AXES):
        e = _EPS + axis
        d = _RATE + axis
        v = _VEL + axis
        for j in range(n):  # rows: A P
            pe, pd, pv = P[e, j], P[d, j], P[v, j]
            P[e, j] = p00 * pe + p01 * pd + a02 * pv
            P[d, j] = p10 * pe + p11 * pd + a12 * pv
            P[v, j] = gamma * pv
        for i in range(n):  # columns: (A P) Aᵀ
            pe, pd, pv = P[i, e], P[i, d], P[i, v]
            P[i, e] = p00 * pe + p01 * pd + a02 * pv
            P[i, d] = p10 * pe + p11 * pd + a12 * pv
            P[i, v] = gamma * pv
        P[e, e] += n00
        P[e, d] += n01
        P[d, e] += n01
        P[d, d] += n11
        P[e, v] += n02
        P[v, e] += n02
        P[d, v] += n12
        P[v, d] += n12
        P[v, v] += var_xi
    if aided:
        _couple_aided_sample(s, c, g0, g1)


@inplace_kernel
def _horizontal_times(
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
def _aided_coupling(s: StateRecord, c: CoefficientsRecord) -> None:
    """w_aid = M = [a]× W: how the attitude error moves an aided sample (in the world)."""
    M = s.w_aid
    so3.hat_into(s.linear_accel, M)
    if c.error != ERROR_LEFT:
        R = s.w_R_tilt
        so3.matrix_from_quat_into(s.q, R)
        for i in range(3):
            r0, r1, r2 = M[i, 0], M[i, 1], M[i, 2]
            for j in range(3):
                s.w_m33[i, j] = r0 * R[0, j] + r1 * R[1, j] + r2 * R[2, j]
        copy_matrix_into(M, s.w_m33)


@inplace_kernel
def _couple_aided_sample(s: StateRecord, c: CoefficientsRecord, g0: float, g1: float) -> None:
    """The attitude error's part in an aided sample: [ε; ḟ] += [Γ₀; Γ₁] M δθ.

    With the known acceleration a removed, R̄f − a = Exp(−δθ_w)(a − g e₃) − a
    ≈ −g e₃ + [a]× δθ_w: a heading error now shows as a horizontal error of
    the sample (in a turn, the centripetal acceleration seen in the wrong
    direction). With δθ_w = W δθ, M = [a]× W, of which the x, y rows are
    carried (M's z row, the sample's vertical error, is not: layout.N_AXES).
    Exact as a linear map of the error, so P ← T P Tᵀ with T = I + (those
    rows): rows first (δθ's rows do not change), then columns. This
    correlation is what lets the gravity update see heading in turns, as a
    GPS-aided INS does.
    """
    _aided_coupling(s, c)
    M = s.w_aid
    n = c.n_state
    P = s.P
    skew = c.error == ERROR_LEFT  # M = [a]×
    for j in range(n):  # rows: T P
        m0, m1 = _horizontal_times(M, skew, P[0, j], P[1, j], P[2, j])
        P[_EPS, j] += g0 * m0
        P[_EPS + 1, j] += g0 * m1
        P[_RATE, j] += g1 * m0
        P[_RATE + 1, j] += g1 * m1
    for i in range(n):  # columns: (T P) Tᵀ
        m0, m1 = _horizontal_times(M, skew, P[i, 0], P[i, 1], P[i, 2])
        P[i, _EPS] += g0 * m0
        P[i, _EPS + 1] += g0 * m1
        P[i, _RATE] += g1 * m0
        P[i, _RATE + 1] += g1 * m1


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
    return max(s.P[_EPS, _EPS], s.P[_EPS + 1, _EPS + 1])


@inplace_kernel
def _take_accel(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray, dt: float) -> bool:
    """The accelerometer sample into the low-pass (when there is one); False if not finite."""
    if not _vector_is_finite(accel):
        s.flags |= _ACCEL_INVALID
        return False
    if _vector_is_finite(s.linear_accel):
        s.flags |= _ACCEL_AIDED
    if c.accel_lowpass_time > 0.0:
        if s.filters_primed == 2:  # primed with this very sample
            s.filters_primed = 1
        else:
            _absorb_sample(s, c, accel, dt, False)
    return True


@inplace_kernel
def accel_update(
    s: StateRecord, c: CoefficientsRecord, t: float, accel: np.ndarray, dt: float
) -> None:
    """The sample into the low-pass, then the gravity-direction update with the
    robustness checks; sets the step's diagnostics."""
    if not _take_accel(s, c, accel, dt):
        return
    _flush_pending(s, c)
    lowpass = c.accel_lowpass_time > 0.0
    aided = _vector_is_finite(s.linear_accel)
    if lowpass:
        so3.quat_conjugate_into(s.q, s.w_q4)
        so3.quat_rotate_into(s.w_q4, s.accel_world_lp[0], s.w_u3)  # R̄ᵀ f̄
    else:
        copy_into(s.w_u3, accel)
        if aided:  # f − R̄ᵀa (its heading coupling is not modelled)
            so3.quat_conjugate_into(s.q, s.w_q4)
            so3.quat_rotate_into(s.w_q4, s.linear_accel, s.w_v3)
            for i in range(3):
                s.w_u3[i] -= s.w_v3[i]
    f = s.w_u3
    norm = math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
    if not norm > _MIN_ACCEL_FRACTION * c.gravity:
        s.flags |= _ACCEL_INVALID
        return
    for i in range(3):
        s.w_z[i] = -f[i] / norm
    sphere.tangent_basis_into(s.w_z, s.w_Bz)
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
            s.flags |= _DIVERGED  # again, soon: _check_health re-initialises
            return
        _reopen_tilt(s, c)
        s.t_reopened = t
        gate = 0.0
        s.flags |= _TILT_REOPENED
    copy_into(s.w_q_before, s.q)
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
        extra = max(0.5 * (r0 * r0 + r1 * r1) - 0.5 * (s.w_S[0, 0] + s.w_S[1, 1]), 0.0)
        if lowpass:
            room = _EPS_ROOM * _linear_limit_variance(c) - _horizontal_eps_variance(s)
            into_eps = min(extra * g2, max(room, 0.0))
            for a in range(2):
                s.P[_EPS + a, _EPS + a] += into_eps
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
        so3.quat_divide_right_into(s.q, s.w_q_before, s.w_q4)  # the world-frame move
        cos_half_tilt = math.sqrt(min(s.w_q4[0] ** 2 + s.w_q4[3] ** 2, 1.0))
        if 2.0 * math.acos(cos_half_tilt) > c.lowpass_restart_angle:
            s.filters_primed = 0
            s.flags |= _LOWPASS_RESTARTED


@inplace_kernel
def _gravity_update(s: StateRecord, c: CoefficientsRecord, var: float, gate: float) -> bool:
    """The configured update (iterated or sigma-point); False if the gate stopped it."""
    if c.update == UPDATE_SIGMA_POINT:
        return _sigma_point_update(s, c, var, gate)
    return _iterated_update(s, c, var, gate)


# --------------------------------------------------------------------------
# The magnetometer: heading only
# --------------------------------------------------------------------------

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
    """w_dx = the error-frame vector of a turn by ψ about the world vertical."""
    _error_frame_from_world(s, c)  # world → error frame in w_m33
    for i in range(c.n_state):
        s.w_dx[i] = 0.0
    for i in range(3):
        s.w_dx[i] = s.w_m33[i, 2] * psi


@inplace_kernel
def _heading_variance(s: StateRecord, c: CoefficientsRecord) -> float:
    """The variance of the attitude error about the world vertical (rad²): vᵀ P_θθ v
    with v the vertical in the error frame (P[2, 2] for the left error)."""
    v0, v1, v2 = _vertical_in_error_frame(s, c)
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
    _apply_correction(s, c, s.w_dx)
    var = min(var, _MAX_ALIGNED_HEADING_VAR)
    _set_attitude_covariance_world(s, c, 0.0, var, False, True)


@inplace_kernel
def turn_heading(s: StateRecord, c: CoefficientsRecord, psi: float) -> None:
    """Turn the estimate by ψ about the world vertical, keeping its uncertainty.

    For a heading the magnetometer has referenced when the declination it was
    referenced to changes by ψ (the vehicle's COMPASS_DEC arriving after the
    first field sample): the estimate's error then has mean ψ about the
    vertical and the same spread, so this is a correction by ψ and its reset.
    """
    _flush_pending(s, c)
    _heading_step(s, c, psi)
    _apply_correction(s, c, s.w_dx)


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
    if not _vector_is_finite(mag):
        return  # no magnetometer in this sample
    if s.mag_state != 0 and not _update_due(c, t - s.t_mag, dt):
        s.flags |= _MAG_BETWEEN_UPDATES  # (its own schedule: the field may come at its own rate)
        return
    _clear_heading_report(s)
    _flush_pending(s, c)
    m = s.w_mag
    magnetic.calibrate_into(mag, c.mag_offsets, c.mag_soft_iron, m)
    azimuth, dip, norm = magnetic.field_geometry(s.q, m, s.w_u3)
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
        if _heading_variance(s, c) < c.mag_reopened_heading_var:
            _set_attitude_covariance_world(s, c, 0.0, c.mag_reopened_heading_var, False, True)
        s.mag_candidate_time = 0.0
        s.mag_clear_time = c.mag_recovery_time
        disturbed = False
        gate = 0.0
    nu = magnetic.wrap(azimuth - c.mag_declination)
    # The measurement: y = H δx + w, H = (H_τ, −1) in world axes, the tilt
    # error leaking into the azimuth through the dip (H_τ = tan(dip)·(cos d, sin d)).
    # H is taken at the reference field (its learned dip), the prediction, not
    # at this sample's dip: that carries the tilt error and the noise, and a
    # gain made from it grew with the very leak it discounts (module docstring).
    Hf = s.w_v3  # the full H (error frame)
    Hp = s.w_Hm  # its heading part H_ψ (the same at zero dip)
    magnetic.heading_jacobians_into(s.q, s.mag_ref_dip, c.mag_declination, c.error, s.w_R, Hf, Hp)
    n = c.n_state
    P = s.P
    C = s.w_Cm
    K = s.w_Km
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
    # correlation (see the module docstring for why) — and, being a slowly
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
    v0, v1, v2 = _vertical_in_error_frame(s, c)
    along = (v0 * C[0, 0] + v1 * C[1, 0] + v2 * C[2, 0]) / S
    K[0, 0], K[1, 0], K[2, 0] = v0 * along, v1 * along, v2 * along
    v0, v1, v2 = _vertical_in_body(s)  # the bias is a body-frame vector
    along = (v0 * C[3, 0] + v1 * C[4, 0] + v2 * C[5, 0]) / S
    K[3, 0], K[4, 0], K[5, 0] = v0 * along, v1 * along, v2 * along
    for i in range(_EPS, n):
        K[i, 0] = 0.0
    # The covariance for this gain and the real measurement: the Joseph form
    # with the full H, C = P Hᵀ, S = H P Hᵀ + R, so that what the leak and
    # the tilt–heading correlation do to the estimate is in P
    S_full = var_mag
    for i in range(n):
        C[i, 0] = P[i, 0] * Hf[0] + P[i, 1] * Hf[1] + P[i, 2] * Hf[2]
        if i < 3:
            S_full += Hf[i] * C[i, 0]
    s.w_Sm[0, 0] = S_full
    gain_update(P[:n, :n], K[:n], C[:n], s.w_Sm, 1)
    for i in range(n):
        s.w_dx[i] = K[i, 0] * nu
    _apply_correction(s, c, s.w_dx)
    s.mag_used = 1
    s.t_mag_used = t


# --------------------------------------------------------------------------
# Rest: detection and the zero-rate update of the bias
# --------------------------------------------------------------------------

# χ² (3 dof) at 99.9 %: a "rest" whose rate disagrees this much with the bias is motion.
_ZERO_RATE_GATE = 16.27


@inplace_kernel
def _detect_rest(
    s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, accel: np.ndarray, dt: float
) -> bool:
    """VQF's rest criteria: gyro and accel stay near their low-passes for rest_min_time.

    The gyro samples since the last update are summed while the criteria hold,
    for the zero-rate update to measure their mean.
    """
    if not (c.rest_detection and _vector_is_finite(accel)):
        s.rest_time = 0.0
        _restart_rest_mean(s)
        return False
    _step_coefficients(s, c, dt)
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
        _restart_rest_mean(s)
    return s.rest_time >= c.rest_min_time


@inplace_kernel
def _restart_rest_mean(s: StateRecord) -> None:
    for i in range(3):
        s.rest_gyro_sum[i] = 0.0
    s.rest_samples = 0
    s.rest_sum_time = 0.0


@inplace_kernel
def _zero_rate_update(s: StateRecord, c: CoefficientsRecord) -> None:
    """At rest the gyro measures its bias: y = ω̄_m − b̄, H = [0 I 0], V = σ_g²/T + σ_rest²,
    ω̄_m the mean of the samples since the last update (over T), all at rest."""
    _flush_pending(s, c)
    n = c.n_state
    var = c.gyro_var_density / s.rest_sum_time + c.rest_rate_var
    P = s.P
    S = s.w_S3
    for i in range(3):
        for j in range(3):
            S[i, j] = P[3 + i, 3 + j] + (var if i == j else 0.0)
    det = inverse_3x3_into(S, s.w_m33)  # S⁻¹ in w_m33
    if not det > 0.0:
        return
    y = s.w_v3
    for i in range(3):
        y[i] = s.rest_gyro_sum[i] / s.rest_samples - s.b[i]
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += y[i] * s.w_m33[i, j] * y[j]
    if not nis <= _ZERO_RATE_GATE:
        return
    K = s.w_K3
    C = s.w_C3  # P Hᵀ = P[:, b]
    for i in range(n):
        for j in range(3):
            C[i, j] = P[i, 3 + j]
        for j in range(3):
            acc = 0.0
            if i < _EPS:  # the considered states get no gain
                for k in range(3):
                    acc += C[i, k] * s.w_m33[k, j]
            K[i, j] = acc
    for i in range(n):
        s.w_dx[i] = K[i, 0] * y[0] + K[i, 1] * y[1] + K[i, 2] * y[2]
    gain_update(P[:n, :n], K[:n], C[:n], S, 3)
    _apply_correction(s, c, s.w_dx)
    s.at_rest = 1


# --------------------------------------------------------------------------
# One sample
# --------------------------------------------------------------------------


@inplace_kernel
def _accel_usable_for_alignment(c: CoefficientsRecord, accel: np.ndarray) -> bool:
    norm = math.sqrt(accel[0] ** 2 + accel[1] ** 2 + accel[2] ** 2)
    return (
        math.isfinite(norm)
        and norm > _MIN_ACCEL_FRACTION * c.gravity
        and abs(norm - c.gravity) <= max(c.accel_norm_tolerance, 0.0)
    )


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
    _step_sample(s, c, t, gyro, accel, mag)
    if s.initialised:
        _check_health(s, c, accel)  # (its LDLᵀ reads one triangle)
    # The structured products round the two triangles differently: the whole P is
    # made symmetric at the updates, the estimate's own 6×6 at every sample.
    symmetrise(
        s.P[:N_ERROR, :N_ERROR] if s.flags & _BETWEEN_UPDATES else s.P[: c.n_state, : c.n_state]
    )


@inplace_kernel
def _clear_gravity_report(s: StateRecord) -> None:
    s.nis = math.nan
    s.innovation[0] = math.nan
    s.innovation[1] = math.nan


@inplace_kernel
def _clear_heading_report(s: StateRecord) -> None:
    s.heading_innovation = math.nan
    s.heading_nis = math.nan


@inplace_kernel
def _set_aside_mag(s: StateRecord, mag: np.ndarray) -> None:
    """The sample's magnetometer reading, if it has one, is not looked at (the attitude
    it would correct is not known): say so."""
    if _vector_is_finite(mag):
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
    if math.isfinite(t) and _vector_is_finite(gyro) and _accel_usable_for_alignment(c, accel):
        _align(s, c, accel, False, False)
        s.initialised = 1
        s.t = t
        s.t_accel = t
        s.samples += 1
        s.flags = _INITIALISED
        s.accel_used = 1
        mag_update(s, c, t, mag, 0.0)
    else:
        s.flags = _NOT_INITIALISED
        if s.samples == 0 and _judge_accel_unit(s, c, t, accel):
            s.flags |= _ACCEL_WRONG_UNIT


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
    for k in range(len(_UNIT_SCALES)):
        if abs(norm * _UNIT_SCALES[k] - c.gravity) <= _UNIT_TOLERANCE * c.gravity:
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
    _flush_pending(s, c)
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
        _clear_gravity_report(s)
        _clear_heading_report(s)
        _initialise(s, c, t, gyro, accel, mag)
        return
    dt = t - s.t
    if _vector_is_finite(gyro) and far_off_kernel(dt, c.reorder_window, c.max_jump):
        if not _new_timeline_confirmed(s, c, t):
            s.flags = _TIME_OFF_TIMELINE
            _clear_gravity_report(s)
            _clear_heading_report(s)
            return
        if not dt > 0.0:  # time went back and stayed: the clock restarted
            _restart_timeline(s, c)
            _initialise(s, c, t, gyro, accel, mag)
            s.flags |= _TIME_RESTARTED
            return
        # forward, and it stayed: a gap (below)
    if not dt > 0.0 or not _vector_is_finite(gyro):  # (also NaN)
        s.flags = _TIME_NOT_INCREASING if not dt > 0.0 else _GYRO_INVALID
        _clear_gravity_report(s)
        _clear_heading_report(s)
        return
    s.timeline_count = 0  # on the timeline: a far-off sample before was a corrupted one
    s.samples += 1
    if dt > c.max_dt:
        _clear_gravity_report(s)
        _clear_heading_report(s)
        _flush_pending(s, c)
        # Nothing is known of the motion in the gap: re-align tilt from this
        # sample's accelerometer, keep heading and bias (which drift slowly).
        if _accel_usable_for_alignment(c, accel):
            for i in range(3):
                s.P[3 + i, 3 + i] += c.bias_var_density * dt
            _align(s, c, accel, True, True)
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
    if _gyro_clipped(c, gyro):
        s.clip_calm_time = 0.0
        s.flags |= _GYRO_CLIPPED
    if _vector_is_finite(s.linear_accel) and _heading_variance(s, c) > c.aided_max_heading_var:
        # The known acceleration is known in the world frame: with heading this
        # uncertain, turning it into the body would be a guess, and the linear
        # model of that guess's error meaningless. Unaided until heading is known.
        s.linear_accel[0] = math.nan
    if not s.filters_primed and _vector_is_finite(accel):
        _prime_filters(s, c, gyro, accel, dt)
        s.filters_primed = 2  # tells accel_update the low-pass already holds this sample
    if s.clip_calm_time >= 0.0:  # nothing corrects an attitude that is not known
        _clear_gravity_report(s)
        _clear_heading_report(s)
        _realign_when_calm(s, c, t, gyro, accel, dt)
        _set_aside_mag(s, mag)
        return
    at_rest = _detect_rest(s, c, gyro, accel, dt)
    if not _update_due(c, t - s.t_update, dt):
        # not due: the sample is predicted (above) and its accelerometer averaged
        # into the low-pass, whose error the covariance carries to the next update;
        # what the last update measured is still reported
        s.flags |= _BETWEEN_UPDATES
        _take_accel(s, c, accel, dt)
        mag_update(s, c, t, mag, dt)
        return
    s.t_update = t
    _clear_gravity_report(s)
    if at_rest:
        _zero_rate_update(s, c)
    _restart_rest_mean(s)
    accel_update(s, c, t, accel, dt)
    mag_update(s, c, t, mag, dt)


# --------------------------------------------------------------------------
# Health
# --------------------------------------------------------------------------

# Beyond these the state is a numerical accident, not an estimate.
_MAX_BIAS = 0.5  # rad/s per axis (29°/s: beyond any MEMS gyro's offset, calibrated or not)
_MAX_ATTITUDE_VAR = 4.0 * math.pi**2  # rad², any δθ axis (heading is capped at π², below)
_MAX_CONSIDERED_VAR = 1e6  # (m/s²)², (m/s³)², (m/s)²: ε, ḟ, v
# Heading's σ never exceeds 180°: a wrapped normal that wide is as good as uniform,
# and the linear model of a wider one means nothing (6-D, hours without a compass).
_MAX_HEADING_VAR = math.pi**2
_FULL_CHECK_EVERY = 64  # checks


@inplace_kernel
def _cap_heading_variance(s: StateRecord, c: CoefficientsRecord) -> None:
    """Heading's variance at most _MAX_HEADING_VAR: its row and column in world axes
    scaled by f (P ← D P D, D = diag(1, 1, f) on δθ: a congruence, so P stays definite)."""
    var = _heading_variance(s, c)
    if not var > _MAX_HEADING_VAR:
        return
    _flush_pending(s, c)
    f = math.sqrt(_MAX_HEADING_VAR / var)
    _attitude_covariance_to_world(s, c)
    for j in range(c.n_state):
        s.P[2, j] *= f
        s.P[j, 2] *= f
    _attitude_covariance_from_world(s, c)


@inplace_kernel
def _state_is_plausible(s: StateRecord, c: CoefficientsRecord) -> bool:
    """Nominal finite and a unit quaternion, bias plausible, every variance within its
    bound (NaN fails every test): what a sample between updates is checked for. (There,
    with the transition pending, the considered rows are not written: the estimate's
    own variances are what can have changed.)"""
    q_norm2 = s.q[0] ** 2 + s.q[1] ** 2 + s.q[2] ** 2 + s.q[3] ** 2
    if not abs(q_norm2 - 1.0) < 1e-6:  # also NaN
        return False
    for i in range(3):
        if not abs(s.b[i]) <= _MAX_BIAS:
            return False
    n = N_ERROR if s.pending_steps > 0 else c.n_state
    for i in range(n):
        bound = _MAX_ATTITUDE_VAR if i < 3 else _MAX_BIAS**2 if i < N_ERROR else _MAX_CONSIDERED_VAR
        if not 0.0 <= s.P[i, i] <= bound:
            return False
    return True


@inplace_kernel
def _state_is_healthy(s: StateRecord, c: CoefficientsRecord) -> bool:
    """:func:`_state_is_plausible`, and P positive definite (LDLᵀ pivots; P is
    symmetric by construction, symmetrise runs at every update)."""
    if not _state_is_plausible(s, c):
        return False
    n = c.n_state
    # The estimate's own 6×6 at every check; the whole, with the considered states, every
    # _FULL_CHECK_EVERY checks: its factorisation would add a fifth to a step. (ε and ḟ
    # are exactly zero until the low-pass holds a sample: semi-definite then.)
    s.health_checks += 1
    m = n if s.filters_primed and s.health_checks % _FULL_CHECK_EVERY == 0 else N_ERROR
    if m > N_ERROR:
        _flush_pending(s, c)
    return is_positive_definite(s.P[:m, :m], s.w_T[:m, :m])


@inplace_kernel
def _reinitialise(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray) -> None:
    """Start again from this sample's accelerometer, keeping heading if it is finite
    (what else knows it, in 6-D?); the bias starts again from its prior, as it may
    be what went wrong. Without a usable accelerometer: uninitialised, and the
    next usable sample initialises."""
    keep_heading = _vector_is_finite(s.q[1:]) and math.isfinite(s.q[0])
    _restart_motion(s, c)  # (measured with the broken attitude, it may be what broke)
    if keep_heading:
        so3.quat_normalize_into(s.q)
    else:
        s.q[0] = 1.0
        for i in range(1, 4):
            s.q[i] = 0.0
    if _accel_usable_for_alignment(c, accel):
        _align(s, c, accel, keep_heading, False)
        s.t_accel = s.t
    else:
        s.w_u3[0] = 0.0  # a placeholder attitude with a valid covariance
        s.w_u3[1] = 0.0
        s.w_u3[2] = -c.gravity
        _align(s, c, s.w_u3, keep_heading, False)
        s.initialised = 0
        s.flags |= _NOT_INITIALISED


@inplace_kernel
def _check_health(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray) -> None:
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
        healthy = _state_is_plausible(s, c)
    else:
        healthy = _state_is_healthy(s, c)
    if not healthy:
        _reinitialise(s, c, accel)
        s.flags |= _UNHEALTHY_RESET
        s.unhealthy_resets += 1
