"""Scoring estimates against an attitude logged at other times: an autopilot's own, or a
simulator's truth.

An estimate computed at the IMU sample times is slerped onto the reference's times (the
two neighbouring samples); the reference itself is never interpolated. Every candidate
of one comparison is scored at the same reference times: those all of them cover (an
autopilot's own estimate starts later than its IMU samples). Roll and pitch: RMSE of the
ZYX Euler angle differences, wrapped; inclination: RMSE of the tilt error (BROAD's
scoring, :func:`~mavest.evaluation.metrics.attitude_errors`). Heading is not scored: a
6-D filter has none.

A reference no estimator wrote: :func:`gravity_at_rest`, the gravity direction the
accelerometer itself shows wherever the vehicle lies still (an autopilot's attitude lags
after a crash as any filter's does).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mavest.estimator.config import STANDARD_GRAVITY
from mavest.evaluation.metrics import attitude_errors, wrap_angles
from mavest.so3 import euler_zyx_from_quats, quats_from_euler_zyx

__all__ = ["Score", "Segment", "gravity_at_rest", "score", "score_segments", "slerp_onto"]

#: An estimate: (N,) times in s and (N, 4) quaternions (w, x, y, z), body → NED.
TimedAttitude = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Segment:
    """A stretch of a log, [start, end) in s of the log's time base."""

    label: str
    start: float
    end: float

    def describe(self, last: float) -> str:
        """E.g. ``"crash 200–243 s"``, an open end shown as ``last``."""
        return f"{self.label} {self.start:.0f}–{min(self.end, last):.0f} s"


def slerp_onto(t: np.ndarray, q: np.ndarray, t_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``q`` (w, x, y, z) at times ``t``, slerped onto the ``t_new`` inside [t[0], t[-1]].

    Returns (mask over t_new of the times inside, (M, 4) quaternions at those times).
    """
    inside = (t_new >= t[0]) & (t_new <= t[-1])
    rotations = Slerp(t, Rotation.from_quat(q[:, [1, 2, 3, 0]]))(t_new[inside])
    return inside, rotations.as_quat()[:, [3, 0, 1, 2]]


@dataclass(frozen=True)
class Score:
    """RMSE in degrees of one estimate against one reference over one segment."""

    n: int
    roll: float
    pitch: float
    inclination: float


def score(q_est: np.ndarray, q_ref: np.ndarray) -> Score:
    """Roll, pitch (ZYX Euler differences, wrapped) and inclination RMSE, degrees."""
    if len(q_ref) == 0:
        return Score(0, np.nan, np.nan, np.nan)
    euler_error = wrap_angles(euler_zyx_from_quats(q_est) - euler_zyx_from_quats(q_ref))
    inclination = attitude_errors(q_est, q_ref).inclination

    def rms_deg(x: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(np.square(x)))))

    return Score(
        len(q_ref), rms_deg(euler_error[:, 0]), rms_deg(euler_error[:, 1]), rms_deg(inclination)
    )


def score_segments(
    candidates: dict[str, TimedAttitude],
    reference_t: np.ndarray,
    reference_q: np.ndarray,
    segments: Sequence[Segment],
) -> dict[str, dict[str, Score]]:
    """segment label → candidate name → its score against the reference in that segment.

    Every candidate is slerped onto the reference times all candidates cover, so that
    within a segment all are scored on the same samples.
    """
    common = np.ones(len(reference_t), dtype=bool)
    for t, _ in candidates.values():
        common &= (reference_t >= t[0]) & (reference_t <= t[-1])
    times = reference_t[common]
    q_ref = reference_q[common]
    at_reference = {name: slerp_onto(t, q, times)[1] for name, (t, q) in candidates.items()}
    scores: dict[str, dict[str, Score]] = {}
    for segment in segments:
        chosen = (times >= segment.start) & (times < segment.end)
        scores[segment.label] = {
            name: score(q[chosen], q_ref[chosen]) for name, q in at_reference.items()
        }
    return scores


def gravity_at_rest(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    spans: Sequence[Segment],
    window: float = 1.0,
    max_mean_rate: float = np.radians(2.0),
    max_rate_spread: float = np.radians(5.0),
    max_norm_error: float = 0.6,
) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's gravity direction in the windows where the vehicle lies still.

    Within ``spans``, consecutive ``window``-long stretches of samples count as still
    when their mean rate is under ``max_mean_rate`` (the attitude does not change
    over the window), the rate's spread under ``max_rate_spread`` (no flight: a
    hovering multicopter's accelerometer reads "level" whatever its tilt, but its
    motors shake the gyro), and the mean specific force is within ``max_norm_error``
    of g (a still accelerometer's own scale and bias errors: log171's reads 9.59 m/s²
    right way up, 10.05 inverted). There the mean specific force is −g along the
    world vertical. (A steady acceleration without rotation shows only in the
    norm: under ~3.5 m/s² it would pass, hence ``spans``, the stretches the
    vehicle is known to lie in.)

    Returns the windows' mid times (W,) and attitudes (W, 4) (w, x, y, z), body → NED,
    heading 0: only roll, pitch and inclination may be scored against them (ZYX roll
    and pitch do not depend on heading).
    """
    times: list[float] = []
    down: list[np.ndarray] = []
    for span in spans:
        start = max(span.start, float(t[0]))
        while start + window <= min(span.end, float(t[-1])):
            inside = slice(*np.searchsorted(t, [start, start + window]))
            start += window
            if inside.stop - inside.start < 2:
                continue
            rate = gyro[inside]
            force = accel[inside].mean(axis=0)
            norm = float(np.linalg.norm(force))
            if (
                np.linalg.norm(rate.mean(axis=0)) < max_mean_rate
                and np.linalg.norm(rate.std(axis=0)) < max_rate_spread
                and abs(norm - STANDARD_GRAVITY) < max_norm_error
            ):
                times.append(float(t[inside].mean()))
                down.append(-force / norm)
    if not times:
        return np.empty(0), np.empty((0, 4))
    d = np.array(down)  # world down in the body: (−sin θ, cos θ sin φ, cos θ cos φ)
    roll = np.arctan2(d[:, 1], d[:, 2])
    pitch = -np.arcsin(np.clip(d[:, 0], -1.0, 1.0))
    angles = np.column_stack([roll, pitch, np.zeros_like(roll)])
    return np.array(times), quats_from_euler_zyx(angles)
