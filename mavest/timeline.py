"""When a timestamp far off a stream's timeline is believed.

A sample stamped far from where its stream's time stands (back by more than a late
packet would be, or forward by more than any gap a stream has) is one of two
things: a single corrupted timestamp, or the start of a new timeline (a reboot, a
clock set anew). They are told apart by what follows: a new timeline continues,
each sample a little after the one before; a corrupted stamp is followed by
samples on the old timeline. So a far-off timestamp is believed once ``CONFIRM``
samples in a row, itself the first, continue from it; until then it is dropped.

The service's :class:`~mavest.mavlink.clock.StreamClock` (integer ticks, wraps
undone) and the estimator's own step (seconds) both decide so, with these
functions: plain Python for the clock, compiled for the step.
"""

from __future__ import annotations

from mavest._jit import inplace_exact_kernel

REORDER_WINDOW = 0.5  # s back that is a late sample, not a new timeline
MAX_JUMP = 60.0  # s forward beyond which a step needs confirming
MAX_STEP = 10.0  # s: a new timeline's samples each follow the one before within this
CONFIRM = 3  # samples in a row on a new timeline that confirm it, its first included


def far_off(dt: float, reorder_window: float, max_jump: float) -> bool:
    """Whether a sample ``dt`` seconds after the timeline's last is far off it (an
    infinite ``dt`` is; NaN is not: it is no time at all)."""
    return dt > max_jump or dt < -reorder_window


def confirmations(count: int, step: float, max_step: float) -> int:
    """Samples in a row on a new timeline after one more far-off sample: ``count + 1``
    when it continues the ``count`` before it (``step`` seconds after the last of
    them, in (0, max_step]), else 1: it starts a new timeline of its own."""
    return count + 1 if count > 0 and 0.0 < step <= max_step else 1


# The same, for compiled callers.
far_off_kernel = inplace_exact_kernel(far_off)
confirmations_kernel = inplace_exact_kernel(confirmations)
