"""Monte Carlo consistency: is the filter's covariance honest about its error?

N simulated flights per scenario. The truth follows the filter's own process
model (:mod:`mavest.sim.kinematic`) with the noise the configuration claims,
and the initial error is drawn from the initial covariance the filter is given,
so a consistent filter has NEES = eᵀP⁻¹e ~ χ²(6) at every step and the average
over N runs, the ANEES, inside the χ² band: N·ANEES ~ χ²(6N) (Bar-Shalom et al.).

The error e = x_true ⊟ x̂ is taken in each filter's own chart (what its P
describes): Log(R R̂ᵀ) for the left exponential error, Log(R̂ᵀR) for the
right, the heading-tilt coordinates for that chart; e_b = b − b̂.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from mavest import so3
from mavest._jit import kernel
from mavest.estimator.charts import chart_quat_into, local_into
from mavest.estimator.config import CHARTS, ERROR_SIDES, EstimatorConfig
from mavest.estimator.estimator import Estimator
from mavest.estimator.frames import lead
from mavest.estimator.smoother import forward_accel, smooth_forward
from mavest.evaluation.metrics import attitude_errors
from mavest.sim.kinematic import ImuNoise, Motion, SimulatedImu, earth_field, simulate


@dataclass(frozen=True)
class Scenario:
    """Initial uncertainty and motion of one Monte Carlo experiment."""

    name: str
    description: str
    tilt_sigma: float  # rad, per horizontal world axis
    heading_sigma: float  # rad
    motion: Motion = field(default_factory=Motion)
    duration: float = 60.0  # s
    rate: float = 100.0  # Hz
    magnetometer: bool = False  # 9-D: the filter also gets the field


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("small", "tilt₀ 2°, heading₀ 2°", math.radians(2.0), math.radians(2.0)),
    Scenario(
        "large_heading",
        "tilt₀ 20°, heading₀ 30° (heading unobservable)",
        math.radians(20.0),
        math.radians(30.0),
    ),
    Scenario(
        "large_tilt",
        "tilt₀ 60° RMS (42° per axis), heading₀ 5°",
        math.radians(60.0) / math.sqrt(2.0),
        math.radians(5.0),
    ),
    Scenario(
        "bursts",
        "tilt₀ 2°, heading₀ 2°, 3 m/s² linear-acceleration bursts of 1 s every ~5 s",
        math.radians(2.0),
        math.radians(2.0),
        Motion(burst_magnitude=3.0, burst_duration=1.0, burst_interval=5.0),
    ),
    Scenario(
        "changing_motion",
        "tilt₀ 2°, heading₀ 2°, velocity σ 0.2 m/s, 3 m/s from 20 s, 0.5 m/s from 40 s "
        "(not the configured level)",
        math.radians(2.0),
        math.radians(2.0),
        Motion(velocity_levels=((0.0, 0.2), (20.0, 3.0), (40.0, 0.5))),
    ),
    Scenario(
        "small_9d",
        "tilt₀ 2°, heading₀ 2°, magnetometer",
        math.radians(2.0),
        math.radians(2.0),
        magnetometer=True,
    ),
    Scenario(
        "large_heading_9d",
        "tilt₀ 5°, heading₀ 30°, magnetometer (heading observed: the reset matters)",
        math.radians(5.0),
        math.radians(30.0),
        magnetometer=True,
    ),
)


def chi2_band(dof: int, runs: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the average of ``runs`` χ²(dof) variables."""
    tail = 0.5 * (1.0 - level)
    return chi2.ppf(tail, dof * runs) / runs, chi2.ppf(1.0 - tail, dof * runs) / runs


@kernel
def _errors(
    q_true: np.ndarray,
    b_true: np.ndarray,
    q_est: np.ndarray,
    b_est: np.ndarray,
    error: int,
    chart: int,
) -> np.ndarray:
    """(N, 6) e = x_true ⊟ x̂ in the filter's chart."""
    out = np.empty((q_true.shape[0], 6))
    work = np.empty(4)
    for i in range(q_true.shape[0]):
        local_into(q_true[i], q_est[i], error, chart, out[i, :3], work)
        for j in range(3):
            out[i, 3 + j] = b_true[i, j] - b_est[i, j]
    return out


