"""A kinematic IMU simulator: smooth flight-like attitude, true bias, noisy samples.

The truth follows the filter's own process model exactly — the attitude is
integrated with the rate held constant over each sample interval, the bias is
a random walk, the noise white with the given densities — so that with
``ImuNoise.matching(config)`` a consistent filter must show NEES ~ χ². On top,
linear-acceleration bursts break the gravity model on purpose, as flight does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from mavest import so3
from mavest._jit import kernel
from mavest.estimator.config import STANDARD_GRAVITY, EstimatorConfig, require_number

# The Earth's field near Zürich (47.4° N, 8.5° E; WMM 2025, rounded), NED, µT:
# 48 µT, dip 63°, declination 1.9° east.
EARTH_FIELD_NED = np.array([21.5, 0.7, 43.0])


def earth_field(declination: float, field: np.ndarray = EARTH_FIELD_NED) -> np.ndarray:
    """``field`` turned about the vertical so that its azimuth is ``declination`` (rad)."""
    horizontal = math.hypot(field[0], field[1])
    return np.array(
        [horizontal * math.cos(declination), horizontal * math.sin(declination), field[2]]
    )


@dataclass(frozen=True)
class ImuNoise:
    """Sensor errors, as densities (per-sample σ = density/√Δt)."""

    gyro_noise_density: float = 0.005  # rad/s/√Hz
    gyro_bias_random_walk: float = 2e-5  # rad/s²/√Hz
    gyro_bias_sigma: float = math.radians(0.5)  # rad/s, initial bias spread per axis
    accel_noise_density: float = 0.02  # m/s²/√Hz
    mag_heading_noise_density: float = 0.08  # rad·√s, the field's azimuth
    # white gyro noise of density this × |ω| on top (scale and alignment errors)
    gyro_scale_noise_density: float = 0.0  # √s
    # the accelerometer turned off the body by a constant rotation about the body's x and
    # y axes, each drawn with this σ: the gravity direction it measures is that far off
    accel_alignment_sigma: float = 0.0  # rad
    # every sample measures the motion this long before its time stamp (the sensor's
    # filters' group delay): the truth at a time stamp is the motion this much later
    imu_delay: float = 0.0  # s

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:  # (the configuration's rule: ConfigError)
            require_number(f"ImuNoise.{name}", getattr(self, name), zero=True)

    @classmethod
    def matching(cls, config: EstimatorConfig) -> ImuNoise:
        """The noise a filter with this configuration assumes."""
        return cls(
            config.gyro_noise_density,
            config.gyro_bias_random_walk,
            config.initial_bias_sigma,
            config.accel_noise_density,
            config.mag_heading_noise_density,
            config.gyro_scale_noise_density,
            config.accel_alignment_sigma,
            config.imu_delay,
        )


@dataclass(frozen=True)
class Motion:
    """A flight-like motion: oscillating roll and pitch, turning yaw, moving about.

    Each of roll and pitch is a sum of three sinusoids with random phases and
    periods between ``min_period`` and ``max_period``; yaw turns at
    ``yaw_rate`` with a sinusoidal modulation. The velocity is Gauss–Markov in
    each world axis (stationary σ ``velocity_sigma``, correlation time
    ``velocity_time``), so the linear acceleration is the derivative of a
    bounded velocity, held over each sample. Bursts add linear acceleration
    (world frame, random direction) of ``burst_magnitude`` m/s² lasting
    ``burst_duration`` s, on average every ``burst_interval`` s.
    """

    roll_amplitude: float = math.radians(30.0)
    pitch_amplitude: float = math.radians(20.0)
    yaw_rate: float = math.radians(10.0)
    min_period: float = 4.0
    max_period: float = 20.0
    velocity_sigma: float = 0.0  # m/s
    velocity_time: float = 1.0  # s
    # (start time s, σ m/s) pairs: from each start on, the velocity's level is that σ
    # (it moves there with the correlation time); empty: velocity_sigma throughout
    velocity_levels: tuple[tuple[float, float], ...] = ()
    burst_magnitude: float = 0.0
    burst_duration: float = 1.0
    burst_interval: float = 10.0

    @classmethod
    def static(cls) -> Motion:
        return cls(roll_amplitude=0.0, pitch_amplitude=0.0, yaw_rate=0.0)


@dataclass(frozen=True)
class SimulatedImu:
    """Samples and truth. Frames as everywhere in mavest: FRD body, NED world."""

    t: np.ndarray  # (N,) s
    gyro: np.ndarray  # (N, 3) rad/s, held over (t[i-1], t[i]]
    accel: np.ndarray  # (N, 3) m/s², specific force
    q_true: np.ndarray  # (N, 4) body → NED at t[i]
    bias_true: np.ndarray  # (N, 3) rad/s
    linear_accel: np.ndarray  # (N, 3) m/s², world frame
    velocity: np.ndarray  # (N, 3) m/s, world frame (the bursts' aside)
    mag: np.ndarray  # (N, 3) µT, the field ``field_ned`` seen in the body, noisy azimuth
    field_ned: np.ndarray  # (3,) µT
    noise: ImuNoise = field(repr=False)

    @property
    def rate(self) -> float:
        return float((len(self.t) - 1) / (self.t[-1] - self.t[0]))


def _sinusoid_sum(
    rng: np.random.Generator, amplitude: float, motion: Motion
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Amplitudes, angular frequencies and phases of three sinusoids summing to ~amplitude."""
    periods = rng.uniform(motion.min_period, motion.max_period, 3)
    weights = rng.uniform(0.5, 1.0, 3)
    return amplitude * weights / weights.sum(), 2.0 * np.pi / periods, rng.uniform(0, 2 * np.pi, 3)


