"""Scoring a running estimate against a reference that arrives as messages.

The autopilot's ATTITUDE and a simulator's SIMSTATE come at their own times
and rates, seldom at an IMU sample's time. Each reference is compared with our
estimate interpolated to its time (the two estimates around it), so a 10 Hz
ATTITUDE against a 1 kHz estimate and a 2 Hz one against a 2 Hz estimate are
both scored fairly. Memory is constant: only running sums are kept.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

Euler = tuple[float, float, float]


def wrap_angle(angle: float) -> float:
    """An angle in [−π, π) (plain floats: this runs per message)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _gravity_in_body(euler: Euler) -> tuple[float, float, float]:
    """Unit vector of the world's down axis in the body frame, from ZYX angles."""
    roll, pitch = euler[0], euler[1]
    cp = math.cos(pitch)
    return (-math.sin(pitch), math.sin(roll) * cp, math.cos(roll) * cp)


def inclination_error(a: Euler, b: Euler) -> float:
    """Angle (rad) between the vertical as two attitudes see it: the tilt error."""
    ga, gb = _gravity_in_body(a), _gravity_in_body(b)
    dot = ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]
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


class EulerComparison:
    """RMS differences between our ZYX angles and a reference's, after ``settle_time``."""

    def __init__(self, settle_time: float = 10.0, history: int = 1024, max_span: float = 2.0):
        self.settle_time = settle_time
        self.max_span = max_span  # s: references between estimates further apart are skipped
        self._ours: deque[tuple[float, Euler]] = deque(maxlen=history)
        self._pending: deque[tuple[float, Euler]] = deque()
        self._start: float | None = None
        self._sums = [0.0, 0.0, 0.0, 0.0]
        self.count = 0
        self.unmatched = 0

    def restart(self) -> None:
        """The estimate started again (a reboot): settle again, forget the old timeline."""
        self._ours.clear()
        self._pending.clear()
        self._start = None

    def add_estimate(self, t: float, euler: Euler) -> None:
        if self._start is None:
            self._start = t
        ours = self._ours
        if ours and t <= ours[-1][0]:
            return
        ours.append((t, euler))
        pending = self._pending
        while pending and pending[0][0] <= t:
            self._resolve(*pending.popleft())

    def add_reference(self, t: float, euler: Euler) -> None:
        if self._ours and t <= self._ours[-1][0]:
            self._resolve(t, euler)
        else:
            self._pending.append((t, euler))
            while len(self._pending) > 64:  # the estimate stalled: keep memory bounded
                self._pending.popleft()
                self.unmatched += 1

    def _resolve(self, t: float, reference: Euler) -> None:
        ours = self._ours
        if self._start is None or not ours or t < ours[0][0]:
            self.unmatched += 1
            return
        # the two estimates around t, searching from the newest (references are recent)
        index = len(ours) - 1
        while index > 0 and ours[index - 1][0] >= t:
            index -= 1
        t1, e1 = ours[index]
        if index == 0 or t1 == t:
            estimate = e1
        else:
            t0, e0 = ours[index - 1]
            if t1 - t0 > self.max_span:
                self.unmatched += 1
                return
            w = (t - t0) / (t1 - t0)
            estimate = (
                e0[0] + w * wrap_angle(e1[0] - e0[0]),
                e0[1] + w * (e1[1] - e0[1]),
                e0[2] + w * wrap_angle(e1[2] - e0[2]),
            )
        if t - self._start < self.settle_time:
            return
        sums = self._sums
        sums[0] += wrap_angle(estimate[0] - reference[0]) ** 2
        sums[1] += (estimate[1] - reference[1]) ** 2
        sums[2] += inclination_error(estimate, reference) ** 2
        sums[3] += wrap_angle(estimate[2] - reference[2]) ** 2
        self.count += 1

    def result(self) -> ComparisonResult:
        n = max(self.count, 1)
        rms = [math.degrees(math.sqrt(s / n)) for s in self._sums]
        return ComparisonResult(self.count, *rms)