def _nees(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[..., None])[..., 0])


@dataclass(frozen=True)
class RunResult:
    nees: np.ndarray  # (N,) 6 dof
    nees_attitude: np.ndarray  # (N,) 3 dof
    nis: np.ndarray  # (N,) NaN where the accelerometer was not used
    tilt_error: np.ndarray  # (N,) rad
    heading_error: np.ndarray  # (N,) rad


def run_once(
    config: EstimatorConfig,
    scenario: Scenario,
    data: SimulatedImu,
    seed: int,
    smoothed: bool = False,
) -> RunResult:
    """One flight: start from a prior drawn from the covariance the filter is given.

    ``smoothed``: score the smoother (:func:`~mavest.estimator.smoother.smooth_forward`
    on this forward pass, run on the accelerometer as the smoother's is:
    :func:`~mavest.estimator.smoother.forward_accel`) instead of the filter; the NIS
    stays the forward pass's.
    """
    rng = np.random.default_rng(seed)
    P0 = np.diag(
        [scenario.tilt_sigma**2, scenario.tilt_sigma**2, scenario.heading_sigma**2]
        + [config.initial_bias_sigma**2] * 3
    )
    delta = rng.multivariate_normal(np.zeros(3), P0[:3, :3])
    # R_true = chart(δ) R̂ for the world-frame charts; the right error sees the same
    # rotation, Exp(δ) R̂ = R̂ Exp(R̂ᵀ δ), whose covariance initialise() converts.
    chart_index = CHARTS.index(config.chart)
    error_rotation = np.empty(4)
    chart_quat_into(delta, chart_index, error_rotation)
    # The filter's state is the IMU's attitude, imu_delay before the truth it reports
    # against (docs/design.md#the-imus-delay): its start is the truth taken back by it.
    truth0 = lead(data.q_true[:1], data.gyro[:1], data.bias_true[:1], -config.imu_delay)[0]
    q0 = so3.quat_multiply(so3.quat_conjugate(error_rotation), truth0)
    estimator = Estimator(config)
    estimator.initialise(data.t[0], q0, np.zeros(3), P0)
    mag = data.mag[1:] if scenario.magnetometer else None
    accel = data.accel[1:]
    if smoothed:  # the forward pass as the smoother runs it
        accel = forward_accel(data.t[1:], data.gyro[1:], accel, config)
    out = estimator.update_batch(data.t[1:], data.gyro[1:], accel, mag)
    nis = np.where(out.accel_used, out.nis, np.nan)
    if smoothed:  # the backward pass as the smoother starts it: from the forward one's end
        out = smooth_forward(out, data.t[1:], data.gyro[1:], data.accel[1:], mag, config)
    e = _errors(
        data.q_true[1:],
        data.bias_true[1:],
        out.q,
        out.bias,
        ERROR_SIDES.index(config.error),
        chart_index,
    )
    errors = attitude_errors(out.q, data.q_true[1:])
    return RunResult(
        _nees(e, out.cov),
        _nees(e[:, :3], out.cov[:, :3, :3]),
        nis,
        errors.inclination,
        errors.heading,
    )


