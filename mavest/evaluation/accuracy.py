"""Accuracy on BROAD beside the peers: the scores behind tools/evidence.py and the tests.

The dataset's scoring: RMSE over the ``movement`` samples with valid truth, of
the inclination (6-D: heading is free) per trial, then the mean over trials.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from mavest.datasets.broad import BroadTrial
from mavest.estimator import EstimatorConfig, estimate, smooth
from mavest.estimator.frames import lead
from mavest.evaluation.metrics import rmse_deg
from mavest.evaluation.peers import PEERS, PeerAdapter

Filter = Callable[[BroadTrial], np.ndarray]
#: A filter's attitudes on a trial, carried forward by a delay (s).
Carried = Callable[[float], np.ndarray]

#: mavest's variants shown beside its default: each changes one choice of the default.
MAVEST_VARIANTS: dict[str, EstimatorConfig] = {
    "no rest detection": EstimatorConfig(rest_detection=False),
    "ekf": EstimatorConfig(update="ekf"),
    "sigma_point": EstimatorConfig(update="sigma_point"),
    "without low-pass": EstimatorConfig(accel_lowpass_time=0.0),
}


def mavest_adapter(config: EstimatorConfig | None = None, smoothed: bool = False) -> PeerAdapter:
    """mavest with ``config``, called like a peer adapter: ``run(t, gyro, accel, mag, rate)``
    (``rate`` is unused: mavest takes each sample's own time step); ``smoothed``: the
    smoother (:func:`mavest.smooth`) instead of the filter."""
    run_mavest = smooth if smoothed else estimate

    def run(
        t: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        mag: np.ndarray | None = None,
        rate: float | None = None,
    ) -> np.ndarray:
        return run_mavest(t, gyro, accel, mag, config).q

    return run


def mavest_filter(
    config: EstimatorConfig | None = None, mag: bool = False, smoothed: bool = False
) -> Filter:
    """mavest in 6-D (gyro and accelerometer), or 9-D with ``mag``, with ``config``;
    ``smoothed``: the smoother."""
    adapter = mavest_adapter(config, smoothed)

    def run(trial: BroadTrial) -> np.ndarray:
        return adapter(trial.t, trial.gyro, trial.accel, trial.mag if mag else None)

    return run


def peer_filter(name: str, mag: bool = False) -> Filter:
    """A peer from :data:`mavest.evaluation.peers.PEERS` in 6-D (9-D with ``mag``), at the
    trial's rate."""
    adapter = PEERS[name]

    def run(trial: BroadTrial) -> np.ndarray:
        return adapter(trial.t, trial.gyro, trial.accel, trial.mag if mag else None, trial.rate)

    return run


def peer_led(q: np.ndarray, gyro: np.ndarray, delay: float) -> np.ndarray:
    """A peer's attitudes carried forward by ``delay`` (s) as mavest carries its own
    (``EstimatorConfig.imu_delay``), by the gyro's rate: what the peer would report with
    mavest's delay, which it has no setting for. (A peer's bias is left in the rate: on
    BROAD it is under 0.01 rad/s, which moves a 3 ms lead by under 0.002°.)"""
    q = np.ascontiguousarray(q, dtype=np.float64)
    gyro = np.ascontiguousarray(gyro, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or gyro.shape != (q.shape[0], 3):
        raise ValueError(f"q must be (N, 4) and gyro (N, 3), got {q.shape} and {gyro.shape}")
    return lead(q, gyro, np.zeros_like(gyro), delay)


def carried_runs(trial: BroadTrial) -> dict[str, Carried]:
    """mavest's filter and smoother (defaults), VQF and offline VQF, each run once on the
    trial in 6-D, as functions of the delay their attitudes are carried forward by
    (mavest's as ``imu_delay`` carries them, the peers' by :func:`peer_led`)."""
    t, gyro, accel = trial.t, trial.gyro, trial.accel
    filtered = estimate(t, gyro, accel)
    smoothed = smooth(t, gyro, accel)
    vqf = PEERS["VQF"](t, gyro, accel, None, trial.rate)
    offline = PEERS["offline VQF"](t, gyro, accel, None, trial.rate)
    return {
        "mavest": lambda d: lead(filtered.q, gyro, filtered.bias, d),
        "mavest.smooth": lambda d: lead(smoothed.q, gyro, smoothed.bias, d),
        "VQF": lambda d: peer_led(vqf, gyro, d),
        "offline VQF": lambda d: peer_led(offline, gyro, d),
    }


@dataclass(frozen=True)
class InclinationScores:
    """Per-trial RMSE (°, inclination unless scored otherwise) of each filter, trials in
    the same order for all."""

    trials: tuple[str, ...]
    scores: dict[str, np.ndarray]

    def mean(self, name: str, subset: Sequence[int] | None = None) -> float:
        values = self.scores[name]
        return float(np.mean(values if subset is None else values[list(subset)]))


def score_inclination(
    trials: Sequence[BroadTrial], filters: dict[str, Filter], metric: str = "inclination"
) -> InclinationScores:
    """Every filter on every trial, scored as BROAD does (``metric``: "inclination",
    "heading" or "total", the keys of :func:`~mavest.evaluation.metrics.rmse_deg`)."""
    scores = {
        name: np.array(
            [rmse_deg(run(trial), trial.truth_q, trial.movement)[metric] for trial in trials]
        )
        for name, run in filters.items()
    }
    return InclinationScores(tuple(trial.name for trial in trials), scores)
