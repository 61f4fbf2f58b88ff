"""Estimator parameters: what a user may set, with defaults that work unconfigured.

Following VQF's split, three things are kept apart:
:class:`EstimatorConfig` (this module: user-facing parameters, immutable),
the coefficients derived from it once (:mod:`mavest.estimator.layout`), and the
filter state that changes every sample. Noise is given as densities, never per
sample, so one configuration serves a 1 Hz and a 2 kHz IMU alike (a per-sample σ
tuned at 200 Hz got worse at 1 kHz: docs/design.md#conventions).
"""

from __future__ import annotations

import codecs
import dataclasses
import functools
import math
import numbers
import sys
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mavest import timeline

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

UpdateKind = Literal["ekf", "iterated", "sigma_point"]
ErrorSide = Literal["left", "right"]
ResetPolicy = Literal["none", "first_order", "full"]
Chart = Literal["exp", "heading_tilt"]

UPDATE_KINDS: tuple[str, ...] = ("ekf", "iterated", "sigma_point")
ERROR_SIDES: tuple[str, ...] = ("left", "right")
RESET_POLICIES: tuple[str, ...] = ("none", "first_order", "full")
CHARTS: tuple[str, ...] = ("exp", "heading_tilt")

STANDARD_GRAVITY = 9.80665  # m/s², the value MAVLink's mG units are defined with
# A specific force beyond this on any axis is a broken sensor or a corrupt packet, never
# flight (IMUs range to ±16 or ±32 g): the service drops such samples, and the
# smoother's average of the accelerometer leaves them out.
MAX_SPECIFIC_FORCE = 50.0 * STANDARD_GRAVITY  # m/s²
# An accelerometer misaligned by more than this is mounted wrong, not miscalibrated.
MAX_ALIGNMENT_SIGMA = math.radians(10.0)  # rad
# A sensor's own filters delay it by milliseconds (45 ms at a 5 Hz cutoff). The estimate
# is carried over the delay at the sample's rate: beyond this, the rate's change over it
# is no longer small (it grows as the delay's square), and the covariance, which leaves
# that out, too small: a Monte Carlo of 1–3 s oscillations, 100 runs, has ANEES 6.40
# without a delay, 6.50 at 50 ms and 7.40 at 100 ms (95 % band [5.34, 6.70]).
MAX_IMU_DELAY = 0.05  # s

# A gyro rate beyond this on any axis is a broken sensor or a corrupt packet, never
# flight (≈ 2900°/s; MEMS gyros range to ±2000°/s): the filter skips such a sample as it
# skips a NaN one (StepFlags.GYRO_INVALID), and the service drops it before.
MAX_ANGULAR_RATE = 50.0  # rad/s

# The filter's health check (mavest.estimator.health) takes a state beyond these for a
# numerical accident, not an estimate, and re-initialises it; the configuration's
# initial state and noise are held within them (else every sample would fail it).
MAX_GYRO_BIAS = 0.5  # rad/s per axis (29°/s: beyond any MEMS gyro's offset, calibrated or not)
MAX_ATTITUDE_VAR = 4.0 * math.pi**2  # rad², any δθ axis
MAX_CONSIDERED_VAR = 1e6  # (m/s²)², (m/s³)², (m/s)²: the low-pass's ε, ḟ and the velocity
# Heading's σ never exceeds 180°: a wrapped normal that wide is as good as uniform, and
# the linear model of a wider one means nothing (6-D, hours without a compass). The health
# check caps heading's variance at this; the smoother gives it to a heading nothing has
# referenced yet, which says nothing of the world's north.
MAX_HEADING_VAR = math.pi**2  # rad²

# The Gauss–Newton iterations of a gravity update at most (max_iterations): quadratic
# convergence reaches any tolerance in a few; a sample's count is stored in 16 bits.
MAX_ITERATIONS = 100
# timeline_confirm at most (samples in a row; a count the filter keeps in 64 bits)
_MAX_CONFIRM = 1_000_000


class ConfigError(ValueError):
    """A configuration value that cannot work, with the reason in the message."""


