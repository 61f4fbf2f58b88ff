"""Prediction: the nominal and P carried over a sample with the gyroscope, and
what happens between updates (the pending transition, the updates' schedule).

Prediction (docs/design.md#prediction), ω̂ = ω_m − b̄, φ = ω̂ Δt, each sample's own Δt:

    R̄ ← R̄ Exp(φ)                                       (exact for constant rate)
    Φ = [[I, −R̄ J_l(φ) Δt], [0, I]]                     (left error)
    Φ = [[Exp(−φ), −J_r(φ) Δt], [0, I]]                 (right error)
    Q = [[(σ_g²Δt + σ_b²Δt³/3) I, −σ_b²Δt²/2 M], [·, σ_b²Δt I]]

with M = R̄ (left) or Exp(−φ) (right, its adjoint image). With the low-pass the
attitude error moves its error ε too, ε ← ε + g E W Δθ (:mod:`mavest.estimator.lowpass`).
The sigma-point filter propagates its sigma points through the exact dynamics
instead (:func:`_predict_sigma_point`).
"""

from __future__ import annotations

import numpy as np

from mavest import so3
from mavest._jit import inplace_inlined_kernel, inplace_kernel
from mavest.estimator.charts import local_into, retract_into
from mavest.estimator.frames import (
    EPS,
    RATE,
    aided_coupling,
    apply_correction,
    horizontal_times,
    set_identity,
)
from mavest.estimator.layout import (
    ERROR_LEFT,
    N_AXES,
    N_CONSIDER,
    N_ERROR,
    N_STATE_MAX,
    UPDATE_SIGMA_POINT,
    CoefficientsRecord,
    StateRecord,
)
from mavest.estimator.linalg import cholesky_into, copy_into, copy_matrix_into


@inplace_kernel
def _process_noise_rotation(s: StateRecord, c: CoefficientsRecord, phi: np.ndarray) -> None:
    """The rotation M in Q's cross term: R̄ before the step for the left error, which
    w_propagation_R must hold already; for the right error Exp(−φ), into
    w_propagation_n33, its image under the adjoint, so that left and right filters stay
    the same filter (with the full reset they give the same estimate:
    docs/design.md#recursion-and-reset)."""
    if c.error != ERROR_LEFT:
        so3.exp_into(phi, s.w_propagation_m33)
        for i in range(3):
            for j in range(3):
                s.w_propagation_n33[i, j] = s.w_propagation_m33[j, i]  # Exp(−φ) = Exp(φ)ᵀ


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
        R = s.w_propagation_R_tilt
        so3.matrix_from_quat_into(s.q, R)
        for j in range(3):
            out[0, j] = -g * R[1, j]
            out[1, j] = g * R[0, j]


