"""The accelerometer low-passed without lag, for the smoother's forward pass.

A recording can be filtered forward and backward: the specific force's linear
acceleration then averages away with no delay, which a causal low-pass (the filter's
own, :mod:`mavest.estimator.lowpass`) cannot do (Laidig & Seel 2023's offline VQF
averages alike, with a Butterworth filter). The average is taken in the gyro's
strapdown frame, in which gravity holds still while the body turns: each sample's
specific force is turned by the attitude integrated from the gyro alone since its
segment began (no bias, no correction), low-passed there by a first-order exponential
average run backward and then forward over the segment (zero phase, each step's weight
from its own interval: 1 − exp(−Δt/τ)), and turned back into the body frame.

A segment is a run of samples to average whose intervals are in (0, ``max_dt``]: a
gap, a step back in time or a sample not to average ends it (a time, gyro or
accelerometer reading not finite, a gyro axis beyond the filter's clip, whose missed
rotation would turn the frame, an accelerometer axis beyond any sensor's range, which
the average would spread over seconds), and such a sample is passed through as it is
(the filter flags it). The averages start at each end of a segment from its sample
there.

The recording is taken in blocks in time order and nothing of length N is held:
the strapdown attitude at each block's start and the backward average's state at
each block's end are kept (a few numbers a block), and each block is computed again
from them when it is handed out (docs/design.md#smoothing).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from mavest._jit import inplace_kernel


@inplace_kernel
def _valid(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, k: int, limits: np.ndarray) -> bool:
    """Whether sample k is one to average: its time finite, each gyro axis within
    ``limits[1]`` (a clipped gyro missed a rotation) and each accelerometer axis within
    ``limits[2]`` (a reading beyond is a broken sensor or packet, which an average would
    spread over seconds). (NaN fails every comparison.)"""
    gyro_limit, accel_limit = limits[1], limits[2]
    return (
        math.isfinite(t[k])
        and abs(gyro[k, 0]) <= gyro_limit
        and abs(gyro[k, 1]) <= gyro_limit
        and abs(gyro[k, 2]) <= gyro_limit
        and abs(accel[k, 0]) <= accel_limit
        and abs(accel[k, 1]) <= accel_limit
        and abs(accel[k, 2]) <= accel_limit
    )


@inplace_kernel
def _joined(t: np.ndarray, k: int, both_valid: bool, limits: np.ndarray) -> bool:
    """Whether sample k continues sample k − 1's segment (``both_valid``: both are to
    average): its interval in (0, ``limits[0]``]. (NaN fails.)"""
    return both_valid and 0.0 < t[k] - t[k - 1] <= limits[0]


@inplace_kernel
def _rotate(
    w: float, x: float, y: float, z: float, vx: float, vy: float, vz: float, out: np.ndarray, k: int
) -> None:
    """out[k] = R(q) v for the unit quaternion q = (w, x, y, z)."""
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    out[k, 0] = vx + w * tx + (y * tz - z * ty)
    out[k, 1] = vy + w * ty + (z * tx - x * tz)
    out[k, 2] = vz + w * tz + (x * ty - y * tx)


@inplace_kernel
def _strapdown(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    limits: np.ndarray,
    lo: int,
    hi: int,
    q: np.ndarray,
    out: np.ndarray,
) -> None:
    """The strapdown attitude of samples [lo, hi) into the rows of ``out``, from ``q``
    (the attitude before sample lo), which is left at the last one's. A segment's first
    sample is the identity; an invalid sample keeps the attitude before it."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    previous_valid = lo > 0 and _valid(t, gyro, accel, lo - 1, limits)
    for k in range(lo, hi):
        valid = _valid(t, gyro, accel, k, limits)
        if valid:
            if _joined(t, k, previous_valid, limits):
                dt = t[k] - t[k - 1]
                # the step's quaternion exp(½ ω dt), its series exact in double precision
                # below 0.01 rad (1 kHz at 10 rad/s)
                px, py, pz = gyro[k, 0] * dt, gyro[k, 1] * dt, gyro[k, 2] * dt
                angle2 = px * px + py * py + pz * pz
                if angle2 < 1e-4:
                    c = 1.0 - angle2 / 8.0 + angle2 * angle2 / 384.0
                    h = 0.5 - angle2 / 48.0 + angle2 * angle2 / 3840.0
                else:
                    angle = math.sqrt(angle2)
                    c = math.cos(0.5 * angle)
                    h = math.sin(0.5 * angle) / angle
                sx, sy, sz = h * px, h * py, h * pz
                w, x, y, z = (
                    w * c - x * sx - y * sy - z * sz,
                    w * sx + x * c + y * sz - z * sy,
                    w * sy - x * sz + y * c + z * sx,
                    w * sz + x * sy - y * sx + z * c,
                )
                # (a unit step keeps the norm to rounding: renormalised when it strays)
                norm2 = w * w + x * x + y * y + z * z
                if abs(norm2 - 1.0) > 1e-12:
                    norm = 1.0 / math.sqrt(norm2)
                    w, x, y, z = w * norm, x * norm, y * norm, z * norm
            else:
                w, x, y, z = 1.0, 0.0, 0.0, 0.0
        previous_valid = valid
        out[k - lo, 0] = w
        out[k - lo, 1] = x
        out[k - lo, 2] = y
        out[k - lo, 3] = z
    q[0], q[1], q[2], q[3] = w, x, y, z


