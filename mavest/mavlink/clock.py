"""A vehicle's clock as one IMU stream shows it: wrap, reboot, gaps, duplicates.

Flight controllers stamp IMU messages with time since boot: ``time_boot_ms``
(uint32, wraps after 49.7 days) or ``time_usec`` (uint64 on the wire, but older
ArduPilot fills it from a 32-bit µs counter that wraps every 71.6 minutes).
A timestamp that goes back is one of three things, told apart by how far:
a wrap (it went back by almost 2³² ticks), a packet out of order (a little),
or a reboot (more than that). A step forward longer than a few sample periods
is a gap; the estimator decides whether to propagate through it or re-align
(its ``max_dt``), the clock only names it.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np

from mavest import timeline
from mavest._jit import inplace_exact_kernel

WRAP_TICKS = 1 << 32


class ClockEvent(enum.Enum):
    FIRST = "first"  # the stream's first sample
    NEXT = "next"  # the usual case
    GAP = "gap"  # later than expected by more than the gap threshold (used)
    WRAPPED = "wrapped"  # the 32-bit counter wrapped (used)
    DUPLICATE = "duplicate"  # same timestamp as the last sample (dropped)
    OUT_OF_ORDER = "out_of_order"  # slightly older than the last sample (dropped)
    OFF_TIMELINE = "off_timeline"  # far from the timeline, not (yet) confirmed (dropped)
    REBOOT = "reboot"  # time went back and stayed back: the vehicle restarted (re-initialise)

    @property
    def used(self) -> bool:
        return self not in (ClockEvent.DUPLICATE, ClockEvent.OUT_OF_ORDER, ClockEvent.OFF_TIMELINE)


class ClockReading(NamedTuple):
    event: ClockEvent
    t: float  # s since the vehicle's boot, wraps undone
    dt: float  # s since the previous used sample (0 for FIRST and REBOOT)


class StreamClock:
    """Turns one stream's raw timestamps into monotonic seconds and names what happened.

    A timestamp far off the timeline (back by more than the reorder window, or
    forward by more than ``max_jump``) is believed only when the next
    ``confirm - 1`` samples continue from it (:mod:`mavest.timeline`, the rule the
    estimator applies too): a reboot or a real jump does that, a single corrupted
    timestamp does not, and is dropped instead of restarting the estimate.
    """

    def __init__(
        self,
        reorder_window: float = timeline.REORDER_WINDOW,
        max_wrap_step: float = timeline.MAX_STEP,
        gap_periods: float = 5.0,
        min_gap: float = 0.05,
        max_jump: float = timeline.MAX_JUMP,
        confirm: int = timeline.CONFIRM,
    ) -> None:
        self.reorder_window = reorder_window  # s back that is a late packet, not a reboot
        # s: a wrap must land within this of the last sample, and a new timeline's
        # samples each within this of the one before
        self.max_wrap_step = max_wrap_step
        self.gap_periods = gap_periods
        self.min_gap = min_gap
        self.max_jump = max_jump  # s forward beyond which a step needs confirming
        self.confirm = confirm
        self._last_ticks: int | None = None
        self._offset = 0  # ticks added by wraps
        self._period = 0.0  # smoothed sample period, s
        self._candidate: int | None = None  # last ticks of an unconfirmed new timeline
        self._candidate_count = 0

    @property
    def pending(self) -> int:
        """Samples so far on an unconfirmed new timeline (0: none)."""
        return self._candidate_count if self._candidate is not None else 0

    def time_of(self, ticks: int, tick: float) -> float:
        """Seconds since boot of a timestamp on the current timeline (wraps undone)."""
        return (ticks + self._offset) * tick

    @property
    def period(self) -> float:
        """The stream's typical sample period (s), 0 until two samples arrived."""
        return self._period

    def _off_timeline(self, ticks: int, tick: float) -> bool:
        """Count a sample towards a new timeline; True once it is confirmed."""
        candidate = self._candidate
        step = 0.0 if candidate is None else (ticks - candidate) * tick
        self._candidate_count = timeline.confirmations(self.pending, step, self.max_wrap_step)
        self._candidate = ticks
        return self._candidate_count >= self.confirm

    def read(self, ticks: int, tick: float) -> ClockReading:
        last = self._last_ticks
        if last is None:
            self._last_ticks = ticks
            return ClockReading(ClockEvent.FIRST, ticks * tick, 0.0)
        delta = ticks - last
        if delta == 0:
            return ClockReading(ClockEvent.DUPLICATE, (ticks + self._offset) * tick, 0.0)
        event = ClockEvent.NEXT
        if delta < 0:
            wrapped = delta + WRAP_TICKS
            if last < WRAP_TICKS and 0 < wrapped * tick <= self.max_wrap_step:
                self._offset += WRAP_TICKS
                delta = wrapped
                event = ClockEvent.WRAPPED
            elif not timeline.far_off(delta * tick, self.reorder_window, self.max_jump):
                return ClockReading(ClockEvent.OUT_OF_ORDER, (ticks + self._offset) * tick, 0.0)
            elif not self._off_timeline(ticks, tick):
                return ClockReading(ClockEvent.OFF_TIMELINE, ticks * tick, 0.0)
            else:
                self._last_ticks = ticks
                self._offset = 0
                self._period = 0.0
                self._candidate = None
                return ClockReading(ClockEvent.REBOOT, ticks * tick, 0.0)
        elif timeline.far_off(
            delta * tick, self.reorder_window, self.max_jump
        ) and not self._off_timeline(ticks, tick):
            return ClockReading(ClockEvent.OFF_TIMELINE, (ticks + self._offset) * tick, 0.0)
        self._candidate = None
        self._last_ticks = ticks
        dt = delta * tick
        threshold = max(self.min_gap, self.gap_periods * self._period)
        if event is ClockEvent.NEXT and self._period > 0.0 and dt > threshold:
            event = ClockEvent.GAP
        else:  # gaps would drag the typical period up; leave them out of it
            self._period = dt if self._period == 0.0 else self._period + 0.05 * (dt - self._period)
        return ClockReading(event, (ticks + self._offset) * tick, dt)

    def read_run(self, ticks: np.ndarray, tick: float) -> np.ndarray:
        """The times of the leading samples that :meth:`read` would call plainly NEXT
        (later than the last, not a gap, no wrap or jump), without moving the clock:
        :meth:`take_run` then takes as many of them as are used. For many samples at
        once (the replay's fast path); the first sample of any other kind is left for
        :meth:`read`.
        """
        if self._last_ticks is None or not ticks.shape[0]:
            return np.empty(0)
        count, times, _ = self._plain_run(ticks, tick)
        return times[:count]

    def take_run(self, ticks: np.ndarray, tick: float, count: int) -> None:
        """Advance the clock over the first ``count`` samples :meth:`read_run` timed."""
        if count == 0:
            return
        _, _, periods = self._plain_run(ticks[:count], tick)
        self._candidate = None
        self._last_ticks = int(ticks[count - 1])
        self._period = float(periods[count - 1])

    def _plain_run(self, ticks: np.ndarray, tick: float) -> tuple[int, np.ndarray, np.ndarray]:
        """(how many lead plainly, their times, the smoothed period after each)."""
        assert self._last_ticks is not None
        times = np.empty(ticks.shape[0])
        periods = np.empty(ticks.shape[0])
        count = _plain_run(
            ticks,
            self._last_ticks,
            self._offset,
            self._period,
            tick,
            self.min_gap,
            self.gap_periods,
            self.max_jump,
            times,
            periods,
        )
        return count, times, periods


# Raw timestamps beyond this are left to the exact integer arithmetic of read().
_RUN_MAX_TICKS = 1 << 62


@inplace_exact_kernel
def _plain_run(
    ticks: np.ndarray,
    last: int,
    offset: int,
    period: float,
    tick: float,
    min_gap: float,
    gap_periods: float,
    max_jump: float,
    times: np.ndarray,
    periods: np.ndarray,
) -> int:
    """StreamClock.read's NEXT branch over many samples; stops at any other event."""
    for i in range(ticks.shape[0]):
        t = ticks[i]
        if t >= _RUN_MAX_TICKS or t < 0:
            return i
        delta = t - last
        if delta <= 0:
            return i
        dt = delta * tick
        if dt > max_jump:
            return i
        if period > 0.0 and dt > max(min_gap, gap_periods * period):
            return i
        period = dt if period == 0.0 else period + 0.05 * (dt - period)
        times[i] = (t + offset) * tick
        periods[i] = period
        last = t
    return ticks.shape[0]