@inplace_kernel
def _add_process_noise(
    s: StateRecord, c: CoefficientsRecord, dt: float, n: int, rate_sq: float
) -> None:
    """P[:n, :n] += Q_d (Van Loan, with the cross term's rotation M, w_propagation_R or
    w_propagation_n33: :func:`_process_noise_rotation`). ``rate_sq``: the step's |ω|², which the
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
    M = s.w_propagation_R if c.error == ERROR_LEFT else s.w_propagation_n33
    for i in range(3):
        P[i, i] += q_aa
        P[3 + i, 3 + i] += q_bb
        for j in range(3):
            v = q_ab * M[i, j]
            P[i, 3 + j] += v
            P[3 + j, i] += v
    if n == N_ERROR:
        return
    G = s.w_propagation_tilt
    _world_tilt_rows(s, c, G)
    # ε receives G Δθ; the low-pass's rate ḟ does not
    for a in range(2):
        for j in range(3):
            # Q_εθ = G Q_θθ = q_aa G ;  Q_εb = G Q_θb = q_ab G M
            cross_b = 0.0
            for k in range(3):
                cross_b += G[a, k] * M[k, j]
            P[EPS + a, j] += q_aa * G[a, j]
            P[j, EPS + a] += q_aa * G[a, j]
            P[EPS + a, 3 + j] += q_ab * cross_b
            P[3 + j, EPS + a] += q_ab * cross_b
        for b in range(2):  # Q_εε = q_aa G Gᵀ
            acc = 0.0
            for k in range(3):
                acc += G[a, k] * G[b, k]
            P[EPS + a, EPS + b] += q_aa * acc


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
    joins the pending transition of the considered rows (:func:`flush_pending`).
    """
    if c.accumulate:  # (before P's 6×6 moves: the interval starts from it)
        _open_pending(s)
    n = N_ERROR if c.accumulate else c.n_state
    phi = s.w_propagation_phi
    for i in range(3):
        phi[i] = (gyro[i] - s.b[i]) * dt
    R = s.w_propagation_R
    so3.matrix_from_quat_into(s.q, R)
    _process_noise_rotation(s, c, phi)  # w_propagation_n33: also Φ_θθ = Exp(−φ) (right error)
    F = s.w_propagation_m33  # Φ_θb
    turn = s.w_propagation_q4  # Exp(φ)
    if c.error == ERROR_LEFT:
        J = s.w_propagation_T  # J_l(φ), in its 3×3 corner
        so3.quat_exp_and_jacobian_into(phi, turn, J[:3, :3], True)
        for i in range(3):
            for j in range(3):
                F[i, j] = -dt * (R[i, 0] * J[0, j] + R[i, 1] * J[1, j] + R[i, 2] * J[2, j])
    else:
        so3.quat_exp_and_jacobian_into(phi, turn, F, False)
        for i in range(3):
            for j in range(3):
                F[i, j] *= -dt
    copy_into(s.w_propagation_p4, s.q)
    so3.quat_multiply_into(s.w_propagation_p4, turn, s.q)
    so3.quat_normalize_into(s.q)
    G = s.w_propagation_G  # ε x, y rows of Φ: G Φ_θb, with G = g E W after the step
    if c.n_state > N_ERROR:
        tilt = s.w_propagation_tilt
        _world_tilt_rows(s, c, tilt)
        for a in range(2):
            for j in range(3):
                G[a, j] = tilt[a, 0] * F[0, j] + tilt[a, 1] * F[1, j] + tilt[a, 2] * F[2, j]
    right = c.error != ERROR_LEFT
    E = s.w_propagation_n33
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
            P[EPS, j] += G[0, 0] * b0 + G[0, 1] * b1 + G[0, 2] * b2
            P[EPS + 1, j] += G[1, 0] * b0 + G[1, 1] * b1 + G[1, 2] * b2
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
            P[i, EPS] += G[0, 0] * b0 + G[0, 1] * b1 + G[0, 2] * b2
            P[i, EPS + 1] += G[1, 0] * b0 + G[1, 1] * b1 + G[1, 2] * b2
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
# needs the whole P (:func:`flush_pending`). P's 6×6, what the estimate shows,
# is propagated every sample as before.
#
# Exact but for one thing: the attitude noise a prediction adds reaches ε too
# (ε moves with δθ, G Δθ), and the accumulated transition carries that as if it
# came at the flush: the low-pass's dynamics over the rest of the interval (ωΔT
# with ω = √2/τ: 1.2 % at 40 Hz for τ = 3 s) and an aided sample's share of it are
# left out of that part of the noise. The low-pass's own noise (η, ξ) is
# accumulated exactly.

N_STATE = N_STATE_MAX  # with the low-pass: what the pending transition carries


@inplace_kernel
def _open_pending(s: StateRecord) -> None:
    """Another transition joins the pending one; the first after a flush starts a new
    interval: P's 6×6 as it stands, the identity transition, no noise."""
    s.pending_steps += 1
    if s.pending_steps > 1:
        return
    copy_matrix_into(s.pending_P6, s.P[:N_ERROR, :N_ERROR])
    set_identity(s.pending_theta)
    set_identity(s.pending_stage)
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
    """The prediction :func:`_predict_linear` just made (Φ_θθ in w_propagation_n33 for
    the right error, Φ_θb in w_propagation_m33, G Φ_θb in w_propagation_G) after the
    pending transition."""
    F = s.w_propagation_m33
    theta = s.pending_theta
    bias = s.pending_bias
    if c.error != ERROR_LEFT:  # Θθ ← E Θθ, Θb ← E Θb (E = Exp(−φ))
        E = s.w_propagation_n33
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
                s.pending_U[a, 3 + j] += s.w_propagation_G[a, j]


