"""Logged samples made fit to estimate from: finite, in strict time order (both readers)."""

from __future__ import annotations

import numpy as np

from mavest._jit import inplace_kernel
from mavest.onboard.model import Series


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

    Logs occasionally repeat or reorder a sample, and a damaged record can carry a time
    far ahead; the estimator needs strictly increasing time, so such samples are dropped
    (and counted by the caller) rather than sorted in. Keeping the longest increasing
    run of times, rather than every sample later than all before it, means one time
    thrown far ahead costs that sample only, not the rest of the log. Of equal choices
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


class Timeline:
    """Makes :class:`Series` of one log's samples, counting what it drops: samples with a
    value that is not finite (a damaged record: ``unreadable``) and samples whose time
    does not increase (``dropped``)."""

    def __init__(self) -> None:
        self.unreadable = 0
        self.dropped = 0

    def series(self, t_us: np.ndarray, values: np.ndarray) -> Series:
        finite = np.all(np.isfinite(values), axis=1)
        self.unreadable += int(finite.size - np.count_nonzero(finite))
        t_us, values = t_us[finite], values[finite]
        keep = increasing(t_us)
        self.dropped += int(keep.size - np.count_nonzero(keep))
        return Series(np.ascontiguousarray(t_us[keep]), np.ascontiguousarray(values[keep]))

    def notes(self) -> list[str]:
        """What was dropped, one line each (none if nothing)."""
        notes = []
        if self.unreadable:
            notes.append(f"dropped {self.unreadable} samples with values that are not numbers")
        if self.dropped:
            notes.append(f"dropped {self.dropped} samples whose time did not increase")
        return notes