@dataclass(frozen=True)
class EstimatorConfig:
    """Every parameter of the attitude filter.

    Structure (see docs/design.md#heading-tilt-chart and the Monte Carlo consistency
    tool for why the defaults are what they are):

    update
        ``"ekf"`` one Gauss–Newton step; ``"iterated"`` Gauss–Newton with the
        prior-correction term until ``iteration_tolerance``; ``"sigma_point"``
        USQUE-style unscented prediction and update.
    error
        ``"left"``: R = Exp(δθ) R̄, δθ in the world frame (docs/design.md#state-and-error);
        ``"right"``: R = R̄ Exp(δθ), δθ in the body frame.
    chart
        How the 3-D attitude error is mapped onto rotations. ``"exp"``: the
        exponential map. ``"heading_tilt"`` (left error only):
        R = Rz(ψ) Exp([τx, τy, 0]) R̄ — rotation about the world vertical split
        from tilt, so that the reset never moves heading uncertainty into tilt
        while gravity alone cannot see heading.
    reset
        How the covariance follows when the error mean is moved into the
        reference (Mueller et al. 2017): ``"none"`` (the MEKF), ``"first_order"``,
        ``"full"`` (the exact Jacobian of the chart, Gill et al. 2020).
    """

    update: UpdateKind = "iterated"
    error: ErrorSide = "left"
    chart: Chart = "heading_tilt"
    reset: ResetPolicy = "full"
    max_iterations: int = 6  # at most MAX_ITERATIONS
    # rad (and rad/s): the iteration ends when ‖Δx‖, or the next step Gauss–Newton's
    # quadratic convergence predicts from it (10 ‖Δθ‖²), is below this
    iteration_tolerance: float = 1e-6
    # Unscented transform: sigma points at ±√(n + λ) σ with n + λ = ``sigma_spread``
    # whatever the dimension n (3: Julier's choice, the points stay near the mean
    # where the charts are good); β = 2 is exact for Gaussian fourth moments.
    sigma_spread: float = 3.0
    sigma_beta: float = 2.0

    # Sensor noise, as densities.
    gyro_noise_density: float = 0.005  # rad/s/√Hz (angle random walk and unmodelled gyro error)
    gyro_bias_random_walk: float = 2e-5  # rad/s²/√Hz
    # The gyro's scale-factor and axis-alignment errors (and a reference's timing)
    # make an attitude error proportional to the rate: white noise of density
    # this × |ω| on top of gyro_noise_density (0: none).
    gyro_scale_noise_density: float = 0.0  # √s
    accel_noise_density: float = 0.02  # m/s²/√Hz
    # The accelerometer's alignment: how far (1σ, each horizontal axis) the gravity
    # direction it measures at rest is from the true vertical, from its calibration
    # (offset, scale, misalignment) and the IMU's mounting. No update can remove
    # that error, so it is added to the tilt covariance the estimate reports, not to
    # the filter's own (docs/design.md#the-accelerometers-alignment). 0: none.
    accel_alignment_sigma: float = 0.0  # rad
    # How long the IMU's samples lag the motion they measure: the group delay of its
    # anti-alias and digital low-pass filters, from its datasheet and settings. The
    # filter runs on the samples as they are, so its state is the attitude this long
    # before each sample's time stamp; the estimate reported is that attitude carried
    # forward by the sample's rate, q ⊗ Exp((ω − b) τ), the attitude at the time stamp
    # (docs/design.md#the-imus-delay). 0: none.
    imu_delay: float = 0.0  # s
    gravity: float = STANDARD_GRAVITY

    # Accelerometer robustness in dynamic motion.
    accel_norm_inflation: float = 0.0  # σ grows by this × |‖a‖ − g| (0: off; docs/limits.md)
    accel_norm_tolerance: float = 3.0  # m/s²: |‖a‖ − g| beyond this is not gravity
    # NIS (χ², 2 dof) beyond which the sample's noise is inflated to match its
    # innovation (0: off); disturbed this long, the attitude gets the blame.
    accel_gate: float = 5.99
    accel_max_disturbance_time: float = 10.0  # s
    # Divergence: tilt reopened a second time within this window means reopening
    # did not cure it (a confidently wrong gyro bias drags the attitude away again):
    # the filter is re-initialised, bias from its prior (0: never). No shared log or
    # BROAD trial reopens tilt; simulated 120 s flights with long turns and no GPS
    # do, once at most (3 of 8 at 200 Hz).
    divergence_window: float = 30.0  # s
    # Low-pass of the specific force in the estimated world frame (0: off). Linear
    # acceleration integrates to a bounded velocity change, so it averages out
    # while gravity stays (VQF's idea, Laidig & Seel 2023). The filter state is
    # rotated with every correction, so it lags only the gyro's drift; its error
    # is carried as a considered state (Schmidt), keeping the covariance honest.
    accel_lowpass_time: float = 3.0  # s; natural frequency √2/τ
    accel_lowpass_damping: float = 1.0 / math.sqrt(2.0)  # ζ ∈ (0, 1]; 1/√2: Butterworth
    # A correction larger than this restarts the low-pass (0: never).
    accel_lowpass_restart_angle: float = math.radians(2.0)  # rad
    # The measurement updates (gravity, the magnetometer, the zero-rate update at
    # rest) run about this often: one is due at the sample nearest to 1/update_rate
    # after the last (ties to the earlier: at 100 Hz, every other sample). Every
    # sample is still predicted (attitude and covariance) and taken into the
    # low-pass, whose error the filter carries, so an update sees every sample's
    # accelerometer and a slower update rate loses next to nothing (BROAD: updates
    # at 1/7 of its 286 Hz score as at every sample). It is what autopilots do
    # (PX4's EKF2 runs at 100 Hz), for the same reason: the updates are most of a
    # step's cost. 40 Hz scores as 50 Hz did on every data set of tools/evidence.py
    # (BROAD, the logs, the JSBSim flights); 33 and 25 Hz begin to cost
    # (docs/limits.md). 0: every sample. Without the low-pass (accel_lowpass_time = 0)
    # every sample is an update: each sample's accelerometer is then information
    # of its own.
    update_rate: float = 40.0  # Hz
    # The vehicle's velocity, whose derivative is the linear acceleration the
    # low-pass averages away: Gauss–Markov, stationary σ (each world axis) and
    # correlation time.
    velocity_sigma: float = 1.5  # m/s
    velocity_time: float = 1.0  # s
    # The velocity's σ measured from the data instead (0: fixed at velocity_sigma):
    # the horizontal specific force in the estimated world frame, less its low-pass,
    # integrated with the velocity's correlation time, gives the velocity's fast part;
    # its mean square over this time is the vehicle's motion level. velocity_sigma
    # is then the level assumed before any data.
    velocity_adapt_time: float = 0.0  # s
    velocity_adapt_gain: float = 2.0  # the measured mean square × this is σ_v²
    velocity_sigma_min: float = 0.05  # m/s: the adapted σ_v goes no lower
    # When the vehicle's acceleration is known (``linear_accel``, e.g. from GPS
    # velocity) it is removed from the specific force and what is left is the
    # error of that knowledge (the GPS velocity's error and its lag): the same
    # Gauss–Markov velocity model with this σ.
    aided_velocity_sigma: float = 0.3  # m/s
    # ... used only while heading is known to within this (1σ): the acceleration
    # is known in the world frame and must be turned into the body.
    aided_max_heading_sigma: float = math.radians(10.0)  # rad

    # Rest detection (VQF's criteria) and, at rest, a zero-rate update of the bias.
    rest_detection: bool = True
    rest_filter_time: float = 0.5  # s, low-pass of gyro and accel for the criteria
    rest_gyro_threshold: float = math.radians(2.0)  # rad/s, ‖ω − ω̄‖ below this
    rest_accel_threshold: float = 0.5  # m/s², ‖a − ā‖ below this
    rest_min_time: float = 1.5  # s the criteria must hold
    rest_rate_sigma: float = math.radians(0.01)  # rad/s of true rotation still allowed at rest

    # Magnetometer (9-D): heading only, never tilt (mavest.estimator.magnetic).
    # Input in µT. Heading noise as a density: an update Δt after the previous
    # magnetometer sample has variance density²/Δt (so a 10 Hz and a 1 kHz
    # magnetometer mean the same); the correction's time constant is about
    # density/gyro_noise_density.
    mag_heading_noise_density: float = 0.08  # rad·√s
    # The tilt error leaks into the field's azimuth (× tan dip); it changes only
    # as fast as gravity corrects tilt, so the heading gain counts it as white
    # noise of the same low-frequency power: its variance × this time / Δt
    # (≈ accel_lowpass_time; 0: the variance alone, as if new every sample).
    mag_tilt_leak_time: float = 3.0  # s
    # heading's σ when the field is trusted again after mag_max_rejection_time
    mag_reopened_heading_sigma: float = math.radians(20.0)  # rad
    # Calibration as ArduPilot names it: m = A (raw + COMPASS_OFS), A the symmetric
    # matrix of COMPASS_DIA (diagonal) and COMPASS_ODI (off-diagonal: xy, xz, yz);
    # COMPASS_DEC the declination (rad, east positive: yaw = magnetic heading + dec).
    # ArduPilot's RAW_IMU already carries the calibrated field: set these only for
    # an uncalibrated sensor. With compass_dec 0 the service takes the vehicle's own
    # COMPASS_DEC when the link (or log) carries it.
    compass_ofs: tuple[float, float, float] = (0.0, 0.0, 0.0)  # milligauss
    compass_dia: tuple[float, float, float] = (1.0, 1.0, 1.0)
    compass_odi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    compass_dec: float = 0.0  # rad
    # Disturbance rejection: the reference field (norm and dip) is learned over
    # the first mag_reference_time, then follows slowly (mag_reference_adapt_time)
    # while undisturbed. A field off the reference by more than the tolerances,
    # or whose heading innovation is beyond the χ² (1 dof) gate, is not used;
    # a disturbed field steady for mag_new_reference_time becomes the reference
    # (a new place, not a passing magnet); rejected for longer than
    # mag_max_rejection_time, heading gets its initial uncertainty back and the
    # field is used again.
    mag_norm_tolerance: float = 0.1  # fraction of the reference norm
    mag_dip_tolerance: float = math.radians(10.0)  # rad
    mag_gate: float = 10.83  # χ² 1 dof, 99.9 %
    mag_reference_time: float = 2.0  # s
    mag_reference_adapt_time: float = 30.0  # s (0: never)
    mag_new_reference_time: float = 20.0  # s
    mag_max_rejection_time: float = 60.0  # s
    # After a disturbance the field must be undisturbed this long before it is
    # used again: a passing magnet's field crosses the tolerances on its way.
    mag_recovery_time: float = 1.0  # s

    # Initial uncertainty (the first samples set tilt from the accelerometer).
    initial_tilt_sigma: float = math.radians(5.0)  # rad
    initial_heading_sigma: float = math.radians(5.0)  # rad, about the world vertical
    initial_bias_sigma: float = math.radians(0.5)  # rad/s, each axis
    initial_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s

    # Time: a step longer than this is a gap; the attitude is re-aligned.
    max_dt: float = 2.0  # s
    # A time far off the timeline (forward by more than max_jump, back by more than
    # mavest.timeline.REORDER_WINDOW) is believed only when it and the samples after
    # it, timeline_confirm in a row, continue from it: a single corrupted timestamp
    # is skipped (StepFlags.TIME_OFF_TIMELINE), a jump that stays is a gap, and time
    # that went back and stayed a restart (StepFlags.TIME_RESTARTED). 1: every time
    # is believed at once, for a caller that confirms its timeline itself (the
    # service's clock does, and holds a new timeline's first samples meanwhile).
    max_jump: float = timeline.MAX_JUMP  # s
    timeline_confirm: int = timeline.CONFIRM

    # A gyro reading this large on any axis is taken as clipped (inf: never): the
    # sensor's range, a little under it where calibration scales the raw limit;
    # 97 % of the ±2000 °/s that flight controllers set their gyros to. The
    # rotation it missed is unknown: the accelerometer is not used until the
    # vehicle is calm again (‖a‖ near g, rate under 30 °/s, for 0.5 s), and then
    # sets tilt afresh (the magnetometer heading). Estimator.gyro_clipped() says
    # the same for a sample the caller knows clipped (an integer field at its limit).
    gyro_clip: float = math.radians(0.97 * 2000.0)  # rad/s

    # Smoothing only (mavest.smooth): the forward pass takes the accelerometer
    # low-passed forward and backward (zero phase) with this time constant in the
    # gyro's strapdown frame, the backward pass takes it as measured (0: both as
    # measured). The two passes' tilt errors are then less alike, and fusing them
    # gains more (docs/design.md#smoothing; chosen on halves of BROAD: docs/results.md).
    smooth_accel_time: float = 0.5  # s

    def __post_init__(self) -> None:
        # The TOML path's rule for each value's type holds for the constructor's too: a
        # bool or a string where a number goes would pass, or fail deep in the filter.
        fields = {name: getattr(self, name) for name in _field_types(type(self))}
        for name, value in check_types(type(self), fields, None).items():
            object.__setattr__(self, name, value)
        _require(self.update in UPDATE_KINDS, f"update must be one of {UPDATE_KINDS}")
        _require(self.error in ERROR_SIDES, f"error must be one of {ERROR_SIDES}")
        _require(self.reset in RESET_POLICIES, f"reset must be one of {RESET_POLICIES}")
        _require(self.chart in CHARTS, f"chart must be one of {CHARTS}")
        _require(
            not (self.chart == "heading_tilt" and self.error == "right"),
            "chart 'heading_tilt' splits rotation about the world vertical and needs "
            "error = 'left'",
        )
        _require(
            1 <= self.max_iterations <= MAX_ITERATIONS,
            f"max_iterations must be from 1 to {MAX_ITERATIONS}, got {self.max_iterations}",
        )
        _require(
            1 <= self.timeline_confirm <= _MAX_CONFIRM,
            f"timeline_confirm must be from 1 to {_MAX_CONFIRM}, got {self.timeline_confirm}",
        )
        _require(self.max_jump > 0.0, f"max_jump must be > 0 (inf: never), got {self.max_jump}")
        _require(self.gyro_clip > 0.0, f"gyro_clip must be > 0 (inf: never), got {self.gyro_clip}")
        _require(0.0 < self.accel_lowpass_damping <= 1.0, "accel_lowpass_damping must be in (0, 1]")
        for name in (
            "gyro_noise_density",
            "accel_noise_density",
            "iteration_tolerance",
            "accel_norm_tolerance",
            "gravity",
            "initial_tilt_sigma",
            "initial_heading_sigma",
            "initial_bias_sigma",
            "max_dt",
            "sigma_spread",
            "velocity_sigma",
            "velocity_time",
            "velocity_adapt_gain",
            "velocity_sigma_min",
            "aided_velocity_sigma",
            "aided_max_heading_sigma",
            "mag_heading_noise_density",
            "mag_reopened_heading_sigma",
            "mag_norm_tolerance",
            "mag_dip_tolerance",
            "mag_reference_time",
            "mag_new_reference_time",
            "mag_max_rejection_time",
        ):
            require_number(name, getattr(self, name))
        for name in (
            "gyro_bias_random_walk",
            "gyro_scale_noise_density",
            "accel_norm_inflation",
            "accel_gate",
            "accel_max_disturbance_time",
            "divergence_window",
            "accel_lowpass_time",
            "accel_lowpass_restart_angle",
            "update_rate",
            "rest_filter_time",
            "rest_gyro_threshold",
            "rest_accel_threshold",
            "rest_min_time",
            "rest_rate_sigma",
            "mag_recovery_time",
            "mag_gate",
            "mag_reference_adapt_time",
            "mag_tilt_leak_time",
            "velocity_adapt_time",
            "smooth_accel_time",
            "accel_alignment_sigma",
            "imu_delay",
        ):
            require_number(name, getattr(self, name), zero=True)
        # (after the number checks: a NaN is said to be no number, not too large)
        _require(
            self.accel_alignment_sigma <= MAX_ALIGNMENT_SIGMA,
            f"accel_alignment_sigma must be at most {MAX_ALIGNMENT_SIGMA:g} rad (10°)",
        )
        _require(
            self.imu_delay <= MAX_IMU_DELAY,
            f"imu_delay must be at most {MAX_IMU_DELAY:g} s, got {self.imu_delay}",
        )
        for name in ("initial_bias", "compass_ofs", "compass_dia", "compass_odi"):
            value = getattr(self, name)
            _require(
                len(value) == 3 and all(math.isfinite(v) for v in value),
                f"{name} must be three finite numbers",
            )
        _require(
            abs(self.compass_dec) <= math.pi,
            f"compass_dec must be within ±π rad, got {self.compass_dec} (degrees?)",
        )
        self._require_healthy_start()
        _require(
            abs(self.sigma_beta) <= NUMBER_RANGE[1],
            f"sigma_beta must be a number from -{NUMBER_RANGE[1]:g} to {NUMBER_RANGE[1]:g}, "
            f"got {self.sigma_beta}",
        )
        # A calibration's soft-iron matrix is a scaling near I: positive definite. A
        # negative or reflecting one turns the field (a heading 170° off, silently).
        with np.errstate(all="ignore"):
            least = float(np.min(np.linalg.eigvalsh(self.soft_iron)))
        _require(
            least > 1e-3 and bool(np.all(np.abs(self.soft_iron) <= 1e3)),
            "compass_dia/compass_odi must make a positive definite soft-iron matrix, a "
            "scaling near the identity (ArduPilot's calibration gives one)",
        )

    def _require_healthy_start(self) -> None:
        """The state the filter starts in, and a second of its gyro noise, within the
        bounds of its health check (MAX_GYRO_BIAS, MAX_ATTITUDE_VAR, MAX_CONSIDERED_VAR):
        beyond them every sample would fail the check and start the filter again."""
        _require(
            all(abs(b) <= MAX_GYRO_BIAS for b in self.initial_bias),
            f"initial_bias must be within ±{MAX_GYRO_BIAS:g} rad/s on each axis (beyond any "
            f"gyro's offset), got {self.initial_bias}",
        )
        _require(
            self.initial_bias_sigma < MAX_GYRO_BIAS,
            f"initial_bias_sigma must be below {MAX_GYRO_BIAS:g} rad/s (beyond any gyro's "
            f"offset), got {self.initial_bias_sigma:g}",
        )
        max_sigma = math.sqrt(MAX_ATTITUDE_VAR)
        _require(
            self.initial_tilt_sigma < max_sigma,
            f"initial_tilt_sigma must be below {max_sigma:.4g} rad (2π), "
            f"got {self.initial_tilt_sigma:g}",
        )
        _require(
            self.gyro_noise_density <= max_sigma,
            f"gyro_noise_density must be at most {max_sigma:.4g} rad/s/√Hz (a second of it "
            f"within 2π), got {self.gyro_noise_density:g}",
        )
        max_velocity = math.sqrt(MAX_CONSIDERED_VAR)
        for name in ("velocity_sigma", "velocity_sigma_min", "aided_velocity_sigma"):
            _require(
                getattr(self, name) <= max_velocity,
                f"{name} must be at most {max_velocity:g} m/s, got {getattr(self, name):g}",
            )

    def replace(self, **changes: Any) -> EstimatorConfig:
        """A copy with some parameters changed (the config itself is immutable)."""
        return dataclasses.replace(self, **changes)

    @property
    def soft_iron(self) -> np.ndarray:
        """ArduPilot's soft-iron matrix from COMPASS_DIA and COMPASS_ODI (symmetric)."""
        (dx, dy, dz), (oxy, oxz, oyz) = self.compass_dia, self.compass_odi
        return np.array([[dx, oxy, oxz], [oxy, dy, oyz], [oxz, oyz, dz]])

    @property
    def variant(self) -> str:
        """A short name of the filter structure, e.g. ``iterated/left/heading_tilt/full``."""
        return f"{self.update}/{self.error}/{self.chart}/{self.reset}"

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> EstimatorConfig:
        """Build from a mapping (e.g. a TOML table), rejecting unknown keys by name and
        values of the wrong type (:func:`check_types`) with a :class:`ConfigError`."""
        require_table(values, "estimator")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(
                f"unknown estimator parameter(s): {', '.join(unknown)}; "
                f"known: {', '.join(sorted(known))}"
            )
        return cls(**check_types(cls, values, "estimator"))

    @classmethod
    def from_toml(cls, path: str | Path, table: str = "estimator") -> EstimatorConfig:
        """Read the ``[estimator]`` table of a TOML file (other tables are ignored)."""
        return cls.from_mapping(read_toml(path).get(table, {}))