@inplace_kernel
def accumulate_absorb(
    s: StateRecord,
    c: CoefficientsRecord,
    A: tuple[float, float, float, float, float, float, float],
    noise: tuple[float, float, float, float, float, float],
    g0: float,
    g1: float,
    aided: bool,
) -> None:
    """The low-pass's step (:func:`~mavest.estimator.lowpass.absorb_sample`) after the
    pending transition: u ← (A ⊗ I₂) u with A = [[a00, a01, a02], [a10, a11, a12],
    [0, 0, γ]] (``A`` those seven), its noise (``noise``: N's upper triangle) added, and
    with a known acceleration the aided sample's coupling, [ε; ḟ] += [Γ₀; Γ₁] M δθ."""
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
    M = s.w_propagation_aid
    aided_coupling(s, c, M)  # the current δθ is Θθ δθ₀ + Θb δb₀
    s.pending_aided = 1
    skew = c.error == ERROR_LEFT  # M = [a]×
    for j in range(N_ERROR):
        T = s.pending_theta if j < 3 else s.pending_bias
        k = j % 3
        m0, m1 = horizontal_times(M, skew, T[0, k], T[1, k], T[2, k])
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
def flush_pending(s: StateRecord, c: CoefficientsRecord) -> None:
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
    # Q₆'s δθ rows (all that reaches ε) into B[:3, :6], via Φ₆'s δθ rows times P₆
    PhiP = s.w_propagation_A
    for i in range(3):
        for j in range(N_ERROR):
            acc = 0.0
            for k in range(3):
                acc += theta[i, k] * P6[k, j] + bias[i, k] * P6[3 + k, j]
            PhiP[i, j] = acc
    Q = s.w_propagation_B
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += PhiP[i, k] * theta[j, k] + PhiP[i, 3 + k] * bias[j, k]
            Q[i, j] = P[i, j] - acc
            Q[i, 3 + j] = P[i, 3 + j] - PhiP[i, 3 + j]
    G = s.w_propagation_tilt
    _world_tilt_rows(s, c, G)
    GQ = s.w_propagation_GQ  # G Q₆'s δθ rows (2×6), transposed; G Q₆θθ Gᵀ below
    for a in range(2):
        for j in range(N_ERROR):
            GQ[j, a] = _row_times_column(G, a, Q, j)
    # V = Λ X into A[6:, :6]; Z = V + U P₆ into B[6:, :6]
    V = s.w_propagation_A
    Z = s.w_propagation_B
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
    # Λ Y's rows into T[6:, 6:], then the new P_uu (lower triangle, mirrored)
    LY = s.w_propagation_T
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
            if r < RATE and q < RATE:  # Q_εε = G Q₆θθ Gᵀ
                a = q - EPS
                acc += GQ[0, r - EPS] * G[a, 0] + GQ[1, r - EPS] * G[a, 1]
                acc += GQ[2, r - EPS] * G[a, 2]
            P[r, q] = acc
            P[q, r] = acc
    # the new P_u6 = Z Φ₆ᵀ + Q_u6 last: Z and V were made from the old one
    for r in range(N_ERROR, N_STATE):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += Z[r, k] * theta[j, k] + Z[r, 3 + k] * bias[j, k]
            if r < RATE:  # Q_ε6 = G Q₆'s δθ rows
                acc += GQ[j, r - EPS]
            P[r, j] = acc
            P[j, r] = acc
            acc = Z[r, 3 + j]
            if r < RATE:
                acc += GQ[3 + j, r - EPS]
            P[r, 3 + j] = acc
            P[3 + j, r] = acc


