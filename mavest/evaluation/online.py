"""Scoring a running estimate against a reference that arrives as messages.

The autopilot's ATTITUDE and a simulator's SIMSTATE come at their own times
and rates, seldom at an IMU sample's time. Each reference is compared with our
estimate interpolated to its time (the two estimates around it), so a 10 Hz
ATTITUDE against a 1 kHz estimate and a 2 Hz one against a 2 Hz estimate are
both scored fairly. Memory is constant: only running sums are kept.

The comparison is compiled: the service feeds it one estimate at a time, the
replay's fast path whole runs of estimates and references at once
(:meth:`EulerComparison.add_many`), through the same code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavest._jit import inplace_kernel, kernel, without_dispatch

Euler = tuple[float, float, float]

ESTIMATE = 0  # kinds of item in EulerComparison.add_many
REFERENCE = 1
_MAX_PENDING = 64  # references waiting for a later estimate (the estimate stalled beyond)


@kernel
def wrap_angle(angle: float) -> float:
    """An angle in [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@kernel
def inclination_error(roll_a: float, pitch_a: float, roll_b: float, pitch_b: float) -> float:
    """Angle (rad) between the vertical as two attitudes see it (ZYX roll and pitch):
    the tilt error. The world's down axis in the body is (−sin θ, sin φ cos θ, cos φ cos θ)."""
    cpa = math.cos(pitch_a)
    cpb = math.cos(pitch_b)
    dot = (
        math.sin(pitch_a) * math.sin(pitch_b)
        + math.sin(roll_a) * cpa * (math.sin(roll_b) * cpb)
        + math.cos(roll_a) * cpa * (math.cos(roll_b) * cpb)
    )
    return math.acos(max(-1.0, min(1.0, dot)))


@dataclass
class ComparisonResult:
    count: int
    roll_rms: float  # deg
    pitch_rms: float
    inclination_rms: float
    yaw_rms: float  # deg; with no heading reference (6-D) this measures drift

    def describe(self, heading_referenced: bool = False) -> str:
        """One line; ``heading_referenced``: the estimate had a magnetometer (9-D)."""
        if self.count == 0:
            return "no overlap"
        yaw = "RMS" if heading_referenced else "(6-D: no heading reference, this is drift)"
        return (
            f"roll {self.roll_rms:.2f}°, pitch {self.pitch_rms:.2f}°, "
            f"tilt {self.inclination_rms:.2f}° RMS (n={self.count}); "
            f"yaw {self.yaw_rms:.1f}° {yaw}"
        )


def _state_dtype(history: int) -> np.dtype:
    """One comparison's state: our recent estimates (a ring), the references waiting
    for a later estimate (a ring), and the running sums."""
    return np.dtype(
        [
            ("ours_t", np.float64, (history,)),
            ("ours_e", np.float64, (history, 3)),
            ("ours_first", np.int64),
            ("ours_len", np.int64),
            ("pending_t", np.float64, (_MAX_PENDING,)),
            ("pending_e", np.float64, (_MAX_PENDING, 3)),
            ("pending_first", np.int64),
            ("pending_len", np.int64),
            ("started", np.int64),
            ("start", np.float64),
            ("sums", np.float64, (4,)),
            ("count", np.int64),
            ("unmatched", np.int64),
            ("references", np.int64),  # every reference taken, scored or not
            ("settle_time", np.float64),
            ("max_span", np.float64),
        ]
    )


@kernel
def _resolve(s: np.void, t: float, r0: float, r1: float, r2: float) -> None:
    """Score one reference against our estimate interpolated to its time."""
    history = s.ours_t.shape[0]
    n = s.ours_len
    first = s.ours_first
    if s.started == 0 or n == 0 or t < s.ours_t[first]:
        s.unmatched += 1
        return
    # the two estimates around t, searching from the newest (references are recent)
    index = n - 1
    while index > 0 and s.ours_t[(first + index - 1) % history] >= t:
        index -= 1
    i1 = (first + index) % history
    t1 = s.ours_t[i1]
    e1 = s.ours_e[i1]
    if index == 0 or t1 == t:
        x, y, z = e1[0], e1[1], e1[2]
    else:
        i0 = (first + index - 1) % history
        t0 = s.ours_t[i0]
        e0 = s.ours_e[i0]
        if t1 - t0 > s.max_span:
            s.unmatched += 1
            return
        w = (t - t0) / (t1 - t0)
        x = e0[0] + w * wrap_angle(e1[0] - e0[0])
        y = e0[1] + w * (e1[1] - e0[1])
        z = e0[2] + w * wrap_angle(e1[2] - e0[2])
    if x != x or y != y or z != z:  # beside an estimate that is none (NaN: no attitude)
        s.unmatched += 1
        return
    if t - s.start < s.settle_time:
        return
    s.sums[0] += wrap_angle(x - r0) ** 2
    s.sums[1] += (y - r1) ** 2
    s.sums[2] += inclination_error(x, y, r0, r1) ** 2
    s.sums[3] += wrap_angle(z - r2) ** 2
    s.count += 1


@kernel
def _add(s: np.void, kind: int, t: float, e0: float, e1: float, e2: float) -> None:
    history = s.ours_t.shape[0]
    if kind != ESTIMATE:
        s.references += 1
    if kind == ESTIMATE:
        if s.started == 0 and e0 == e0:  # (the settling starts at the first attitude)
            s.start = t
            s.started = 1
        if s.ours_len > 0 and t <= s.ours_t[(s.ours_first + s.ours_len - 1) % history]:
            return
        if s.ours_len == history:  # the oldest gives way
            s.ours_first = (s.ours_first + 1) % history
            s.ours_len -= 1
        i = (s.ours_first + s.ours_len) % history
        s.ours_t[i] = t
        s.ours_e[i, 0] = e0
        s.ours_e[i, 1] = e1
        s.ours_e[i, 2] = e2
        s.ours_len += 1
        while s.pending_len > 0 and s.pending_t[s.pending_first] <= t:
            p = s.pending_first
            s.pending_first = (p + 1) % _MAX_PENDING
            s.pending_len -= 1
            _resolve(s, s.pending_t[p], s.pending_e[p, 0], s.pending_e[p, 1], s.pending_e[p, 2])
        return
    if s.ours_len > 0 and t <= s.ours_t[(s.ours_first + s.ours_len - 1) % history]:
        _resolve(s, t, e0, e1, e2)
        return
    if s.pending_len == _MAX_PENDING:  # the estimate stalled: keep memory bounded
        s.pending_first = (s.pending_first + 1) % _MAX_PENDING
        s.pending_len -= 1
        s.unmatched += 1
    i = (s.pending_first + s.pending_len) % _MAX_PENDING
    s.pending_t[i] = t
    s.pending_e[i, 0] = e0
    s.pending_e[i, 1] = e1
    s.pending_e[i, 2] = e2
    s.pending_len += 1


@inplace_kernel
def _add_one(state: np.ndarray, kind: int, t: float, e0: float, e1: float, e2: float) -> None:
    _add(state[0], kind, t, e0, e1, e2)


@inplace_kernel
def _add_many(state: np.ndarray, kinds: np.ndarray, t: np.ndarray, euler: np.ndarray) -> None:
    s = state[0]
    for i in range(kinds.shape[0]):
        _add(s, kinds[i], t[i], euler[i, 0], euler[i, 1], euler[i, 2])


class EulerComparison:
    """RMS differences between our ZYX angles and a reference's, after ``settle_time``."""

    def __init__(self, settle_time: float = 10.0, history: int = 1024, max_span: float = 2.0):
        self.settle_time = settle_time
        self.max_span = max_span  # s: references between estimates further apart are skipped
        state = np.zeros(1, dtype=_state_dtype(history))
        state["settle_time"] = settle_time
        state["max_span"] = max_span
        self._state = state
        # one call costs less than numba's dispatch on the state record: skip it
        self._add_one = without_dispatch(_add_one, state.copy(), ESTIMATE, 0.0, 0.0, 0.0, 0.0)

    @property
    def count(self) -> int:
        return int(self._state["count"][0])

    @property
    def unmatched(self) -> int:
        return int(self._state["unmatched"][0])

    @property
    def references(self) -> int:
        """References taken, scored or not (before the settle time, or matching none)."""
        return int(self._state["references"][0])

    def restart(self) -> None:
        """The estimate started again (a reboot): settle again, forget the old timeline."""
        state = self._state
        state["ours_len"] = 0
        state["pending_len"] = 0
        state["started"] = 0

    def add_estimate(self, t: float, euler: Euler) -> None:
        self._add_one(self._state, ESTIMATE, t, euler[0], euler[1], euler[2])

    def add_reference(self, t: float, euler: Euler) -> None:
        self._add_one(self._state, REFERENCE, t, euler[0], euler[1], euler[2])

    def add_many(self, kinds: np.ndarray, t: np.ndarray, euler: np.ndarray) -> None:
        """Estimates and references in the order they came: ``kinds`` (int64) says
        which each row is (ESTIMATE or REFERENCE); the same as one call per row."""
        _add_many(self._state, kinds, t, euler)

    def result(self) -> ComparisonResult:
        n = max(self.count, 1)
        rms = [math.degrees(math.sqrt(float(s) / n)) for s in self._state["sums"][0]]
        return ComparisonResult(self.count, *rms)