@inplace_kernel
def _checkpoints(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    limits: np.ndarray,
    block: int,
    rows: np.ndarray,
    out: np.ndarray,
) -> None:
    """The strapdown attitude before each block's first sample (out: blocks × 4; rows:
    block × 4, scratch)."""
    n = t.shape[0]
    q = out[0]
    q[0], q[1], q[2], q[3] = 1.0, 0.0, 0.0, 0.0
    for j in range(out.shape[0] - 1):
        for i in range(4):
            out[j + 1, i] = out[j, i]
        lo = j * block
        _strapdown(t, gyro, accel, limits, lo, min(lo + block, n), out[j + 1], rows)


@inplace_kernel
def _weight(dt: float, time_constant: float, last: np.ndarray) -> float:
    """1 − exp(−Δt/τ), kept in ``last`` (Δt, weight) for the next equal interval."""
    if dt != last[0]:
        last[0] = dt
        last[1] = 1.0 - math.exp(-dt / time_constant)
    return last[1]


@inplace_kernel
def _backward(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    limits: np.ndarray,
    time_constant: float,
    lo: int,
    hi: int,
    attitude: np.ndarray,
    state: np.ndarray,
    out: np.ndarray,
    end: np.ndarray,
    last: np.ndarray,
) -> None:
    """The backward average of samples [lo, hi) in the strapdown frame (``attitude``:
    their rows) into ``out``, and the time of their segment's last sample into ``end``,
    from ``state`` (the average and that time at sample hi), which is left at sample
    lo's."""
    n = t.shape[0]
    next_valid = hi < n and _valid(t, gyro, accel, hi, limits)
    for k in range(hi - 1, lo - 1, -1):
        valid = _valid(t, gyro, accel, k, limits)
        if valid:
            r = k - lo
            _rotate(
                attitude[r, 0], attitude[r, 1], attitude[r, 2], attitude[r, 3],
                accel[k, 0], accel[k, 1], accel[k, 2], out, r,
            )  # fmt: skip
            if next_valid and _joined(t, k + 1, True, limits):
                weight = _weight(t[k + 1] - t[k], time_constant, last)
                for i in range(3):
                    state[i] += weight * (out[r, i] - state[i])
            else:  # the segment's last sample
                for i in range(3):
                    state[i] = out[r, i]
                state[3] = t[k]
            for i in range(3):
                out[r, i] = state[i]
            end[r] = state[3]
        next_valid = valid