@inplace_kernel
def sigma_points(s: StateRecord, c: CoefficientsRecord, chi: np.ndarray) -> bool:
    """chi's rows (2n + 1 of them) = 0, ±columns of √((n + λ) P) (Cholesky). False if P
    is not PD."""
    n = c.n_state
    A = s.w_propagation_B[:n, :n]
    L = s.w_propagation_A[:n, :n]
    for i in range(n):
        for j in range(n):
            A[i, j] = c.sigma_spread * s.P[i, j]
    if not cholesky_into(A, L):
        return False
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
    """mean = Σ wᵢ χᵢ and P = Σ wᵢᶜ (χᵢ − mean)(χᵢ − mean)ᵀ over w_propagation_sigma_chi."""
    n = c.n_state
    chi = s.w_propagation_sigma_chi
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
    chi = s.w_propagation_sigma_chi
    if not sigma_points(s, c, chi):
        return False
    n = c.n_state
    so3.matrix_from_quat_into(s.q, s.w_propagation_R)  # R̄ before the step, for Q_d
    phi = s.w_propagation_phi
    for i in range(3):
        phi[i] = (gyro[i] - s.b[i]) * dt
    rate_sq = _rate_squared(phi, dt)
    _process_noise_rotation(s, c, phi)
    # the new reference: the nominal propagated with the nominal bias
    so3.quat_exp_into(phi, s.w_propagation_q4)
    so3.quat_multiply_into(s.q, s.w_propagation_q4, s.w_propagation_prior_q)
    so3.quat_normalize_into(s.w_propagation_prior_q)
    G_before = s.w_propagation_tilt_before  # ε rows before the step (W = R̄)
    if n > N_ERROR:
        _world_tilt_rows(s, c, G_before)
    qk = s.w_propagation_point_q  # the sigma point's attitude, one point at a time
    for k in range(2 * n + 1):
        retract_into(s.q, chi[k, :3], c.error, c.chart, qk, s.w_propagation_q4)
        for i in range(3):
            phi[i] = (gyro[i] - s.b[i] - chi[k, 3 + i]) * dt
        so3.quat_exp_into(phi, s.w_propagation_q4)
        copy_into(s.w_propagation_p4, qk)
        so3.quat_multiply_into(s.w_propagation_p4, s.w_propagation_q4, qk)
        if n > N_ERROR:
            for a in range(2):
                acc = 0.0
                for j in range(3):
                    acc += G_before[a, j] * chi[k, j]
                chi[k, EPS + a] -= acc
        local_into(qk, s.w_propagation_prior_q, c.error, c.chart, chi[k, :3], s.w_propagation_q4)
    copy_into(s.q, s.w_propagation_prior_q)
    if n > N_ERROR:
        G_after = s.w_propagation_tilt
        _world_tilt_rows(s, c, G_after)  # W' = R̄ after the step
        for k in range(2 * n + 1):
            for a in range(2):
                acc = 0.0
                for j in range(3):
                    acc += G_after[a, j] * chi[k, j]
                chi[k, EPS + a] += acc
    _weighted_mean_and_covariance_of_chi(s, c, s.w_propagation_dx)
    for i in range(EPS, n):  # ε is considered: its mean stays zero
        s.w_propagation_dx[i] = 0.0
    _add_process_noise(s, c, dt, n, rate_sq)
    apply_correction(s, c, s.w_propagation_dx)
    return True


@inplace_kernel
def predict(s: StateRecord, c: CoefficientsRecord, gyro: np.ndarray, dt: float) -> None:
    """Propagate nominal and covariance over Δt with the gyroscope sample."""
    if c.update == UPDATE_SIGMA_POINT and _predict_sigma_point(s, c, gyro, dt):
        return
    _predict_linear(s, c, gyro, dt)


# The updates' schedule: an update is due at the sample nearest to update_interval
# after the last one. A tie (100 Hz samples with 40 Hz updates: 2.5 samples apart)
# goes to the earlier sample; this slack (s) keeps the timestamps' last-bit jitter
# from deciding it, which would make the schedule irregular.
_SCHEDULE_SLACK = 1e-9


@inplace_kernel
def update_due(c: CoefficientsRecord, elapsed: float, dt: float) -> bool:
    """Whether ``elapsed`` since the last update reaches the sample (Δt = ``dt``) nearest
    to the update interval (a NaN, none yet, is due)."""
    return not elapsed < c.update_interval - 0.5 * dt - _SCHEDULE_SLACK