def _euler_and_rates(
    t: np.ndarray, rng: np.random.Generator, motion: Motion, yaw0: float
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) ZYX angles and (N, 3) their time derivatives at times t."""
    angles = np.zeros((len(t), 3))
    rates = np.zeros((len(t), 3))
    for axis, amplitude in ((0, motion.roll_amplitude), (1, motion.pitch_amplitude)):
        a, w, p = _sinusoid_sum(rng, amplitude, motion)
        arg = np.outer(t, w) + p
        angles[:, axis] = (a * np.sin(arg)).sum(axis=1)
        rates[:, axis] = (a * w * np.cos(arg)).sum(axis=1)
    w_yaw = 2.0 * np.pi / rng.uniform(motion.min_period, motion.max_period)
    p_yaw = rng.uniform(0, 2 * np.pi)
    angles[:, 2] = yaw0 + motion.yaw_rate * (t + np.sin(w_yaw * t + p_yaw) / w_yaw)
    rates[:, 2] = motion.yaw_rate * (1.0 + np.cos(w_yaw * t + p_yaw))
    return angles, rates


def _body_rates(angles: np.ndarray, rates: np.ndarray) -> np.ndarray:
    """Body angular velocity of ZYX Euler angles and their derivatives."""
    roll, pitch = angles[:, 0], angles[:, 1]
    droll, dpitch, dyaw = rates[:, 0], rates[:, 1], rates[:, 2]
    return np.column_stack(
        [
            droll - dyaw * np.sin(pitch),
            dpitch * np.cos(roll) + dyaw * np.cos(pitch) * np.sin(roll),
            -dpitch * np.sin(roll) + dyaw * np.cos(pitch) * np.cos(roll),
        ]
    )


def _velocity(t: np.ndarray, rng: np.random.Generator, motion: Motion) -> np.ndarray:
    """A Gauss–Markov velocity per world axis (what the filter assumes); zero if σ = 0.
    With ``velocity_levels`` its σ changes over the flight."""
    n = len(t)
    sigma = np.full(n, motion.velocity_sigma)
    for start, level in motion.velocity_levels:
        sigma[t >= start] = level
    if not np.any(sigma > 0.0) or n < 2:
        return np.zeros((n, 3))
    dt = np.diff(t)
    gamma = np.exp(-dt / motion.velocity_time)
    xi = rng.normal(0.0, 1.0, (n - 1, 3)) * (sigma[1:] * np.sqrt(1 - gamma**2))[:, None]
    v = np.empty((n, 3))
    v[0] = rng.normal(0.0, sigma[0], 3)
    for i in range(1, n):
        v[i] = gamma[i - 1] * v[i - 1] + xi[i - 1]
    return v


def _bursts(t: np.ndarray, rng: np.random.Generator, motion: Motion) -> np.ndarray:
    """World-frame linear acceleration: smooth (raised-cosine) pulses in random directions."""
    out = np.zeros((len(t), 3))
    if motion.burst_magnitude <= 0.0:
        return out
    start = t[0] + rng.exponential(motion.burst_interval)
    while start < t[-1]:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        inside = (t >= start) & (t < start + motion.burst_duration)
        phase = (t[inside] - start) / motion.burst_duration
        out[inside] += (motion.burst_magnitude * 0.5 * (1.0 - np.cos(2.0 * np.pi * phase)))[
            :, None
        ] * direction
        start += motion.burst_duration + rng.exponential(motion.burst_interval)
    return out


@kernel
def _integrate(q0: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """q[i] = q[i−1] ⊗ Exp(ω_i Δt), q[0] = q0."""
    q = np.empty((omega.shape[0], 4))
    q[0] = q0
    step = np.empty(4)
    for i in range(1, omega.shape[0]):
        so3.quat_exp_into(omega[i] * dt, step)
        so3.quat_multiply_into(q[i - 1], step, q[i])
        so3.quat_normalize_into(q[i])
    return q


@kernel
def rotate_to_body(q: np.ndarray, v_world: np.ndarray) -> np.ndarray:
    """R(q[i])ᵀ v_world[i] for each i."""
    out = np.empty_like(v_world)
    R = np.empty((3, 3))
    for i in range(q.shape[0]):
        so3.matrix_from_quat_into(q[i], R)
        out[i] = R.T @ v_world[i]
    return out


def simulate(
    duration: float = 60.0,
    rate: float = 100.0,
    noise: ImuNoise | None = None,
    motion: Motion | None = None,
    seed: int = 0,
    gravity: float = STANDARD_GRAVITY,
    field_ned: np.ndarray = EARTH_FIELD_NED,
) -> SimulatedImu:
    """Simulate an IMU at ``rate`` Hz for ``duration`` s.

    The truth at t[i] is q[i] = q[i−1] ⊗ Exp(ω_i Δt) with ω_i the body rate at
    the middle of the interval, so the filter's "rate held over the interval"
    model is exact; gyro_i = ω_i + b_i + white noise. With ``noise.imu_delay`` τ the
    samples are those of the motion τ before their time stamps: the attitude returned
    at t[i] is q[i] ⊗ Exp(ω τ), ω the body rate at t[i] + τ/2 (the same midpoint rule);
    the linear acceleration and velocity returned stay those the samples measured.
    """
    noise = noise if noise is not None else ImuNoise()
    motion = motion if motion is not None else Motion()
    rng = np.random.default_rng(seed)
    n = round(duration * rate) + 1
    dt = 1.0 / rate
    t = np.arange(n) * dt
    yaw0 = rng.uniform(-np.pi, np.pi)

    def motion_at(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The one motion of this seed (its own stream: the same draws every call), at
        these times: Euler angles and their rates."""
        return _euler_and_rates(times, np.random.default_rng(seed + 1), motion, yaw0)

    angles0, _ = motion_at(t[:1])
    angles, rates = motion_at(t - 0.5 * dt)
    omega = _body_rates(angles, rates)

    q = _integrate(so3.quat_from_euler_zyx(*angles0[0]), omega, dt)

    bias = np.empty((n, 3))
    bias[0] = rng.normal(0.0, noise.gyro_bias_sigma, 3)
    steps = rng.normal(0.0, noise.gyro_bias_random_walk * math.sqrt(dt), (n - 1, 3))
    bias[1:] = bias[0] + np.cumsum(steps, axis=0)

    density = np.sqrt(
        noise.gyro_noise_density**2 + noise.gyro_scale_noise_density**2 * np.sum(omega**2, axis=1)
    )
    gyro = omega + bias + rng.normal(0.0, 1.0, (n, 3)) * (density / math.sqrt(dt))[:, None]
    velocity = _velocity(t, rng, motion)
    linear = _bursts(t, rng, motion)
    linear[1:] += np.diff(velocity, axis=0) / np.diff(t)[:, None]  # held over each sample
    specific_force_world = linear - np.array([0.0, 0.0, gravity])
    accel = rotate_to_body(q, specific_force_world)
    if noise.accel_alignment_sigma > 0.0:  # (its own stream: the other draws stay as they were)
        tilt = np.random.default_rng(seed + 3).normal(0.0, noise.accel_alignment_sigma, 2)
        accel = accel @ so3.exp(np.array([tilt[0], tilt[1], 0.0])).T
    accel += rng.normal(0.0, noise.accel_noise_density / math.sqrt(dt), (n, 3))
    # the magnetometer's error as the filter models it: white noise on the
    # field's azimuth (its norm and dip stay those of an undisturbed field)
    field_ned = np.asarray(field_ned, dtype=np.float64)
    azimuth_noise = np.random.default_rng(seed + 2).normal(
        0.0, noise.mag_heading_noise_density / math.sqrt(dt), n
    )
    cos, sin = np.cos(azimuth_noise), np.sin(azimuth_noise)
    north = cos * field_ned[0] - sin * field_ned[1]
    east = sin * field_ned[0] + cos * field_ned[1]
    field_world = np.column_stack([north, east, np.full(n, field_ned[2])])
    mag = rotate_to_body(q, field_world)
    if noise.imu_delay > 0.0:
        later, later_rates = motion_at(t + 0.5 * noise.imu_delay)
        # (scipy's rotations, not the filter's: the truth is made independently of it)
        turn = Rotation.from_rotvec(_body_rates(later, later_rates) * noise.imu_delay)
        moved = (Rotation.from_quat(q[:, [1, 2, 3, 0]]) * turn).as_quat(canonical=True)
        q = np.ascontiguousarray(moved[:, [3, 0, 1, 2]])
    return SimulatedImu(t, gyro, accel, q, bias, linear, velocity, mag, field_ned, noise)
