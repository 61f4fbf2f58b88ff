"""Whether a recording's gyroscope is in rad/s, as seen by its own accelerometer.

An accelerometer at rest or in slow motion measures gravity, and the direction it
measures it in turns as the body tilts: over a short window, by the angle the gyro's
rates turn it, the part of the integrated rate that is not about gravity itself
(d a/dt = −ω × a for a gravity vector fixed in the world). A gyro in another unit
turns it by that unit's factor more (°/s: 57.3×, mrad/s: 1000×) while the
accelerometer shows the true angle; the filter then rejects nearly every
accelerometer sample and its estimate is meaningless, with no flag to say so. The
ratio of the two angles over the windows where the accelerometer turned clearly
tells the unit. It is robust to linear acceleration and vibration, which add to the
accelerometer's angle and so can only lower the ratio; a ratio near 57 or 1000 is not
something a gyro in rad/s gives.

The accelerometer's own unit is judged by the filter's first samples
(``StepFlags.ACCEL_WRONG_UNIT``); this is judged on a batch's samples as a whole, by
:func:`mavest.estimate` and :func:`mavest.smooth` before they run.
"""

from __future__ import annotations

import math

import numpy as np

#: The window over which the two turns are compared: long enough for a tilt to show
#: above the accelerometer's noise, short enough that the rates add up as a rotation.
WINDOW = 0.25  # s
#: Where too few windows of :data:`WINDOW` tilt enough (a vehicle that tilts slowly:
#: a simulated flight banking ±30° over seconds had 1–13), windows this long are
#: compared instead: the rates of a slow tilt still add up as its rotation.
LONG_WINDOW = 1.0  # s
#: Each end of a window is the accelerometer averaged over this many samples.
END_SAMPLES = 5
#: A window counts when the accelerometer turned by at least this and both ends are
#: within :data:`NORM_TOLERANCE` of g (gravity, not a push).
MIN_TURN = math.radians(5.0)
NORM_TOLERANCE = 0.1  # of g
#: The windows needed for a verdict, and the most looked at (the rest is not needed).
MIN_WINDOWS = 20
MAX_WINDOWS = 2000
#: A median ratio beyond this is not a gyro in rad/s (BROAD's 22 shared trials: medians
#: 0.15–0.93, 95th percentiles up to 2.2; the same in °/s: 8.5–53).
WRONG_RATIO = 5.0
#: Units a gyro is often in, with their factor to rad/s's reading.
UNITS = (("°/s", 180.0 / math.pi), ("mrad/s", 1000.0), ("centi-°/s", 18000.0 / math.pi))


def turn_ratios(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    gravity: float,
    max_dt: float,
    window: float = WINDOW,
) -> np.ndarray:
    """Per window (non-overlapping, ``window`` long, its span that of as many
    regular steps to within 10 %: no gap, no jump of the clock in it), the angle the gyro
    turns gravity by over the accelerometer's, for the windows whose accelerometer turned
    by :data:`MIN_TURN` or more near g; at most :data:`MAX_WINDOWS` of them, from the
    start. Vectorised a chunk of windows at a time, each window's rates summed once:
    about ten nanoseconds a sample, and nothing of the recording's length held."""
    n = t.shape[0]
    steps = np.diff(t[: min(n, 1 << 16)])
    steps = steps[np.isfinite(steps) & (steps > 0.0)]
    if steps.shape[0] == 0:
        return np.empty(0)
    step = float(np.median(steps))
    if step > max_dt:  # (no two samples joined: nothing turns within a window)
        return np.empty(0)
    if window / step > n:  # not one window (and a subnormal step's window is infinite)
        return np.empty(0)
    length = max(2 * END_SAMPLES + 1, round(window / step))
    windows = n // length
    per_chunk = max(1, (1 << 16) // length)
    half = END_SAMPLES // 2
    span = slice(half + 1, length - half)  # sample j's rate covers the step into it
    found: list[np.ndarray] = []
    count = 0
    for first in range(0, windows, per_chunk):
        k = min(per_chunk, windows - first)
        rows = slice(first * length, (first + k) * length)
        wt = t[rows].reshape(k, length)
        wa = accel[rows].reshape(k, length, 3)
        with np.errstate(invalid="ignore"):
            ok = np.abs(wt[:, -1] - wt[:, 0] - (length - 1) * step) <= 0.1 * (length - 1) * step
        # (absurd values overflow to inf here, and the norm's check leaves their windows out)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            ends = np.stack([wa[:, :END_SAMPLES].mean(axis=1), wa[:, -END_SAMPLES:].mean(axis=1)])
            norms = np.linalg.norm(ends, axis=2)
            ok &= np.all(np.abs(norms - gravity) <= NORM_TOLERANCE * gravity, axis=0)
            u, v = ends[0] / norms[0, :, None], ends[1] / norms[1, :, None]
            measured = np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.sum(u * v, axis=1))
            ok &= measured >= MIN_TURN
            # the rates from one end's middle to the other's, a regular step each; about
            # gravity they turn nothing it measures
            starts = np.arange(k) * length
            bounds = np.stack([starts + span.start, starts + span.stop], axis=1).ravel()
            phi = np.add.reduceat(gyro[rows], bounds, axis=0)[0::2] * step
            turned = np.linalg.norm(phi - np.sum(phi * u, axis=1)[:, None] * u, axis=1)
            ratio = turned / measured
        ok &= np.isfinite(ratio)  # (a sample not finite in the sum or at the ends)
        found.append(ratio[ok])
        count += int(ok.sum())
        if count >= MAX_WINDOWS:
            break
    ratios = np.concatenate(found) if found else np.empty(0)
    return ratios[:MAX_WINDOWS]


def gyro_unit_problem(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, gravity: float, max_dt: float
) -> str | None:
    """One line if the gyroscope turns gravity :data:`WRONG_RATIO` times or more than the
    accelerometer sees it turn, over :data:`MIN_WINDOWS` windows or more (the median
    ratio), naming the unit it is likely in; None otherwise, or without the motion to
    tell (a recording at rest, or turning about the vertical only)."""
    ratios = turn_ratios(t, gyro, accel, gravity, max_dt)
    if ratios.shape[0] < MIN_WINDOWS:
        ratios = turn_ratios(t, gyro, accel, gravity, max_dt, LONG_WINDOW)
    if ratios.shape[0] < MIN_WINDOWS:
        return None
    ratio = float(np.median(ratios))
    if ratio < WRONG_RATIO:
        return None
    # (the accelerometer's own pushes and noise only add to its turn: a unit's factor
    # is at least the ratio seen, to the median's spread)
    fitting = [(unit, factor) for unit, factor in UNITS if factor >= ratio / 1.5]
    likely = f"in {fitting[0][0]}? (× {fitting[0][1]:.4g})" if fitting else "in another unit?"
    return (
        f"the gyro turns gravity {ratio:.0f}× as far as the accelerometer sees it turn "
        f"(median of {ratios.shape[0]} windows): {likely} mavest takes rad/s"
    )