def config_or_default(config: EstimatorConfig | None) -> EstimatorConfig:
    """``config``, or the defaults for None; a :class:`TypeError` for anything else (a
    dict, a file's path), saying how to make one."""
    if config is None:
        return EstimatorConfig()
    if not isinstance(config, EstimatorConfig):
        raise TypeError(
            f"config must be an EstimatorConfig, got {type(config).__name__}: build one with "
            "EstimatorConfig(...), EstimatorConfig.from_mapping(dict) or "
            "EstimatorConfig.from_toml(path)"
        )
    return config


def require_table(values: Any, table: str) -> None:
    """A :class:`ConfigError` unless ``values`` is a table (a mapping of settings)."""
    _require(
        isinstance(values, Mapping),
        f"[{table}] must be a table of settings, got {type(values).__name__} {values!r}",
    )


def check_types(cls: type, values: Mapping[str, Any], table: str | None) -> dict[str, Any]:
    """``values`` for the dataclass ``cls``, each checked against its field's type (a
    :class:`ConfigError` names the table, None: the constructor's arguments, and the
    key) and made that type: lists and arrays become tuples, numpy's numbers Python's."""
    require_table(values, "" if table is None else table)
    hints = _field_types(cls)
    checked = dict(values)
    for key, value in values.items():
        expected = hints[key]
        origin = typing.get_origin(expected)
        if origin is tuple:
            items = typing.get_args(expected)
            kind = items[0]
            fits = isinstance(value, (list, tuple, np.ndarray)) and all(
                _fits(v, kind) for v in value
            )
            if fits and items[-1] is not Ellipsis:
                fits = len(value) == len(items)
            count = "" if items[-1] is Ellipsis else f"{len(items)} "
            wanted = f"a list of {count}{_TYPE_NAMES[kind]}s"
            if fits:
                checked[key] = tuple(kind(v) for v in value)
        else:
            kind = str if origin is Literal else expected
            fits = _fits(value, kind)
            wanted = _TYPE_NAMES[kind]
            if fits:
                checked[key] = kind(value)
        if not fits:
            where = key if table is None else f"[{table}] {key}"
            raise ConfigError(f"{where} = {value!r}: expected {wanted}")
    return checked


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """A dataclass's fields and their types (resolved once: get_type_hints takes as long
    as the rest of a configuration's checks)."""
    hints = typing.get_type_hints(cls)
    return {field.name: hints[field.name] for field in dataclasses.fields(cls)}