@inplace_kernel
def _forward(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    limits: np.ndarray,
    time_constant: float,
    lo: int,
    hi: int,
    attitude: np.ndarray,
    backward: np.ndarray,
    end: np.ndarray,
    taper: float,
    state: np.ndarray,
    out: np.ndarray,
    last: np.ndarray,
) -> None:
    """The forward average of the backward one over samples [lo, hi), from ``state``
    (the average and its segment's first time at sample lo − 1, left at hi − 1's),
    turned back into the body frame into ``out``; invalid samples as they are. Within
    ``taper`` s of the segment's ends (``end``: its last time) the sample as measured
    takes over, linearly: there the average would be one-sided, so lag or lead."""
    previous_valid = lo > 0 and _valid(t, gyro, accel, lo - 1, limits)
    for k in range(lo, hi):
        valid = _valid(t, gyro, accel, k, limits)
        r = k - lo
        if not valid:
            for i in range(3):
                out[r, i] = accel[k, i]
            previous_valid = False
            continue
        if _joined(t, k, previous_valid, limits):
            weight = _weight(t[k] - t[k - 1], time_constant, last)
            for i in range(3):
                state[i] += weight * (backward[r, i] - state[i])
        else:  # the segment's first sample
            for i in range(3):
                state[i] = backward[r, i]
            state[3] = t[k]
        previous_valid = True
        # turned back: by the conjugate of the sample's attitude
        _rotate(
            attitude[r, 0], -attitude[r, 1], -attitude[r, 2], -attitude[r, 3],
            state[0], state[1], state[2], out, r,
        )  # fmt: skip
        inside = min(t[k] - state[3], end[r] - t[k])
        if inside < taper:
            share = inside / taper
            for i in range(3):
                out[r, i] = share * out[r, i] + (1.0 - share) * accel[k, i]


def zero_phase_blocks(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    time_constant: float,
    max_dt: float,
    block: int,
    taper: float = 0.0,
    gyro_limit: float = math.inf,
    accel_limit: float = math.inf,
) -> Iterator[np.ndarray]:
    """The accelerometer low-passed with zero phase (time constant ``time_constant`` s;
    segments split at intervals beyond ``max_dt`` and at samples not to average: not
    finite, or a gyro axis beyond ``gyro_limit`` or an accelerometer axis beyond
    ``accel_limit``), as (≤ block, 3) arrays of samples [0, block), [block, 2·block), …
    in turn. ``t`` (N,), ``gyro`` and ``accel`` (N, 3) float64 arrays, the inputs
    :func:`~mavest.estimator.estimate` takes; ``taper``: see :func:`_forward`."""
    limits = np.array([max_dt, gyro_limit, accel_limit])
    n = t.shape[0]
    blocks = -(-n // block)
    attitude = np.empty((block, 4))
    starts = np.empty((max(blocks, 1), 4))
    _checkpoints(t, gyro, accel, limits, block, attitude, starts)
    # the backward average and its segment's last time at each block's end (at the
    # next block's first sample)
    ends = np.zeros((blocks + 1, 4))
    averaged = np.empty((block, 3))
    end = np.empty(block)
    last = np.zeros(2)  # the last interval and its weight
    state = np.zeros(4)
    for j in range(blocks - 1, -1, -1):
        lo, hi = j * block, min((j + 1) * block, n)
        _strapdown(t, gyro, accel, limits, lo, hi, starts[j].copy(), attitude)
        _backward(
            t, gyro, accel, limits, time_constant, lo, hi, attitude, state, averaged, end, last
        )
        ends[j] = state
    forward_state = np.zeros(4)
    for j in range(blocks):
        lo, hi = j * block, min((j + 1) * block, n)
        _strapdown(t, gyro, accel, limits, lo, hi, starts[j].copy(), attitude)
        state = ends[j + 1].copy()
        _backward(
            t, gyro, accel, limits, time_constant, lo, hi, attitude, state, averaged, end, last
        )
        out = np.empty((hi - lo, 3))
        _forward(
            t, gyro, accel, limits, time_constant, lo, hi, attitude, averaged, end, taper,
            forward_state, out, last,
        )  # fmt: skip
        yield out
