"""A plain NumPy reference of the attitude filter, written from docs/design.md.

Slow and readable on purpose: one sample at a time, whole matrices, every product
written as the design states it (``Φ P Φᵀ + Q``, ``T P Tᵀ``, the Joseph form). It
shares no code with the compiled kernels (it uses NumPy and
:class:`~mavest.estimator.config.EstimatorConfig` only), so that a mistake in the
kernels cannot also be here; ``tests/test_reference.py`` runs both on simulated
flights and on BROAD and holds them to a stated tolerance.

**Scope.** The default filter, ``iterated/left/heading_tilt/full`` with the
world-frame low-pass and its considered states, 6-D (gyroscope and accelerometer)
and 9-D (with a magnetometer), on well-behaved input: time increasing by at most
``max_dt`` a sample, a finite gyroscope below ``gyro_clip``, a finite
accelerometer. It covers, each step naming its section of docs/design.md:

- the initial alignment from the accelerometer, and heading from the first field;
- the prediction of the nominal and of the covariance, with the process noise;
- the low-pass of the specific force in the estimated world frame (its mean
  initialisation, its restart) and its considered states ε, ḟ, v;
- the update schedule (``update_rate``), rest detection and the zero-rate update;
- the iterated gravity update in the heading-tilt chart with the full reset, its
  χ² gate and disturbance inflation, the deferral while ε is large, tilt reopened;
- the magnetometer's heading update, its reference field and disturbance rules;
- heading's variance cap.

Where the compiled filter accumulates the considered rows' transition between
updates (docs/design.md#update-schedule, "the pending transition") this
reference propagates the whole covariance at every sample, as the design states
the model; the two differ by that section's stated approximation.

Not covered, and refused with a ``ValueError`` naming the option: other update
kinds, error sides, charts and reset policies, the filter without the low-pass
(``accel_lowpass_time = 0``), the measured motion level (``velocity_adapt_time``),
and known accelerations (``linear_accel``). Not covered at run time, refused with
a ``ValueError`` saying why: time not increasing or a gap beyond ``max_dt``, a
non-finite or clipped gyroscope, an accelerometer not finite or beyond 50 g, a
divergence (tilt reopened twice within ``divergence_window``) and a failed health check
(docs/design.md#health-rules: what follows is a re-initialisation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from mavest.estimator import StepFlags
from mavest.estimator.config import MAX_SPECIFIC_FORCE, EstimatorConfig

# Indices of the error state: δθ (heading-tilt chart: τx, τy, ψ), δb, then the
# considered states, each along the world's x and y (docs/design.md, "Two axes").
THETA = slice(0, 3)
BIAS = slice(3, 6)
EPS = 6  # ε, the low-passed specific force's error
RATE = 8  # ḟ, the low-pass's rate
VEL = 10  # v, the vehicle's velocity
N = 12

# Constants the design states (docs/design.md section in brackets).
MIN_ACCEL_FRACTION = 0.05  # below 0.05 g no direction [Gravity update]
MIN_DIRECTION_VAR = 1e-14  # the floor under the direction's variance [Gravity update]
LINEAR_LIMIT = 0.2  # ε's σ beyond 0.2 g: the direction waits [Low-pass, limits]
EPS_ROOM = 0.9  # a disturbance fills ε up to 90 % of that limit [Gravity update]
ZERO_RATE_GATE = 16.27  # χ²₃ at 99.9 % [Rest and the zero-rate update]
SCHEDULE_SLACK = 1e-9  # s, timestamps' last-bit jitter does not decide [Update schedule]
MAG_MIN_DT, MAG_MAX_DT = 1e-6, 0.1  # s, the clamp of Δt_m [Magnetometer update]
MAG_CHECK_TIME = 0.05  # s, the norm and dip low-pass [Magnetometer update]
MAG_MIN_HORIZONTAL = 0.05  # horizontal field below 5 % of the norm: no azimuth
MAX_ALIGNED_HEADING_VAR = 1.0  # rad², heading set from one field sample
MAX_HEADING_VAR = math.pi**2  # rad² [Health rules]
MAX_BIAS = 0.5  # rad/s [Health rules]
MAX_ATTITUDE_VAR = 4.0 * math.pi**2
MAX_CONSIDERED_VAR = 1e6

E3 = np.array([0.0, 0.0, 1.0])
# x, y rows of [e₃]×: E v = (−v_y, v_x), how a world rotation moves a horizontal vector
E_XY = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


# --------------------------------------------------------------------------
# Rotations (docs/design.md#conventions): quaternions (w, x, y, z), Hamilton
# --------------------------------------------------------------------------


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p ⊗ q: first q, then p."""
    pw, pv = p[0], p[1:]
    qw, qv = q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def quat_inverse(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_normalised(q: np.ndarray) -> np.ndarray:
    """Unit norm, w ≥ 0 (one of the double cover)."""
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0.0 else q


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """The quaternion of the rotation vector φ."""
    theta = float(np.linalg.norm(phi))
    # sin(θ/2)/θ = ½ sinc(θ/2), NumPy's sinc being sin(πx)/(πx)
    return np.concatenate([[math.cos(0.5 * theta)], 0.5 * np.sinc(0.5 * theta / math.pi) * phi])


def quat_log(q: np.ndarray) -> np.ndarray:
    """The rotation vector of a unit quaternion, the shorter one."""
    if q[0] < 0.0:
        q = -q
    s = float(np.linalg.norm(q[1:]))
    return np.zeros(3) if s == 0.0 else 2.0 * math.atan2(s, q[0]) / s * q[1:]


def quat_about_z(psi: float) -> np.ndarray:
    return np.array([math.cos(0.5 * psi), 0.0, 0.0, math.sin(0.5 * psi)])


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """R (body → world) of a unit quaternion."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)."""
    qx = np.array([math.cos(0.5 * roll), math.sin(0.5 * roll), 0.0, 0.0])
    qy = np.array([math.cos(0.5 * pitch), 0.0, math.sin(0.5 * pitch), 0.0])
    return quat_multiply(quat_about_z(yaw), quat_multiply(qy, qx))


def skew(v: np.ndarray) -> np.ndarray:
    """[v]×, with [v]× w = v × w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(φ) = I + (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×² (docs/design.md#conventions)."""
    theta = float(np.linalg.norm(phi))
    a = 0.5 * np.sinc(0.5 * theta / math.pi) ** 2  # (1 − cos θ)/θ², without cancellation
    if theta < 0.05:  # (θ − sin θ)/θ³ cancels: its series
        b = 1.0 / 6.0 - theta**2 / 120.0 + theta**4 / 5040.0
    else:
        b = (theta - math.sin(theta)) / theta**3
    K = skew(phi)
    return np.eye(3) + a * K + b * K @ K


def rotation_2d(psi: float) -> np.ndarray:
    return np.array([[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]])


def wrap(angle: float) -> float:
    """angle wrapped to [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# --------------------------------------------------------------------------
# The heading-tilt chart (docs/design.md#heading-tilt-chart), left error
# --------------------------------------------------------------------------


def chart(delta: np.ndarray) -> np.ndarray:
    """C(τx, τy, ψ) = R_z(ψ) Exp([τx, τy, 0]), as a quaternion."""
    return quat_multiply(quat_about_z(delta[2]), quat_exp(np.array([delta[0], delta[1], 0.0])))


def chart_inverse(e: np.ndarray) -> np.ndarray:
    """C⁻¹ of the error rotation e: e = q_z(ψ) ⊗ (c, a, b, 0) gives ψ/2 = atan2(e_z, e_w),
    and (a, b) is (e_x, e_y) turned back by ψ/2."""
    half = math.atan2(e[3], e[0])
    tilt = quat_multiply(quat_about_z(-2.0 * half), e)  # (c, a, b, 0)
    tau = quat_log(np.array([math.hypot(e[0], e[3]), tilt[1], tilt[2], 0.0]))
    psi = 2.0 * half  # in (−2π, 2π]: to (−π, π]
    if psi > math.pi:
        psi -= 2.0 * math.pi
    elif psi <= -math.pi:
        psi += 2.0 * math.pi
    return np.array([tau[0], tau[1], psi])


def retract(q: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """q ⊞ δθ = C(δθ) ⊗ q (left error)."""
    return quat_normalised(quat_multiply(chart(delta), q))


def local(q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """q ⊟ q_ref = C⁻¹(q ⊗ q_ref⁻¹)."""
    return chart_inverse(quat_multiply(q, quat_inverse(q_ref)))


def reset_jacobian(delta: np.ndarray) -> np.ndarray:
    """T_θ of the full reset in the heading-tilt chart (docs/design.md#heading-tilt-chart):
    [[R_z2(ψ̂) J_xy,xy, 0], [J_z,xy, 1]] with J = J_l(τ̂), τ̂ = (τx, τy, 0)."""
    J = left_jacobian(np.array([delta[0], delta[1], 0.0]))
    T = np.zeros((3, 3))
    T[:2, :2] = rotation_2d(delta[2]) @ J[:2, :2]
    T[2, :2] = J[2, :2]
    T[2, 2] = 1.0
    return T


def twist(dq: np.ndarray) -> np.ndarray:
    """W: the 2×2 turn about the vertical of the world-frame move dq (the twist of a
    swing–twist split, ψ = 2 atan2(z, w); docs/design.md, "The twist at a reset")."""
    w, z = dq[0], dq[3]
    if w * w + z * z == 0.0:  # a half turn about a horizontal axis: no twist
        return np.eye(2)
    return rotation_2d(2.0 * math.atan2(z, w))


# --------------------------------------------------------------------------
# The sphere (docs/design.md#gravity-update)
# --------------------------------------------------------------------------


def tangent_basis(z: np.ndarray) -> np.ndarray:
    """B_z (3×2): b₁ from the coordinate axis least aligned with z, b₂ = z × b₁."""
    axis = np.zeros(3)
    axis[int(np.argmin(np.abs(z)))] = 1.0
    b1 = np.cross(axis, z)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(z, b1)])


def sphere_log(h: np.ndarray, z: np.ndarray) -> np.ndarray:
    """ρ(h, z) = ϑ (h × z)/‖h × z‖, ϑ = atan2(‖h × z‖, h·z): the rotation turning h onto z."""
    w = np.cross(h, z)
    s = float(np.linalg.norm(w))
    return np.zeros(3) if s == 0.0 else math.atan2(s, h @ z) / s * w


def sphere_log_jacobian(h: np.ndarray, z: np.ndarray) -> np.ndarray:
    """∂ρ/∂h = −(ϑ/s)[z]× − ((cs − ϑ)/s³) w wᵀ[z]× − w zᵀ, its series near s = 0."""
    w = np.cross(h, z)
    s = float(np.linalg.norm(w))
    c = float(h @ z)
    theta = math.atan2(s, c)
    g = theta / s if s > 0.0 else 1.0
    m = -2.0 / 3.0 - s * s / 5.0 if (s < 1e-3 and c > 0.0) else (c * s - theta) / s**3
    Z = skew(z)
    return -g * Z - m * np.outer(w, w) @ Z - np.outer(w, z)


# --------------------------------------------------------------------------
# The filter
# --------------------------------------------------------------------------


def check_scope(config: EstimatorConfig) -> None:
    """Refuse, by name, every option the reference does not implement."""
    default = EstimatorConfig()
    for name in ("update", "error", "chart", "reset"):
        if getattr(config, name) != getattr(default, name):
            raise ValueError(
                f"the reference filter implements {name} = {getattr(default, name)!r} only "
                f"(got {getattr(config, name)!r})"
            )
    if not config.accel_lowpass_time > 0.0:
        raise ValueError("the reference filter needs the low-pass (accel_lowpass_time > 0)")
    if config.velocity_adapt_time != 0.0:
        raise ValueError("the reference filter has no measured motion level (velocity_adapt_time)")


def lowpass_transition(config: EstimatorConfig, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Φ (2×2) and Γ (2) of the second-order low-pass over Δt, input held
    (docs/design.md#low-pass-and-considered-states)."""
    omega = math.sqrt(2.0) / config.accel_lowpass_time
    zeta = config.accel_lowpass_damping
    sigma = zeta * omega
    omega_d = omega * math.sqrt(max(1.0 - zeta * zeta, 0.0))
    decay = math.exp(-sigma * dt)
    cosine = math.cos(omega_d * dt)
    sin_over_wd = dt * np.sinc(omega_d * dt / math.pi)  # sin(ω_d Δt)/ω_d
    Phi = decay * np.array(
        [
            [cosine + sigma * sin_over_wd, sin_over_wd],
            [-omega * omega * sin_over_wd, cosine - sigma * sin_over_wd],
        ]
    )
    return Phi, np.array([1.0 - Phi[0, 0], -Phi[1, 0]])


@dataclass
class _Report:
    """What one sample did, as the compiled filter reports it."""

    innovation: np.ndarray
    nis: float
    accel_used: bool = False
    flags: int = 0
    iterations: int = 0
    at_rest: bool = False
    heading_innovation: float = math.nan
    heading_nis: float = math.nan
    mag_used: bool = False


class ReferenceFilter:
    """The default filter, one sample at a time (docs/design.md#overview, "One sample runs")."""

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config if config is not None else EstimatorConfig()
        check_scope(self.config)
        c = self.config
        self.update_interval = 1.0 / c.update_rate if c.update_rate > 0.0 else 0.0
        # before the first usable sample: identity, the initial covariance
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.b = np.array(c.initial_bias, dtype=float)
        self.P = np.zeros((N, N))
        self.P[:6, :6] = np.diag(
            [c.initial_tilt_sigma**2] * 2
            + [c.initial_heading_sigma**2]
            + [c.initial_bias_sigma**2] * 3
        )
        self.P[VEL:, VEL:] = c.velocity_sigma**2 * np.eye(2)
        self.initialised = False
        self.t = -math.inf  # the last sample's time
        self.t_update = -math.inf  # the last update sample's
        self.t_accel = -math.inf  # the last undisturbed gravity update's
        self.t_reopened = -math.inf  # when tilt was last reopened
        # the low-pass: f̄ and ḟ (estimated world frame), the time averaged so far
        self.primed = False
        self.f_bar = np.zeros(3)
        self.f_rate = np.zeros(3)
        self.lowpass_time = 0.0
        # rest detection
        self.rest_gyro_lp = np.zeros(3)
        self.rest_accel_lp = np.zeros(3)
        self.rest_time = 0.0
        self.rest_gyro_sum = np.zeros(3)
        self.rest_samples = 0
        self.rest_sum_time = 0.0
        # the magnetometer: 0 heading free, 1 learning the reference field, 2 referenced
        self.mag_state = 0
        self.t_mag = -math.inf
        self.t_mag_used = -math.inf
        self.mag_ref_norm = self.mag_ref_dip = 0.0
        self.mag_learn_time = 0.0
        self.mag_candidate_norm = self.mag_candidate_dip = self.mag_candidate_time = 0.0
        self.mag_lp_norm = self.mag_lp_dip = 0.0
        self.mag_clear_time = 0.0
        self.soft_iron = c.soft_iron
        # COMPASS_OFS is in milligauss, the field in µT
        self.mag_offsets = 0.1 * np.asarray(c.compass_ofs, dtype=float)
        self.report = _Report(innovation=np.full(2, math.nan), nis=math.nan)

    # -- one sample ---------------------------------------------------------

    def update(
        self, t: float, gyro: ArrayLike, accel: ArrayLike, mag: ArrayLike | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Take the sample at time ``t`` (s); return the attitude q (w, x, y, z), the
        bias and the 6×6 covariance after it. ``mag`` None or NaN: no field sample.

        The order is the design's (docs/design.md#overview): prediction; at an update
        sample the zero-rate update if at rest, the accelerometer into the low-pass and
        the gravity update, the magnetometer; between them the accelerometer only
        joins the low-pass; then the health rules.
        """
        c = self.config
        gyro = np.asarray(gyro, dtype=float)
        accel = np.asarray(accel, dtype=float)
        mag = np.full(3, math.nan) if mag is None else np.asarray(mag, dtype=float)
        if not (math.isfinite(t) and np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            raise ValueError(f"t = {t}: a non-finite sample is outside the reference's scope")
        if np.any(np.abs(gyro) >= c.gyro_clip):
            raise ValueError(f"t = {t}: a clipped gyroscope is outside the reference's scope")
        if np.any(np.abs(accel) > MAX_SPECIFIC_FORCE):
            raise ValueError(
                f"t = {t}: an accelerometer beyond 50 g is outside the reference's scope"
            )
        report = self.report
        report.accel_used = report.mag_used = report.at_rest = False
        report.flags = report.iterations = 0
        if not self.initialised:
            report.innovation = np.full(2, math.nan)
            report.nis = report.heading_innovation = report.heading_nis = math.nan
            self.initialise(t, accel, mag)
            return self.estimate(gyro)
        dt = t - self.t
        if not 0.0 < dt <= c.max_dt:
            raise ValueError(f"t = {t}: Δt = {dt} s is outside the reference's scope")
        self.predict(gyro, dt)
        self.t = t
        primed_now = False
        if not self.primed:
            self.prime_lowpass(gyro, accel, dt)
            primed_now = True
        at_rest = self.detect_rest(gyro, accel, dt)
        elapsed = t - self.t_update
        due = not elapsed < self.update_interval - 0.5 * dt - SCHEDULE_SLACK
        if not due:
            report.flags |= StepFlags.BETWEEN_UPDATES
            if not primed_now:
                self.absorb(accel, dt)
            self.mag_update(t, mag, dt)
        else:
            self.t_update = t
            report.innovation = np.full(2, math.nan)
            report.nis = math.nan
            if at_rest:
                self.zero_rate_update()
            self.restart_rest_mean()
            if not primed_now:
                self.absorb(accel, dt)
            self.accel_update(t)
            self.mag_update(t, mag, dt)
        self.health_rules()
        return self.estimate(gyro)

    def estimate(self, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, b and the covariance reported: q carried forward over ``imu_delay`` by
        this sample's rate, ``gyro`` − b (docs/design.md#the-imus-delay); P's attitude
        and bias, and the accelerometer's alignment on the world's two horizontal axes,
        which no update removes (docs/design.md#the-accelerometers-alignment)."""
        cov = self.P[:6, :6].copy()
        cov[0, 0] += self.config.accel_alignment_sigma**2  # (left error: δθ in the world)
        cov[1, 1] += self.config.accel_alignment_sigma**2
        q = self.q.copy()
        # (not the placeholder before the filter starts: it is no attitude of the IMU's)
        if self.config.imu_delay and not self.report.flags & StepFlags.NOT_INITIALISED:
            turn = Rotation.from_rotvec((gyro - self.b) * self.config.imu_delay)
            lead = Rotation.from_quat(np.roll(q, -1)) * turn  # (scipy's x, y, z, w)
            led = np.roll(lead.as_quat(), 1)
            q = led if np.dot(led, q) >= 0.0 else -led  # (the filter's sign: q's side)
        return q, self.b.copy(), cov

    # -- initial alignment (docs/design.md#health-rules, "Input") -------------

    def accel_usable_for_alignment(self, accel: np.ndarray) -> bool:
        norm = float(np.linalg.norm(accel))
        g = self.config.gravity
        return norm > MIN_ACCEL_FRACTION * g and abs(norm - g) <= self.config.accel_norm_tolerance

    def initialise(self, t: float, accel: np.ndarray, mag: np.ndarray) -> None:
        """The first sample with an accelerometer near g sets roll and pitch, yaw 0 (or
        the magnetometer's), the initial covariance and the configured bias."""
        if not self.accel_usable_for_alignment(accel):
            self.report.flags = StepFlags.NOT_INITIALISED
            return
        c = self.config
        roll = math.atan2(-accel[1], -accel[2])
        pitch = math.atan2(accel[0], math.hypot(accel[1], accel[2]))
        self.q = quat_normalised(quat_from_euler_zyx(roll, pitch, 0.0))
        self.b = np.array(c.initial_bias, dtype=float)
        self.P = np.zeros((N, N))
        self.P[:3, :3] = np.diag([c.initial_tilt_sigma**2] * 2 + [c.initial_heading_sigma**2])
        self.P[BIAS, BIAS] = c.initial_bias_sigma**2 * np.eye(3)
        self.P[VEL:, VEL:] = c.velocity_sigma**2 * np.eye(2)  # nothing known of the velocity
        self.mag_state = 0
        self.primed = False  # the low-pass starts with the next sample
        self.initialised = True
        self.t = t
        self.t_accel = t
        self.report.flags = StepFlags.INITIALISED
        self.report.accel_used = True
        self.mag_update(t, mag, 0.0)

    # -- prediction (docs/design.md#prediction) -----------------------------

    def predict(self, gyro: np.ndarray, dt: float) -> None:
        """R̄ ← R̄ Exp(φ), P ← Φ P Φᵀ + Q_d, with ε moving with the attitude error
        (docs/design.md#prediction; #low-pass-and-considered-states, "prediction")."""
        c = self.config
        phi = (gyro - self.b) * dt
        R = rotation_matrix(self.q)  # R̄ before the step
        F = -R @ left_jacobian(phi) * dt  # Φ_θb of the left error
        G = c.gravity * E_XY  # g E W, W = I for the left error
        Phi = np.eye(N)
        Phi[THETA, BIAS] = F
        Phi[EPS : EPS + 2, BIAS] = G @ F  # ε ← ε + G Δθ, Δθ = Φ_θb δb
        # Van Loan's Q_d with R̄ held over the sample; σ_g² grows with |ω|² by σ_s²
        var_g = c.gyro_noise_density**2 + c.gyro_scale_noise_density**2 * (phi @ phi) / dt**2
        var_b = c.gyro_bias_random_walk**2
        Q6 = np.zeros((6, 6))
        Q6[THETA, THETA] = (var_g * dt + var_b * dt**3 / 3.0) * np.eye(3)
        Q6[THETA, BIAS] = -0.5 * var_b * dt**2 * R
        Q6[BIAS, THETA] = Q6[THETA, BIAS].T
        Q6[BIAS, BIAS] = var_b * dt * np.eye(3)
        L = np.zeros((N, 6))  # the noise moves δθ, δb and, through δθ, ε
        L[:6, :6] = np.eye(6)
        L[EPS : EPS + 2, THETA] = G
        self.P = Phi @ self.P @ Phi.T + L @ Q6 @ L.T
        self.q = quat_normalised(quat_multiply(self.q, quat_exp(phi)))

    # -- the low-pass (docs/design.md#low-pass-and-considered-states) ---------

    def prime_lowpass(self, gyro: np.ndarray, accel: np.ndarray, dt: float) -> None:
        """Start the low-passes (and the rest detector's) with this sample: f̄ = R̄ a,
        ḟ = 0; ε and ḟ start afresh, the velocity keeps its correlations."""
        self.rest_gyro_lp = gyro.copy()
        self.rest_accel_lp = accel.copy()
        self.rest_time = 0.0
        self.restart_rest_mean()
        self.primed = True
        for i in range(EPS, VEL):
            self.P[i, :] = 0.0
            self.P[:, i] = 0.0
        self.f_bar = np.zeros(3)
        self.f_rate = np.zeros(3)
        self.lowpass_time = 0.0
        self.absorb(accel, dt)  # mean mode with nothing averaged: f̄ = R̄ a
        for a in range(2):  # ḟ is known to be zero; a hair keeps P definite
            self.P[RATE + a, RATE + a] = 1e-12 * self.P[EPS + a, EPS + a]

    def absorb(self, accel: np.ndarray, dt: float) -> None:
        """The low-pass takes R̄ a; per axis its errors u = (ε, ḟ, v) follow,
        u ← A u + b_η η + b_ξ ξ. For the first τ, f̄ is the running mean of R̄ a
        (β = T/(T + Δt)), ḟ stays 0."""
        c = self.config
        u = rotation_matrix(self.q) @ accel
        if self.lowpass_time < c.accel_lowpass_time:
            beta = self.lowpass_time / (self.lowpass_time + dt)
            Phi, Gamma = np.array([[beta, 0.0], [0.0, 1.0]]), np.array([1.0 - beta, 0.0])
            self.lowpass_time += dt
        else:
            Phi, Gamma = lowpass_transition(c, dt)
        stage = Phi @ np.vstack([self.f_bar, self.f_rate]) + np.outer(Gamma, u)
        self.f_bar, self.f_rate = stage[0], stage[1]
        # the velocity, Gauss–Markov: v ← γ v + ξ, its acceleration a = ((γ − 1) v + ξ)/Δt
        gamma = math.exp(-dt / c.velocity_time)
        cv = (gamma - 1.0) / dt
        A = np.array(
            [
                [Phi[0, 0], Phi[0, 1], Gamma[0] * cv],
                [Phi[1, 0], Phi[1, 1], Gamma[1] * cv],
                [0.0, 0.0, gamma],
            ]
        )
        var_eta = c.accel_noise_density**2 / dt
        var_xi = c.velocity_sigma**2 * (1.0 - gamma * gamma)
        b_eta = np.array([Gamma[0], Gamma[1], 0.0])
        b_xi = np.array([Gamma[0] / dt, Gamma[1] / dt, 1.0])
        noise = np.outer(b_eta, b_eta) * var_eta + np.outer(b_xi, b_xi) * var_xi
        T = np.eye(N)
        Qn = np.zeros((N, N))
        for axis in range(2):
            rows = [EPS + axis, RATE + axis, VEL + axis]
            T[np.ix_(rows, rows)] = A
            Qn[np.ix_(rows, rows)] = noise
        self.P = T @ self.P @ T.T + Qn

    # -- the reset (docs/design.md#recursion-and-reset) -----------------------

    def move_nominal(self, dx: np.ndarray) -> np.ndarray:
        """x ← x ⊞ δx; the low-pass's world vectors turn with the estimated world
        frame. Returns the world-frame move q⁺ ⊗ q⁻¹."""
        q_before = self.q
        self.q = retract(self.q, dx[THETA])
        self.b = self.b + dx[BIAS]
        move = quat_multiply(self.q, quat_inverse(q_before))
        R_move = rotation_matrix(move)
        self.f_bar = R_move @ self.f_bar
        self.f_rate = R_move @ self.f_rate
        return move

    @staticmethod
    def reset_transform(dx: np.ndarray, move: np.ndarray) -> np.ndarray:
        """T = blockdiag(T_θ(δ̂θ), I, W, W, W): the reset's Jacobian, the considered
        states turned by the move's twist W."""
        T = np.eye(N)
        T[THETA, THETA] = reset_jacobian(dx[THETA])
        W = twist(move)
        for block in (EPS, RATE, VEL):
            T[block : block + 2, block : block + 2] = W
        return T

    def apply_correction(self, dx: np.ndarray) -> None:
        """The measurement reset: the error mean into the nominal, P ← T P Tᵀ."""
        move = self.move_nominal(dx)
        T = self.reset_transform(dx, move)
        self.P = T @ self.P @ T.T

    # -- rest (docs/design.md#rest-and-the-zero-rate-update) ----------------

    def restart_rest_mean(self) -> None:
        self.rest_gyro_sum = np.zeros(3)
        self.rest_samples = 0
        self.rest_sum_time = 0.0

    def detect_rest(self, gyro: np.ndarray, accel: np.ndarray, dt: float) -> bool:
        """VQF's criteria: gyro and accelerometer within their thresholds of their
        low-passes (rest_filter_time) for rest_min_time."""
        c = self.config
        if not c.rest_detection:
            self.rest_time = 0.0
            self.restart_rest_mean()
            return False
        alpha = 1.0 - math.exp(-dt / c.rest_filter_time)
        self.rest_gyro_lp = self.rest_gyro_lp + alpha * (gyro - self.rest_gyro_lp)
        self.rest_accel_lp = self.rest_accel_lp + alpha * (accel - self.rest_accel_lp)
        still = (
            np.sum((gyro - self.rest_gyro_lp) ** 2) < c.rest_gyro_threshold**2
            and np.sum((accel - self.rest_accel_lp) ** 2) < c.rest_accel_threshold**2
        )
        if still:
            self.rest_time += dt
            self.rest_gyro_sum = self.rest_gyro_sum + gyro
            self.rest_samples += 1
            self.rest_sum_time += dt
        else:
            self.rest_time = 0.0
            self.restart_rest_mean()
        return self.rest_time >= c.rest_min_time

    def zero_rate_update(self) -> None:
        """At rest the gyro measures its bias: y = ω̄_m − b̄, H = [0 I 0],
        V = σ_g²/T + σ_rest², gated at χ²₃ = 16.27, Schmidt gain, Joseph form, reset."""
        c = self.config
        var = c.gyro_noise_density**2 / self.rest_sum_time + c.rest_rate_sigma**2
        H = np.zeros((3, N))
        H[:, BIAS] = np.eye(3)
        S = H @ self.P @ H.T + var * np.eye(3)
        y = self.rest_gyro_sum / self.rest_samples - self.b
        if not np.linalg.det(S) > 0.0:
            return
        S_inv = np.linalg.inv(S)
        if not y @ S_inv @ y <= ZERO_RATE_GATE:
            return
        K = self.P @ H.T @ S_inv
        K[EPS:] = 0.0  # considered states get no gain
        self.P = joseph(self.P, K, H, var * np.eye(3))
        self.apply_correction(K @ y)
        self.report.at_rest = True

    # -- gravity (docs/design.md#gravity-update, #iterated-update) ----------

    def gravity_residual(self, q: np.ndarray, z: np.ndarray, Bz: np.ndarray) -> np.ndarray:
        """r = B_zᵀ ρ(R̄ᵀe₃, z) at the attitude q."""
        h = rotation_matrix(q).T @ E3
        return Bz.T @ sphere_log(h, z)

    def gravity_jacobian(self, q: np.ndarray, z: np.ndarray, Bz: np.ndarray) -> np.ndarray:
        """H (2×12): H_θ = B_zᵀ (∂ρ/∂h) R̄ᵀ[e₃]×, H_ε = (1/g) B_zᵀ R̄ᵀ[e₃]× (its x, y
        columns); zero on the bias, ḟ and v."""
        R = rotation_matrix(q)
        h = R.T @ E3
        D = R.T @ skew(E3)  # ∂h/∂δθ for the left error; its third column is zero
        H = np.zeros((2, N))
        H[:, THETA] = Bz.T @ sphere_log_jacobian(h, z) @ D
        H[:, EPS : EPS + 2] = Bz.T @ D[:, :2] / self.config.gravity
        return H

    def gravity_leaves_heading(self) -> bool:
        """With a magnetometer referencing heading, the gravity gain keeps no heading."""
        return self.t_mag_used > -math.inf

    def iterated_gravity_update(
        self, z: np.ndarray, Bz: np.ndarray, var: float, gate: float
    ) -> tuple[bool, np.ndarray]:
        """Gauss–Newton with the prior-correction term transported to the iterate:
        δ_i = m_i − K_i (r_i + H_i m_i), m_i = −T_i d_i, P_i = T_i P T_iᵀ; the Joseph
        form at the last iterate, moved onto x_{i+1} by T(δ_i). Returns whether the gate
        let it through, and the first iteration's S."""
        c = self.config
        q_prior, b_prior = self.q, self.b
        V = var * np.eye(2)
        S0 = np.zeros((2, 2))
        for it in range(c.max_iterations):
            if it == 0:
                m = np.zeros(N)
                Pi = self.P
            else:
                d = np.zeros(N)
                d[THETA] = local(self.q, q_prior)
                d[BIAS] = self.b - b_prior
                Ti = self.reset_transform(d, quat_multiply(self.q, quat_inverse(q_prior)))
                Pi = Ti @ self.P @ Ti.T
                m = -Ti @ d  # (d's considered part is zero: ε stays at its mean)
            r = self.gravity_residual(self.q, z, Bz)
            H = self.gravity_jacobian(self.q, z, Bz)
            C = Pi @ H.T
            S = H @ C + V
            S = 0.5 * (S + S.T)
            S_inv = np.linalg.inv(S)
            K = C @ S_inv
            K[EPS:] = 0.0  # Schmidt: the considered states' means are never estimated
            if self.gravity_leaves_heading():
                K[THETA] -= np.outer(E3, E3 @ K[THETA])  # heading is considered
            if it == 0:
                S0 = S
                nis = float(r @ S_inv @ r)
                self.report.innovation = r
                self.report.nis = nis
                if gate > 0.0 and not nis <= gate:
                    return False, S0
            dx = m - K @ (r + H @ m)
            move = self.move_nominal(dx)
            self.report.iterations = it + 1
            attitude_step2 = dx[THETA] @ dx[THETA]
            step2 = attitude_step2 + dx[BIAS] @ dx[BIAS]
            tol = c.iteration_tolerance
            if step2 <= tol * tol or attitude_step2 <= 0.1 * tol:
                break
        P = joseph_gain(Pi, K, C, S)
        T = self.reset_transform(dx, move)
        self.P = T @ P @ T.T
        return True, S0

    def accel_update(self, t: float) -> None:
        """The low-passed direction z = −R̄ᵀ f̄/‖f̄‖ against gravity, with the robustness
        rules: invalid, deferred while ε is large, norm rejected, tilt reopened, the
        χ² gate's inflation, the low-pass's restart after a large correction."""
        c = self.config
        report = self.report
        g = c.gravity
        f = rotation_matrix(self.q).T @ self.f_bar
        norm = float(np.linalg.norm(f))
        if not norm > MIN_ACCEL_FRACTION * g:
            report.flags |= StepFlags.ACCEL_INVALID
            return
        z = -f / norm
        Bz = tangent_basis(z)
        eps_var = max(self.P[EPS, EPS], self.P[EPS + 1, EPS + 1])
        limit_var = (LINEAR_LIMIT * g) ** 2
        if eps_var > limit_var:
            report.flags |= StepFlags.ACCEL_DEFERRED
            return
        deviation = norm - g
        if abs(deviation) > c.accel_norm_tolerance:
            report.flags |= StepFlags.ACCEL_REJECTED_NORM
            report.innovation = self.gravity_residual(self.q, z, Bz)
            return
        # with the low-pass the white noise lives in ε: only the optional inflation
        var = max((c.accel_norm_inflation * deviation) ** 2 / g**2, MIN_DIRECTION_VAR)
        gate = c.accel_gate
        if c.accel_max_disturbance_time > 0.0 and t - self.t_accel > c.accel_max_disturbance_time:
            if c.divergence_window > 0.0 and t - self.t_reopened < c.divergence_window:
                raise ValueError(f"t = {t}: a divergence is outside the reference's scope")
            self.set_attitude_variance_world(tilt=c.initial_tilt_sigma**2)
            self.t_reopened = t
            gate = 0.0
            report.flags |= StepFlags.TILT_REOPENED
        q_before = self.q
        used, S0 = self.iterated_gravity_update(z, Bz, var, gate)
        if not used:
            # beyond the gate: the variance grows by what the innovation shows, into ε
            # up to 90 % of the linear limit, the rest with this sample
            r = report.innovation
            extra = max(0.5 * (r @ r) - 0.5 * np.trace(S0), 0.0)
            room = EPS_ROOM * limit_var - eps_var
            into_eps = min(extra * g * g, max(room, 0.0))
            self.P[EPS, EPS] += into_eps
            self.P[EPS + 1, EPS + 1] += into_eps
            var += extra - into_eps / (g * g)
            nis = report.nis
            self.iterated_gravity_update(z, Bz, var, 0.0)
            report.nis = nis  # what the innovation was, not the matched 2
            report.flags |= StepFlags.ACCEL_DISTURBED
        else:
            self.t_accel = t
        report.accel_used = True
        if c.accel_lowpass_restart_angle > 0.0:
            move = quat_multiply(self.q, quat_inverse(q_before))
            tilt = 2.0 * math.acos(math.sqrt(min(move[0] ** 2 + move[3] ** 2, 1.0)))
            if tilt > c.accel_lowpass_restart_angle:
                self.primed = False  # the low-pass starts again with the next sample
                report.flags |= StepFlags.LOWPASS_RESTARTED

    def set_attitude_variance_world(
        self, tilt: float | None = None, heading: float | None = None
    ) -> None:
        """Set tilt's and/or heading's variance (world axes: the left error's own);
        what is set loses its correlations."""
        for axes, var in (((0, 1), tilt), ((2,), heading)):
            if var is None:
                continue
            for i in axes:
                self.P[i, :] = 0.0
                self.P[:, i] = 0.0
                self.P[i, i] = var

    # -- the magnetometer (docs/design.md#magnetometer-update) --------------

    def mag_update(self, t: float, mag: np.ndarray, dt: float) -> None:
        """Heading only: the first field sets heading, later ones are scalar updates
        gated by the reference field and the χ² gate, the gain on heading and the
        vertical bias alone, the covariance the Joseph form with the full H."""
        c = self.config
        report = self.report
        if not np.all(np.isfinite(mag)):
            return  # no field in this sample
        elapsed = t - self.t_mag
        if self.mag_state != 0 and elapsed < self.update_interval - 0.5 * dt - SCHEDULE_SLACK:
            report.flags |= StepFlags.MAG_BETWEEN_UPDATES
            return
        report.heading_innovation = report.heading_nis = math.nan
        m = self.soft_iron @ (mag + self.mag_offsets)
        u = rotation_matrix(self.q) @ m
        horizontal = math.hypot(u[0], u[1])
        norm = math.sqrt(horizontal**2 + u[2] ** 2)
        dip = math.atan2(u[2], horizontal)
        if not (norm > 0.0 and horizontal > MAG_MIN_HORIZONTAL * norm):
            report.flags |= StepFlags.MAG_INVALID
            return
        azimuth = math.atan2(u[1], u[0])
        dt_mag = elapsed if self.t_mag > -math.inf else dt
        dt_mag = max(min(dt_mag, MAG_MAX_DT), MAG_MIN_DT)
        self.t_mag = t
        var_mag = c.mag_heading_noise_density**2 / dt_mag
        if self.mag_state == 0:  # the first field sets heading
            dx = np.zeros(N)
            dx[2] = wrap(c.compass_dec - azimuth)
            self.apply_correction(dx)
            self.set_attitude_variance_world(heading=min(var_mag, MAX_ALIGNED_HEADING_VAR))
            self.start_reference(norm, dip, dt_mag)
            self.t_mag_used = t
            report.heading_innovation = wrap(azimuth - c.compass_dec)
            report.mag_used = True
            report.flags |= StepFlags.HEADING_ALIGNED
            return
        disturbed = self.track_reference(norm, dip, dt_mag)
        self.mag_clear_time = 0.0 if disturbed else self.mag_clear_time + dt_mag
        disturbed = self.mag_clear_time < c.mag_recovery_time
        gate = c.mag_gate
        if c.mag_max_rejection_time > 0.0 and t - self.t_mag_used > c.mag_max_rejection_time:
            report.flags |= StepFlags.HEADING_REOPENED
            if self.P[2, 2] < c.mag_reopened_heading_sigma**2:
                self.set_attitude_variance_world(heading=c.mag_reopened_heading_sigma**2)
            self.mag_candidate_time = 0.0
            self.mag_clear_time = c.mag_recovery_time
            disturbed = False
            gate = 0.0
        nu = wrap(azimuth - c.compass_dec)
        # H at the reference dip, in world axes (the left error's): H_τ the tilt leak,
        # H_ψ = (0, 0, −1) heading's own term
        d = c.compass_dec
        slope = math.tan(self.mag_ref_dip)
        H_psi = np.zeros(N)
        H_psi[2] = -1.0
        H_tau = np.zeros(N)
        H_tau[:2] = slope * math.cos(d), slope * math.sin(d)
        # the noise turns the field the leak goes along: mean leak e^(−σ²/2) H_τ, the rest
        # of its variance (1 − e^(−σ²)) white
        leak = float(H_tau @ self.P @ H_tau)
        shrink = math.exp(-0.5 * var_mag)
        var_mag += (1.0 - shrink**2) * leak
        leak *= shrink**2
        H_full = H_psi + shrink * H_tau
        # the gain's innovation variance: heading's, the noise, the leak as slow noise
        S = float(H_psi @ self.P @ H_psi) + var_mag + leak * max(1.0, c.mag_tilt_leak_time / dt_mag)
        nis = nu * nu / S
        report.heading_innovation = nu
        report.heading_nis = nis
        if disturbed:
            report.flags |= StepFlags.MAG_DISTURBED
            return
        if gate > 0.0 and not nis <= gate:
            report.flags |= StepFlags.MAG_REJECTED
            return
        # the gain moves heading (world vertical) and the bias about the body's vertical
        C = self.P @ H_psi
        v_body = rotation_matrix(self.q).T @ E3
        K = np.zeros(N)
        K[THETA] = E3 * (E3 @ C[THETA]) / S
        K[BIAS] = v_body * (v_body @ C[BIAS]) / S
        self.P = joseph(self.P, K[:, None], H_full[None, :], np.array([[var_mag]]))
        self.apply_correction(K * nu)
        report.mag_used = True
        self.t_mag_used = t

    def start_reference(self, norm: float, dip: float, learned: float) -> None:
        """Heading has just been set: learn the reference field afresh."""
        self.mag_state = 1
        self.mag_ref_norm, self.mag_ref_dip = norm, dip
        self.mag_learn_time = learned
        self.mag_candidate_time = 0.0
        self.mag_lp_norm, self.mag_lp_dip = norm, dip
        self.mag_clear_time = self.config.mag_recovery_time

    def track_reference(self, norm: float, dip: float, dt: float) -> bool:
        """Learn (running mean over mag_reference_time) or follow (mag_reference_adapt_time)
        the reference norm and dip; a steady disturbed field becomes the reference after
        mag_new_reference_time. True if the field, low-passed over 0.05 s, is disturbed."""
        c = self.config
        alpha = min(dt / MAG_CHECK_TIME, 1.0)
        self.mag_lp_norm += alpha * (norm - self.mag_lp_norm)
        self.mag_lp_dip += alpha * (dip - self.mag_lp_dip)
        if self.mag_state == 1:
            weight = dt / (self.mag_learn_time + dt)
            self.mag_ref_norm += weight * (norm - self.mag_ref_norm)
            self.mag_ref_dip += weight * (dip - self.mag_ref_dip)
            self.mag_learn_time += dt
            if self.mag_learn_time >= c.mag_reference_time:
                self.mag_state = 2
            return False
        norm, dip = self.mag_lp_norm, self.mag_lp_dip
        tol = c.mag_norm_tolerance
        disturbed = (
            abs(norm - self.mag_ref_norm) > tol * self.mag_ref_norm
            or abs(dip - self.mag_ref_dip) > c.mag_dip_tolerance
        )
        if not disturbed:
            self.mag_candidate_time = 0.0
            if c.mag_reference_adapt_time > 0.0:
                alpha = min(dt / c.mag_reference_adapt_time, 1.0)
                self.mag_ref_norm += alpha * (norm - self.mag_ref_norm)
                self.mag_ref_dip += alpha * (dip - self.mag_ref_dip)
            return False
        steady = (
            self.mag_candidate_time > 0.0
            and abs(norm - self.mag_candidate_norm) <= tol * self.mag_candidate_norm
            and abs(dip - self.mag_candidate_dip) <= c.mag_dip_tolerance
        )
        if steady:
            weight = dt / (self.mag_candidate_time + dt)
            self.mag_candidate_norm += weight * (norm - self.mag_candidate_norm)
            self.mag_candidate_dip += weight * (dip - self.mag_candidate_dip)
            self.mag_candidate_time += dt
        else:
            self.mag_candidate_norm, self.mag_candidate_dip = norm, dip
            self.mag_candidate_time = dt
        if self.mag_candidate_time >= c.mag_new_reference_time:
            self.mag_ref_norm, self.mag_ref_dip = self.mag_candidate_norm, self.mag_candidate_dip
            self.mag_candidate_time = 0.0
            self.report.flags |= StepFlags.MAG_REFERENCE_CHANGED
            return False
        return True

    # -- health (docs/design.md#health-rules, "State") ----------------------

    def health_rules(self) -> None:
        """Heading's variance capped at π² (its row and column scaled); P symmetric. A
        state that fails the checks would be re-initialised: outside the scope."""
        var = self.P[2, 2]
        if var > MAX_HEADING_VAR:
            f = math.sqrt(MAX_HEADING_VAR / var)
            self.P[2, :] *= f
            self.P[:, 2] *= f
        self.P = 0.5 * (self.P + self.P.T)
        variances = np.diag(self.P)
        bounds = np.array([MAX_ATTITUDE_VAR] * 3 + [MAX_BIAS**2] * 3 + [MAX_CONSIDERED_VAR] * 6)
        plausible = (
            abs(self.q @ self.q - 1.0) < 1e-6
            and np.all(np.abs(self.b) <= MAX_BIAS)
            and np.all((variances >= 0.0) & (variances <= bounds))
            and np.all(np.linalg.eigvalsh(self.P[:6, :6]) > 0.0)
        )
        if not plausible:
            raise ValueError(
                f"t = {self.t}: a failed health check is outside the reference's scope"
            )


def joseph(P: np.ndarray, K: np.ndarray, H: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(I − K H) P (I − K H)ᵀ + K V Kᵀ: the covariance for any gain
    (docs/design.md#gravity-update)."""
    I_KH = np.eye(P.shape[0]) - K @ H
    return I_KH @ P @ I_KH.T + K @ V @ K.T


def joseph_gain(P: np.ndarray, K: np.ndarray, C: np.ndarray, S: np.ndarray) -> np.ndarray:
    """The Joseph form written with C = P Hᵀ and S = H P Hᵀ + V: P − K Cᵀ − C Kᵀ + K S Kᵀ."""
    return P - K @ C.T - C @ K.T + K @ S @ K.T


@dataclass(frozen=True)
class ReferenceSeries:
    """The reference's estimates, fields named as :class:`mavest.EstimateSeries`'s."""

    t: np.ndarray  # (N,)
    q: np.ndarray  # (N, 4) w, x, y, z
    bias: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 6, 6)
    innovation: np.ndarray  # (N, 2)
    nis: np.ndarray  # (N,)
    accel_used: np.ndarray  # (N,) bool
    flags: np.ndarray  # (N,) StepFlags bits of what the reference covers
    iterations: np.ndarray  # (N,)
    at_rest: np.ndarray  # (N,) bool
    heading_innovation: np.ndarray  # (N,)
    heading_nis: np.ndarray  # (N,)
    mag_used: np.ndarray  # (N,) bool


def reference_estimate(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
) -> ReferenceSeries:
    """Run :class:`ReferenceFilter` over a recording, as :func:`mavest.estimate` does."""
    t = np.asarray(t, dtype=float)
    gyro = np.asarray(gyro, dtype=float)
    accel = np.asarray(accel, dtype=float)
    n = t.shape[0]
    mags = np.full((n, 3), math.nan) if mag is None else np.asarray(mag, dtype=float)
    filt = ReferenceFilter(config)
    out = {
        "q": np.empty((n, 4)),
        "bias": np.empty((n, 3)),
        "cov": np.empty((n, 6, 6)),
        "innovation": np.empty((n, 2)),
        "nis": np.empty(n),
        "accel_used": np.empty(n, dtype=bool),
        "flags": np.empty(n, dtype=np.int64),
        "iterations": np.empty(n, dtype=np.int64),
        "at_rest": np.empty(n, dtype=bool),
        "heading_innovation": np.empty(n),
        "heading_nis": np.empty(n),
        "mag_used": np.empty(n, dtype=bool),
    }
    for i in range(n):
        out["q"][i], out["bias"][i], out["cov"][i] = filt.update(t[i], gyro[i], accel[i], mags[i])
        report = filt.report
        out["innovation"][i] = report.innovation
        for name in ("nis", "accel_used", "flags", "iterations", "at_rest"):
            out[name][i] = getattr(report, name)
        for name in ("heading_innovation", "heading_nis", "mag_used"):
            out[name][i] = getattr(report, name)
    return ReferenceSeries(t=t, **out)