_TYPE_NAMES = {float: "number", int: "whole number", bool: "true or false", str: "string"}
# A bool is a number to Python, never a setting's number; numpy's own are its numbers
_BOOLS = (bool, np.bool_)


def _fits(value: Any, kind: type) -> bool:
    if kind is float:
        return isinstance(value, numbers.Real) and not isinstance(value, _BOOLS)
    if kind is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, _BOOLS)
    if kind is bool:
        return isinstance(value, _BOOLS)
    return isinstance(value, kind)


def read_toml(path: str | Path) -> dict[str, Any]:
    """A TOML file as a dict; :class:`ConfigError` says why it cannot be read."""
    path = Path(path)
    try:
        data = path.read_bytes()
        # a byte-order mark, as Windows editors write at the start of UTF-8 text: not
        # TOML's, but not the user's mistake either
        data = data.removeprefix(codecs.BOM_UTF8)
        if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
            raise ConfigError(f"{path} is UTF-16 text: TOML is UTF-8 (save it as UTF-8)")
        return tomllib.loads(data.decode("utf-8"))
    except OSError as error:
        raise ConfigError(f"cannot read {path}: {error.strerror}") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path} is not valid TOML: {error}") from None
    except UnicodeDecodeError as error:  # TOML is UTF-8 text: a binary file, or a log
        raise ConfigError(
            f"{path} is not a TOML file: byte {error.start} is not UTF-8 text"
        ) from None


# The magnitudes a number in a configuration may have (besides 0 where 0 means "off"):
# the filter squares its σ and densities into variances and inverts its times and
# rates, and a number outside these would overflow to inf (an OverflowError, or a
# filter that is NaN from its first sample) or vanish to 0. No sensor, motion or time
# is within many orders of magnitude of either end.
NUMBER_RANGE = (1e-150, 1e150)


def require_number(name: str, value: float, *, zero: bool = False) -> None:
    """The rule for a numeric setting: finite and positive (``zero``: or 0, its "off"),
    within :data:`NUMBER_RANGE`; else a :class:`ConfigError` naming the setting."""
    least = "≥ 0" if zero else "> 0"
    _require(
        math.isfinite(value) and (value > 0.0 or (zero and value == 0.0)),
        f"{name} must be {least}, got {value}",
    )
    low, high = NUMBER_RANGE
    _require(
        value == 0.0 or low <= value <= high,
        f"{name} = {value:g} is out of range: mavest squares or inverts it, which must "
        f"stay a finite number; use {'0 or ' if zero else ''}{low:g} to {high:g}",
    )


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)
