"""Logged samples made fit to estimate from: finite, on a timeline, in strict time order
(both readers).

A series is one sensor's samples in the order the log holds them. Its times are taken
as :mod:`mavest.timeline` takes a live stream's: a time far off the timeline is one
corrupted stamp, skipped, unless ``timeline.CONFIRM`` samples in a row continue from it;
then it is believed, and a clock that went back and stayed starts a new timeline (a
restart: the samples before and after are all kept, each part in its own time order).
Within a timeline, a sample repeated or a little late (within the reorder window) is
dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from mavest import timeline
from mavest._jit import inplace_kernel
from mavest.onboard.errors import FieldError
from mavest.onboard.model import Series
from mavest.timeline import confirmations_kernel, far_off_kernel

#: The latest boot time believed, µs (about 285 years): a larger one is no time at all,
#: and below it times stay exact as float64 and far from int64's end once a record's
#: Unix time is added.
MAX_BOOT_US = 2**53
#: The time given to a sample whose logged time is not a boot time (see :func:`boot_times`).
NO_TIME = -1


def boot_times(raw: np.ndarray, scale: int = 1) -> np.ndarray:
    """A numeric time column (µs since boot once multiplied by ``scale``) as int64; a
    value that is no boot time (not finite, negative, beyond :data:`MAX_BOOT_US`: an
    unsigned 64-bit stamp with its top bit set would otherwise wrap to a negative one) is
    :data:`NO_TIME`, and is skipped as a time far off the timeline."""
    raw = np.asarray(raw)
    limit = MAX_BOOT_US // scale
    if raw.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            usable = np.isfinite(raw) & (raw >= 0) & (raw <= limit)
    elif raw.dtype.kind == "u":
        usable = raw <= limit
    else:
        usable = (raw >= 0) & (raw <= limit)
    out = np.full(raw.shape, NO_TIME, dtype=np.int64)
    out[usable] = raw[usable].astype(np.int64) * scale
    return out


@inplace_kernel
def _timelines(
    t: np.ndarray,
    label: np.ndarray,
    stack: np.ndarray,
    confirm: int,
    reorder_window: float,
    max_jump: float,
) -> int:
    """Give each sample of ``t`` (µs) its timeline in ``label`` (0, 1…; -1: skipped, far
    off); returns how many timelines. ``stack`` is scratch of ``t``'s length.

    A run of samples each continuing the one before (0 < step <= ``max_jump``: a series
    is one sensor's samples, some logged slower than a live stream's ``MAX_STEP``; a
    sample repeated or a little late is within the run, not counted) is believed once
    ``confirm`` long; the first timeline too, so that a wild first time is
    skipped as a wild later one is. A believed run far back starts a new timeline, unless
    fewer than ``confirm`` samples of the current one stand after its start and it goes
    on from the one before them: then those were stamps thrown ahead, and are skipped.
    A series in which no run is believed keeps its longest (the first of equals).
    """
    n = t.shape[0]
    current = -1  # the timeline being followed (-1: none yet)
    latest = 0  # its latest time
    depth = 0  # stack[:depth]: its samples, in order
    start, end, count, last = 0, 0, 0, 0  # the run of far-off samples in a row
    best_start, best_end, best_count = 0, 0, 0  # before any timeline: the longest run
    for i in range(n):
        ti = t[i]
        label[i] = -1
        if current >= 0 and not far_off_kernel((ti - latest) * 1e-6, reorder_window, max_jump):
            label[i] = current
            stack[depth] = i
            depth += 1
            latest = max(latest, ti)
            count = 0  # the far-off ones before it were corrupted stamps
            continue
        step = (ti - last) * 1e-6
        if count > 0 and not step > 0.0 and not far_off_kernel(step, reorder_window, max_jump):
            end = i  # repeated or a little late: within the run, dropped with its repeats
            continue
        following = confirmations_kernel(count, step, max_jump)
        if following == 1:
            if current < 0 and count > best_count:
                best_start, best_end, best_count = start, end, count
            start = i
        count, last, end = following, ti, i
        if count < confirm:
            continue
        if current < 0:
            current = 0
        elif t[start] < latest:
            first = t[start]
            ahead = 0
            while ahead < depth and ahead < confirm and t[stack[depth - 1 - ahead]] >= first:
                ahead += 1
            before = depth - 1 - ahead
            if (
                ahead < confirm
                and before >= 0
                and not far_off_kernel((first - t[stack[before]]) * 1e-6, reorder_window, max_jump)
            ):
                for k in range(ahead):
                    label[stack[depth - 1 - k]] = -1
                depth -= ahead
            else:
                current += 1
                depth = 0
        for k in range(start, i + 1):
            label[k] = current
            stack[depth] = k
            depth += 1
        latest = ti
        count = 0
    if current >= 0:
        return current + 1
    if count > best_count:
        best_start, best_end, best_count = start, end, count
    for k in range(best_start, best_end + 1 if best_count > 0 else best_start):
        label[k] = 0
    return 1 if best_count > 0 else 0


@inplace_kernel
def _longest_rising(values: np.ndarray, tails: np.ndarray, previous: np.ndarray) -> int:
    """The longest strictly rising subsequence of ``values`` (patience sorting): returns
    the index of its last element; ``previous`` links each element to the one before it
    (-1: none). ``tails`` is scratch of the same length."""
    length = 0
    for i in range(values.shape[0]):
        low, high = 0, length
        while low < high:
            middle = (low + high) // 2
            if values[tails[middle]] < values[i]:
                low = middle + 1
            else:
                high = middle
        previous[i] = tails[low - 1] if low > 0 else -1
        tails[low] = i
        if low == length:
            length += 1
    return tails[length - 1] if length else -1


def increasing(t: np.ndarray) -> np.ndarray:
    """Mask of the most samples that can be kept with time strictly increasing.

    Logs occasionally repeat or reorder a sample; the estimator needs strictly increasing
    time, so such samples are dropped (and counted by the caller) rather than sorted in.
    Keeping the longest increasing run of times, rather than every sample later than all
    before it, means one time a little ahead costs that sample only. Of equal choices
    the earlier sample is kept (a repeated time keeps its first sample).
    """
    keep = np.zeros(t.size, dtype=bool)
    if t.size == 0:
        return keep
    if np.all(t[1:] > t[:-1]):  # the usual case, at no cost
        keep[:] = True
        return keep
    # Reversed and negated, so that of equal choices the earliest sample is kept.
    backwards = -np.ascontiguousarray(t[::-1], dtype=np.float64)
    previous = np.empty(t.size, dtype=np.int64)
    k = _longest_rising(backwards, np.empty(t.size, dtype=np.int64), previous)
    while k >= 0:
        keep[t.size - 1 - k] = True
        k = previous[k]
    return keep


def timelines(t: np.ndarray) -> np.ndarray:
    """Each sample's timeline (0, 1…), -1 for one skipped as far off (see the module's
    docstring); ``t`` in µs, :data:`NO_TIME` where the log's time was no time."""
    label = np.full(t.size, -1, dtype=np.int64)
    known = np.flatnonzero(t != NO_TIME)
    if known.size == 0:
        return label
    times = np.ascontiguousarray(t[known], dtype=np.int64)
    steps = np.diff(times)
    if np.all((steps > 0) & (steps <= timeline.MAX_JUMP * 1e6)):  # the usual case
        label[known] = 0
        return label
    found = np.empty(times.size, dtype=np.int64)
    _timelines(
        times,
        found,
        np.empty(times.size, dtype=np.int64),
        timeline.CONFIRM,
        timeline.REORDER_WINDOW,
        timeline.MAX_JUMP,
    )
    label[known] = found
    return label


