"""The low-passed accelerometer: what the gravity update measures when
``accel_lowpass_time`` τ > 0, its errors carried as considered states, and the
vehicle's velocity behind them.

The filter then measures gravity with f̄, a second-order low-pass (state f̄ and its rate ḟ,
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
about the vertical, :func:`~mavest.estimator.frames.world_move_into`.) The vertical
ε is invisible to the measurement and to the lag, and with the reset's turn about the
vertical alone nothing moves it into the horizontal: ε, ḟ and v are carried along the
world's x and y only (:data:`~mavest.estimator.layout.N_AXES`).

Linear acceleration a is what the low-pass is for, and what makes its error
coloured: it is the derivative of a bounded velocity. The vehicle's velocity
v is modelled as Gauss–Markov (σ_v, T_v) and carried too, a held over each
sample: v ← γ v + ξ, a = ((γ − 1) v + ξ)/Δt, γ = e^(−Δt/T_v). The low-pass
averages such an a away (its integral stays bounded), which this model lets
the filter know, and its covariance then honestly holds what is left.
ε, ḟ and v are *considered* states (Schmidt): their covariance and correlations shape the
gain and are updated with their gain rows set to zero, but their means are
never estimated. Estimating them would turn the filter back into the
raw-accelerometer filter; considering them keeps the low-pass — what makes
the estimate robust to linear acceleration — and keeps the covariance the true
covariance of that estimator.
"""

from __future__ import annotations

import math

import numpy as np

from mavest import so3
from mavest._jit import inplace_kernel
from mavest.estimator.config import MAX_SPECIFIC_FORCE
from mavest.estimator.frames import (
    EPS,
    RATE,
    VEL,
    aided_coupling,
    horizontal_times,
    vector_is_finite,
    within,
)
from mavest.estimator.layout import (
    ERROR_LEFT,
    N_AXES,
    N_ERROR,
    CoefficientsRecord,
    StateRecord,
    StepFlags,
)
from mavest.estimator.propagation import accumulate_absorb

_ACCEL_INVALID = StepFlags.ACCEL_INVALID
_ACCEL_AIDED = StepFlags.ACCEL_AIDED


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


@inplace_kernel
def step_coefficients(s: StateRecord, c: CoefficientsRecord, dt: float) -> None:
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
def accel_is_valid(accel: np.ndarray) -> bool:
    """Whether an accelerometer sample is a measurement: within any accelerometer's range
    (MAX_SPECIFIC_FORCE, which a NaN is not), and not zero on all three axes (no real
    sensor reads exactly nothing: noise alone moves it; all zero is an empty field).
    StepFlags.ACCEL_INVALID says a sample is not. A value beyond the range is a corrupt
    one: averaged into the low-pass it would hold the direction of gravity away for the
    low-pass's seconds, and every update after it rejected."""
    return within(accel, MAX_SPECIFIC_FORCE) and (
        accel[0] != 0.0 or accel[1] != 0.0 or accel[2] != 0.0
    )


@inplace_kernel
def take_accel(s: StateRecord, c: CoefficientsRecord, accel: np.ndarray, dt: float) -> bool:
    """The accelerometer sample into the low-pass (when there is one); False if it is not
    a measurement (:func:`accel_is_valid`)."""
    if not accel_is_valid(accel):
        s.flags |= _ACCEL_INVALID
        return False
    if vector_is_finite(s.linear_accel):
        s.flags |= _ACCEL_AIDED
    if c.accel_lowpass_time > 0.0:
        if s.filters_primed == 2:  # primed with this very sample
            s.filters_primed = 1
        else:
            absorb_sample(s, c, accel, dt, False)
    return True


@inplace_kernel
def absorb_sample(
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
    sample = s.w_lowpass_sample
    so3.quat_rotate_into(s.q, accel, sample)  # R̄ a
    aided = vector_is_finite(s.linear_accel)
    if aided:
        for i in range(3):
            sample[i] -= s.linear_accel[i]
    lp = s.accel_world_lp
    step_coefficients(s, c, dt)
    step = s.step_coefficients
    primed = s.lowpass_time > 0.0  # f̄ holds a sample: the motion is measured against it
    if s.lowpass_time < c.accel_lowpass_time:
        beta = s.lowpass_time / (s.lowpass_time + dt)
        p00, p01, p10, p11, g0, g1 = beta, 0.0, 0.0, 1.0, 1.0 - beta, 0.0
        s.lowpass_time += dt
    else:
        p00, p01, p10, p11, g0, g1 = step[0], step[1], step[2], step[3], step[4], step[5]
    if primed and not aided:
        _track_motion(s, c, sample, step[6], dt)
    for i in range(3):
        y, rate = lp[0, i], lp[1, i]
        lp[0, i] = p00 * y + p01 * rate + g0 * sample[i]
        lp[1, i] = p10 * y + p11 * rate + g1 * sample[i]
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
        accumulate_absorb(s, c, (p00, p01, a02, p10, p11, a12, gamma), noise, g0, g1, aided)
        return
    n = c.n_state
    P = s.P
    for axis in range(N_AXES):
        e = EPS + axis
        d = RATE + axis
        v = VEL + axis
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
    M = s.w_lowpass_aid
    aided_coupling(s, c, M)
    n = c.n_state
    P = s.P
    skew = c.error == ERROR_LEFT  # M = [a]×
    for j in range(n):  # rows: T P
        m0, m1 = horizontal_times(M, skew, P[0, j], P[1, j], P[2, j])
        P[EPS, j] += g0 * m0
        P[EPS + 1, j] += g0 * m1
        P[RATE, j] += g1 * m0
        P[RATE + 1, j] += g1 * m1
    for i in range(n):  # columns: (T P) Tᵀ
        m0, m1 = horizontal_times(M, skew, P[i, 0], P[i, 1], P[i, 2])
        P[i, EPS] += g0 * m0
        P[i, EPS + 1] += g0 * m1
        P[i, RATE] += g1 * m0
        P[i, RATE + 1] += g1 * m1


@inplace_kernel
def reset_velocity_covariance(s: StateRecord, c: CoefficientsRecord) -> None:
    """Nothing known of the vehicle's velocity: its stationary variance, uncorrelated."""
    n = c.n_state
    if n == N_ERROR:
        return
    for i in range(VEL, n):
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
def restart_motion(s: StateRecord, c: CoefficientsRecord) -> None:
    """The motion level back to the one assumed before any data."""
    for i in range(3):
        s.motion_velocity[i] = 0.0
    s.motion_var = c.velocity_var


@inplace_kernel
def _track_motion(
    s: StateRecord, c: CoefficientsRecord, sample: np.ndarray, gamma: float, dt: float
) -> None:
    """The vehicle's motion level from this sample (``sample``: R̄ a, before the
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
        v = gamma * s.motion_velocity[i] + (sample[i] - s.accel_world_lp[0, i]) * dt
        s.motion_velocity[i] = v
        square += v * v
    alpha = dt / (c.velocity_adapt_time + dt)
    s.motion_var += alpha * (c.velocity_adapt_gain * square / N_AXES - s.motion_var)