@dataclass(frozen=True)
class Summary:
    """ANEES over runs: averaged over the whole run, and over its first and last 10 s.

    The verdict (:meth:`in_band`) is on the whole-run averages, 6 dof and
    attitude alone, against the 95 % band of a single time step: a time
    average varies less than one step, so the band is conservative for it,
    while one verdict per scenario keeps the chance of a false alarm at 5 %
    instead of compounding it over many windows.
    """

    runs: int
    anees: float
    anees_attitude: float
    anees_early: float
    anees_late: float
    nis: float
    tilt_rmse_deg: float
    heading_rmse_deg: float

    @property
    def band6(self) -> tuple[float, float]:
        return chi2_band(6, self.runs)

    @property
    def band3(self) -> tuple[float, float]:
        return chi2_band(3, self.runs)

    def in_band(self) -> bool:
        lo6, hi6 = self.band6
        lo3, hi3 = self.band3
        return lo6 <= self.anees <= hi6 and lo3 <= self.anees_attitude <= hi3

    @staticmethod
    def combine(parts: list[Summary]) -> Summary:
        """The summary of disjoint sets of runs, from theirs (run-weighted)."""
        runs = sum(p.runs for p in parts)

        def mean(name: str) -> float:
            return sum(getattr(p, name) * p.runs for p in parts) / runs

        def rms(name: str) -> float:
            return math.sqrt(sum(getattr(p, name) ** 2 * p.runs for p in parts) / runs)

        return Summary(
            runs,
            mean("anees"),
            mean("anees_attitude"),
            mean("anees_early"),
            mean("anees_late"),
            mean("nis"),
            rms("tilt_rmse_deg"),
            rms("heading_rmse_deg"),
        )


def summarise(results: list[RunResult], rate: float, window: float = 10.0) -> Summary:
    anees = np.array([r.nees for r in results]).mean(axis=0)
    anees_att = np.array([r.nees_attitude for r in results]).mean(axis=0)
    n_window = round(window * rate)
    tilt = np.concatenate([r.tilt_error for r in results])
    heading = np.concatenate([r.heading_error for r in results])
    nis = np.concatenate([r.nis for r in results])
    return Summary(
        len(results),
        float(anees.mean()),
        float(anees_att.mean()),
        float(anees[:n_window].mean()),
        float(anees[-n_window:].mean()),
        float(np.nanmean(nis)) if np.any(np.isfinite(nis)) else math.nan,
        float(np.degrees(np.sqrt(np.mean(tilt**2)))),
        float(np.degrees(np.sqrt(np.mean(heading**2)))),
    )


def distinct_flights(names: Sequence[str] | None = None) -> list[Scenario]:
    """The scenarios whose flights differ (those named, or all): scenarios that differ
    only in the prior the Monte Carlo draws fly the same, and the first of them stands
    for the rest (for tools that let the filter align itself on the flights)."""
    kept: dict[tuple, Scenario] = {}
    for scenario in SCENARIOS:
        if names and scenario.name not in names:
            continue
        flight = (scenario.motion, scenario.duration, scenario.rate, scenario.magnetometer)
        kept.setdefault(flight, scenario)
    return list(kept.values())


def simulate_scenario(scenario: Scenario, config: EstimatorConfig, seed: int) -> SimulatedImu:
    """The flight of one run (the same for every variant compared on it).

    Sensor noise and the vehicle's velocity variations are what the
    configuration claims (unless the scenario sets the velocity's levels); the
    scenario's bursts come on top, unmodelled.
    """
    motion = dataclasses.replace(
        scenario.motion,
        velocity_sigma=config.velocity_sigma,
        velocity_time=config.velocity_time,
    )
    return simulate(
        scenario.duration,
        scenario.rate,
        noise=ImuNoise.matching(config),
        motion=motion,
        seed=seed,
        gravity=config.gravity,
        field_ned=earth_field(config.compass_dec),
    )


def monte_carlo(
    configs: list[EstimatorConfig],
    scenario: Scenario,
    runs: int,
    seed: int = 0,
    smoothed: bool = False,
) -> list[Summary]:
    """Summaries for each config on the same ``runs`` flights (their noise must agree);
    ``smoothed``: of the smoother on each config's forward pass."""
    per_config: list[list[RunResult]] = [[] for _ in configs]
    for k in range(runs):
        data = simulate_scenario(scenario, configs[0], seed + k)
        for i, config in enumerate(configs):
            per_config[i].append(
                run_once(config, scenario, data, seed + 10_000 + k, smoothed=smoothed)
            )
    return [summarise(results, scenario.rate) for results in per_config]