class Timeline:
    """Makes :class:`Series` of one log's samples, counting what it drops: samples with a
    value that is not finite (a damaged record: ``unreadable``), samples whose time is
    far off the timeline (``off_timeline``), samples whose time does not increase
    (``dropped``), and the most times a series' clock went back and stayed
    (``restarts``)."""

    def __init__(self) -> None:
        self.unreadable = 0
        self.off_timeline = 0
        self.dropped = 0
        self.restarts = 0

    def series(self, t_us: np.ndarray, values: np.ndarray) -> Series:
        finite = np.all(np.isfinite(values), axis=1)
        self.unreadable += int(finite.size - np.count_nonzero(finite))
        t_us, values = t_us[finite], values[finite]
        label = timelines(t_us)
        on = label >= 0
        self.off_timeline += int(on.size - np.count_nonzero(on))
        if np.all(label == 0):  # the usual case: one timeline, nothing skipped
            keep = increasing(t_us)
        else:
            keep = np.zeros(t_us.size, dtype=bool)
            for number in range(int(label.max()) + 1):
                part = np.flatnonzero(label == number)
                keep[part[increasing(t_us[part])]] = True
        self.dropped += int(np.count_nonzero(on) - np.count_nonzero(keep))
        kept = label[keep]
        restarts = np.flatnonzero(kept[1:] != kept[:-1]) + 1
        self.restarts = max(self.restarts, len(restarts))  # (each series sees the same clock)
        return Series(
            np.ascontiguousarray(t_us[keep]),
            np.ascontiguousarray(values[keep]),
            restarts.astype(np.int64),
        )

    def notes(self) -> list[str]:
        """What was dropped or found, one line each (none if nothing)."""
        notes = []
        if self.unreadable:
            notes.append(f"dropped {self.unreadable} samples with values that are not numbers")
        if self.off_timeline:
            notes.append(f"skipped {self.off_timeline} samples whose time was far off the timeline")
        if self.dropped:
            notes.append(f"dropped {self.dropped} samples whose time did not increase")
        if self.restarts:
            notes.append(
                f"the clock went back and stayed ({self.restarts}×): "
                "each a new timeline, its samples kept"
            )
        return notes


_T = TypeVar("_T")


class Collector:
    """What a reader gathers from one log: its series (through one :class:`Timeline`)
    and its notes, one line each."""

    def __init__(self, notes: list[str] | None = None) -> None:
        self.timeline = Timeline()
        self.notes: list[str] = list(notes or ())

    def series(self, t_us: np.ndarray, values: np.ndarray) -> Series:
        return self.timeline.series(t_us, values)

    def attempt(self, read: Callable[..., _T], *args: Any, part: str = "") -> _T | None:
        """``read(*args)``; None, with a note, if a field it reads is missing or not a
        number (:class:`FieldError`): the one rule for what a damaged or odd format
        costs. ``part``: what is left out, when not all the message type or topic."""
        try:
            return read(*args)
        except FieldError as error:
            self.notes.append(f"{error}: {part + ' ' if part else ''}left out")
            return None

    def final_notes(self) -> tuple[str, ...]:
        """The notes, the timeline's last, each said once."""
        return tuple(dict.fromkeys(self.notes + self.timeline.notes()))
