"""Offline smoothing: each sample's attitude and bias given the whole recording.

A two-filter smoother (Fraser & Potter 1969; Simon 2006, ch. 9; the design is
docs/design.md#smoothing). The forward pass is :func:`estimate` on the accelerometer
averaged with zero phase in the gyro's strapdown frame
(:mod:`mavest.estimator.zero_phase`, ``EstimatorConfig.smooth_accel_time``), so that
its tilt error is less like the backward pass's; the backward pass is
the same filter run over the time-reversed recording, in which the attitude
kinematics read dR/ds = R[−ω]×: the gyroscope negated, accelerometer, magnetometer
and known acceleration unchanged, so the backward filter's bias is −b. It starts at
the forward pass's last attitude with the configured initial uncertainty, its heading
set again by its own magnetometer where there is one. At each sample
the forward estimate (after that sample's update) is updated with the backward
filter's *prior* attitude there (before that sample's update: its estimate one sample
later in time, predicted one gyro step back), so that no sample's measurement counts
twice, and with its attitude alone: the bias is the forward pass's, corrected through
its correlation with the attitude (fusing the biases too is better on simulated
flights, whose noise is the filter's model, and worse on BROAD's real recordings).

Without a referenced heading in the backward pass (6-D), heading is not observed and
the backward pass's heading drifts apart from the forward one's: it is turned onto the
forward heading and only its tilt is used. With both referenced (9-D) tilt and heading
are. Where only the backward pass's is (the forward pass started afresh, at the
recording's start or after a restart, and has not yet met its magnetometer), its
heading is taken: the forward heading is free there, of no information.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike

from mavest.estimator.config import MAX_SPECIFIC_FORCE, EstimatorConfig, config_or_default
from mavest.estimator.estimator import (
    EstimateSeries,
    Estimator,
    InputError,
    batch_inputs,
    estimate,
    refuse_wrong_gyro_unit,
    refuse_wrong_unit,
)
from mavest.estimator.frames import add_alignment, lead
from mavest.estimator.fusion import BACKWARD_HEADING, TILT, TILT_AND_HEADING, fuse_block
from mavest.estimator.layout import StepFlags
from mavest.estimator.zero_phase import zero_phase_blocks

_Pass = TypeVar("_Pass")

# Samples whose estimate is a placeholder or a held copy of an earlier one: the smoother
# fuses none there, and its result holds no attitude of theirs.
NO_ESTIMATE = StepFlags.NOT_INITIALISED | StepFlags.SKIPPED
# Samples at which a pass starts afresh from that sample's accelerometer: its
# estimate there holds no earlier sample's attitude information, and its prior
# (the estimate before the sample) is not that of the estimate it holds.
_RESTARTS = (
    StepFlags.INITIALISED
    | StepFlags.GAP_REALIGNED
    | StepFlags.UNHEALTHY_RESET
    | StepFlags.DIVERGED
    | StepFlags.CLIP_REALIGNED
    | StepFlags.TIME_RESTARTED
)
# Backward samples are run and fused in blocks of this many: what the smoother holds
# beyond the forward estimates (the backward pass's estimates and inputs, about 0.5 kB
# a sample), whatever the length of the recording.
BLOCK = 1 << 13
# Within this many time constants of a segment's ends the forward pass's accelerometer
# goes over from the average to the sample as measured (zero_phase_blocks' taper).
TAPER = 4.0


def smooth(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
    linear_accel: ArrayLike | None = None,
) -> EstimateSeries:
    """Each sample's attitude and bias given the whole recording.

    The same arguments, validation and :class:`~mavest.estimator.estimator.InputError`
    as :func:`estimate`, and the same fields and conventions in the result: ``q``,
    ``bias`` and ``cov`` smoothed; ``flags`` and the update diagnostics (innovation,
    NIS, ``accel_used``, ...) those of the forward pass, which is :func:`estimate` on
    the averaged accelerometer (:func:`forward_accel`; with ``smooth_accel_time`` 0, a
    known acceleration, or where the average never lets the filter start, :func:`estimate`'s
    own).
    Where the forward pass has no estimate (not initialised, skipped samples) or the
    backward pass has none to fuse (see :func:`smooth_forward`), the forward estimate
    is returned unchanged.
    """
    config = config_or_default(config)
    t, gyro, accel, mag, linear_accel = batch_inputs(t, gyro, accel, mag, linear_accel)
    refuse_wrong_gyro_unit(t, gyro, accel, config)
    forward = _forward_pass(
        config,
        linear_accel,
        lambda: _forward_on_averaged_accel(t, gyro, accel, mag, config),
        lambda: estimate(t, gyro, accel, mag, config, linear_accel),
    )
    return smooth_forward(forward, t, gyro, accel, mag, config, linear_accel)


def _forward_pass(
    config: EstimatorConfig,
    linear_accel: np.ndarray | None,
    on_averaged: Callable[[], _Pass],
    on_measured: Callable[[], _Pass],
) -> _Pass:
    """The smoother's forward pass: run on the averaged accelerometer (``on_averaged``),
    or on the samples as measured (``on_measured``) with ``smooth_accel_time`` 0, with a
    known acceleration (which already takes out what the average would), or where the
    average never lets the filter start."""
    if config.smooth_accel_time > 0.0 and not _any_known(linear_accel):
        try:
            return on_averaged()
        except InputError:
            # Never near g on average (a long turn with a moment level), where the filter
            # starts on that moment's samples: the forward pass takes them as measured.
            pass
    return on_measured()


def _any_known(linear_accel: np.ndarray | None) -> bool:
    """Whether the vehicle's acceleration is known at any sample."""
    return linear_accel is not None and bool(np.any(np.isfinite(linear_accel)))


def forward_accel(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, config: EstimatorConfig
) -> np.ndarray:
    """The accelerometer as :func:`smooth`'s forward pass takes it (without a known
    acceleration), whole: averaged with zero phase over ``config.smooth_accel_time``,
    or ``accel`` itself when that is 0. For a forward pass run otherwise (e.g. from a
    known state, then given to :func:`smooth_forward`); :func:`smooth` itself takes it
    a block at a time."""
    t, gyro, accel, _, _ = batch_inputs(t, gyro, accel)
    if config.smooth_accel_time <= 0.0 or t.shape[0] == 0:
        return accel
    # (each block copied as it comes: the blocks are not all held at once)
    averaged = np.empty_like(accel)
    lo = 0
    for block in _averaged_blocks(t, gyro, accel, config):
        averaged[lo : lo + block.shape[0]] = block
        lo += block.shape[0]
    return averaged


def _averaged_blocks(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, config: EstimatorConfig
) -> Iterator[np.ndarray]:
    tau = config.smooth_accel_time
    return zero_phase_blocks(
        t, gyro, accel, tau, config.max_dt, BLOCK, TAPER * tau, config.gyro_clip, MAX_SPECIFIC_FORCE
    )


def _forward_on_averaged_accel(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray | None,
    config: EstimatorConfig,
) -> EstimateSeries:
    """:func:`estimate` on the accelerometer low-passed with zero phase
    (:mod:`mavest.estimator.zero_phase`), a block at a time: nothing of the
    recording's length is held beyond the result."""
    n = t.shape[0]
    forward = EstimateSeries.empty(n)
    estimator = Estimator(config)
    averaged = _averaged_blocks(t, gyro, accel, config)
    for lo, block in zip(range(0, n, BLOCK), averaged, strict=True):
        hi = lo + block.shape[0]
        part = None if mag is None else mag[lo:hi]
        estimator.update_batch(t[lo:hi], gyro[lo:hi], block, part, out=forward.rows(lo, hi))
    refuse_wrong_unit(estimator, forward.flags)
    return forward


def smooth_forward(
    forward: EstimateSeries,
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
    linear_accel: ArrayLike | None = None,
    backward_start: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
) -> EstimateSeries:
    """Smooth a forward pass already run over these samples with this configuration
    (e.g. one started from a known state with :meth:`Estimator.initialise`; on
    :func:`forward_accel`'s accelerometer, as :func:`smooth`'s is, or on the samples as
    measured), its cov as the filter reports it (with the configuration's
    ``accel_alignment_sigma``). ``accel`` is what the backward pass takes: the samples
    as measured.

    ``forward``'s q, bias and cov arrays are overwritten with the smoothed ones (a
    recording's estimates are most of what smoothing holds in memory; this way it
    holds them once) and it is returned. The backward pass starts at the time of the
    forward pass's last estimate from ``backward_start``, (q, bias, cov) as
    :meth:`Estimator.initialise` takes them (bias and cov in the forward sense); by
    default from the forward pass's last attitude, the configured initial bias and the
    configured initial uncertainty, its heading then set by its first magnetometer
    reading (unless a known acceleration needs it from the start). The measurements of
    that sample are not used backward.

    A sample is fused where the forward pass has an estimate and the backward pass a
    prior: not where either has none (not initialised, skipped), nor where the
    backward pass restarts (initialisation, re-alignment after a gap or a clipped
    gyro, reset after a failed health check, a restarted clock): its prior there is
    not that of its estimate. Gaps and resets need no other splitting: each pass's
    covariance already says what it knows across them.
    """
    config = config_or_default(config)
    t, gyro, accel, mag_array, linear = batch_inputs(t, gyro, accel, mag, linear_accel)
    n = t.shape[0]
    if len(forward) != n:
        raise ValueError(f"the forward pass has {len(forward)} samples, t has {n}")
    if backward_start is not None:
        q0, b0, P0 = (np.asarray(v, dtype=np.float64) for v in backward_start)
        if P0.shape != (6, 6):  # (the rest Estimator.initialise checks)
            raise ValueError(f"backward_start's cov must be (6, 6), got shape {P0.shape}")
        backward_start = (q0, b0, P0)
    blocks = _fused_blocks(
        forward.flags,
        forward.mag_used,
        lambda k: (forward.q[k], forward.bias[k]),
        forward.rows,
        (t, gyro, accel, mag_array, linear),
        config,
        backward_start,
    )
    for _ in blocks:  # (each block fused in place: forward's rows)
        pass
    return forward


def smooth_blocks(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
    linear_accel: ArrayLike | None = None,
) -> Iterator[tuple[int, EstimateSeries]]:
    """:func:`smooth`'s result a block of rows at a time, from the recording's end to its
    start: (the block's first row, its estimates), the same numbers bit for bit, the
    same validation and :class:`~mavest.estimator.estimator.InputError` (raised before
    the first block).

    For a recording too long to hold its smoothed covariances (288 bytes a sample: an
    hour at 1 kHz, 1 GB), taken a block at a time: the forward pass is run once to note
    its state every :data:`BLOCK` samples and again, a block at a time, as the backward
    pass reaches each, so nothing of the recording's length is held but the forward
    pass's flags and its averaged accelerometer (33 bytes a sample at the peak), for
    about the time of one more filter pass. Each block's estimates are the caller's (not
    kept).
    """
    config = config_or_default(config)
    t, gyro, accel, mag_array, linear = batch_inputs(t, gyro, accel, mag, linear_accel)
    refuse_wrong_gyro_unit(t, gyro, accel, config)
    forward = _forward_pass(
        config,
        linear,
        lambda: _CheckpointedPass(
            t, gyro, forward_accel(t, gyro, accel, config), mag_array, None, config
        ),
        lambda: _CheckpointedPass(t, gyro, accel, mag_array, linear, config),
    )
    yield from _fused_blocks(
        forward.flags,
        forward.mag_used,
        forward.estimate_at,
        forward.rows,
        (t, gyro, accel, mag_array, linear),
        config,
        None,
    )


class _CheckpointedPass:
    """A forward pass over a recording run once, keeping its flags, its magnetometer use
    and its state at the start of each of the backward pass's blocks (the recording's
    last :data:`BLOCK` samples, the block before them, …), then run again a block at a
    time (:meth:`rows`, each block once, in any order): each block's estimates as the
    first run gave them, as a filter's steps depend on its state and inputs alone."""

    def __init__(
        self,
        t: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        mag: np.ndarray | None,
        linear_accel: np.ndarray | None,
        config: EstimatorConfig,
    ) -> None:
        n = t.shape[0]
        self._inputs = (t, gyro, accel, mag, linear_accel)
        self._estimator = Estimator(config)
        self._states: dict[int, np.ndarray] = {}
        self._last: tuple[int, np.ndarray | None, np.ndarray | None] = (-1, None, None)
        self.flags = np.zeros(n, dtype=np.int32)
        self.mag_used = np.zeros(n, dtype=np.bool_)
        for lo, hi in reversed(list(_backward_blocks(n))):
            self._states[lo] = self._estimator.snapshot()
            out = self._run(lo, hi)
            self.flags[lo:hi] = out.flags
            self.mag_used[lo:hi] = out.mag_used
            estimated = np.flatnonzero((out.flags & NO_ESTIMATE) == 0)
            if estimated.shape[0]:
                k = int(estimated[-1])
                self._last = (lo + k, out.q[k].copy(), out.bias[k].copy())
        refuse_wrong_unit(self._estimator, self.flags)

    def _run(self, lo: int, hi: int) -> EstimateSeries:
        t, gyro, accel, mag, linear_accel = self._inputs
        return self._estimator.update_batch(
            t[lo:hi],
            gyro[lo:hi],
            accel[lo:hi],
            None if mag is None else mag[lo:hi],
            None if linear_accel is None else linear_accel[lo:hi],
        )

    def estimate_at(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The attitude and bias of the pass's last estimate (``k``, its row)."""
        last, q, b = self._last
        if k != last or q is None or b is None:
            raise ValueError(f"row {k} is not the forward pass's last estimate ({last})")
        return q, b

    def rows(self, lo: int, hi: int) -> EstimateSeries:
        """The estimates of block [lo, hi), run again from the state noted at ``lo``."""
        self._estimator.restore(self._states.pop(lo))
        return self._run(lo, hi)


def _backward_blocks(n: int) -> Iterator[tuple[int, int]]:
    """The backward pass's blocks of rows, [lo, hi), from the recording's end."""
    for hi in range(n, 0, -BLOCK):
        yield max(0, hi - BLOCK), hi


def _fused_blocks(
    flags: np.ndarray,
    mag_used: np.ndarray,
    estimate_at: Callable[[int], tuple[np.ndarray, np.ndarray]],
    forward_rows: Callable[[int, int], EstimateSeries],
    inputs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None],
    config: EstimatorConfig,
    backward_start: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
) -> Iterator[tuple[int, EstimateSeries]]:
    """The backward pass over the recording, fused a block at a time into the forward
    pass's estimates of those rows (``forward_rows(lo, hi)``: each block asked once, from
    the end; its q, bias and cov overwritten with the smoothed ones), each yielded with
    its first row. ``flags``, ``mag_used``: the forward pass's, whole; ``estimate_at(k)``:
    its attitude and bias at its last estimate, row ``k``; ``inputs``: the samples as measured
    (t, gyro, accel, mag, linear_accel), which the backward pass takes."""
    t, gyro, accel, mag_array, linear = inputs
    n = t.shape[0]
    has_forward = (flags & NO_ESTIMATE) == 0
    if n == 0 or not np.any(has_forward):
        for lo, hi in _backward_blocks(n):
            yield lo, forward_rows(lo, hi)
        return
    # Reversed time, increasing: t' = t_last − t, t_last a time the forward pass took
    # (a corrupt timestamp elsewhere is then far off the backward timeline as well).
    last = int(np.flatnonzero(has_forward)[-1])
    t_last = t[last]
    # (a block at a time, as the backward pass's: its temporaries are 40 bytes a sample)
    forward_heading = np.empty(n, dtype=np.bool_)
    referenced = False
    for lo in range(0, n, BLOCK):
        block = slice(lo, min(lo + BLOCK, n))
        forward_heading[block], referenced = _referenced_since_start(
            ((flags[block] & StepFlags.HEADING_ALIGNED) != 0) | mag_used[block],
            (flags[block] & StepFlags.INITIALISED) != 0,
            referenced,
        )
    # The passes are fused on the filter's own covariances: the accelerometer's alignment
    # is the same error in both, not two independent ones, and no fusing removes it. It
    # is taken off each block of the forward pass's and added to the smoothed ones.
    alignment = config.accel_alignment_sigma**2
    right = config.error == "right"
    # Both passes' states are the attitude ``imu_delay`` before each time stamp (each
    # takes the samples as they are). The forward pass's reported attitudes are taken
    # back to its state's, fused there, and the smoothed one carried forward as the
    # filter carries its own (frames.lead_into, as frames.report_attitude_into does).
    delay = config.imu_delay
    backward = Estimator(
        config.replace(
            initial_bias=tuple(-np.asarray(config.initial_bias)),
            accel_alignment_sigma=0.0,
            imu_delay=0.0,
        )
    )
    if backward_start is None:
        # The backward pass starts at the forward pass's last attitude, with the
        # configured initial bias and uncertainty: its value is taken, not its certainty
        # (and without a magnetometer only its tilt is fused). Aligned on its first
        # sample instead, as the filter aligns, a recording that ends in motion left it
        # at the mercy of that sample's linear acceleration: 135° off in tilt on a
        # simulated flight, where it then stayed wrong with a small σ and made the
        # smoothed attitude worse than the filter's. Its own magnetometer sets its
        # heading, unless a known acceleration (removed in the world frame) needs the
        # heading from the start.
        q_last, b_last = estimate_at(last)
        state = lead(q_last[None], gyro[last : last + 1], b_last[None], -delay)[0]
        backward.initialise(0.0, state, heading_known=_any_known(linear))
    else:
        q0, b0, P0 = backward_start
        flip = np.diag([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])  # δb of the backward pass is −δb
        backward.initialise(0.0, q0, -b0, flip @ P0 @ flip)
    backward_heading = False
    # the backward estimate at the sample after the block (its next block's first)
    after_flags = StepFlags.NOT_INITIALISED
    after_q, after_b, after_P = np.zeros(4), np.zeros(3), np.zeros((6, 6))
    for lo, hi in _backward_blocks(n):
        forward = forward_rows(lo, hi)
        # The rows with an estimate of their own taken back to the filter's state; the
        # attitudes of the others, and of those not fused, given back as reported, bit
        # for bit (their covariance, the alignment taken off and put back, to rounding).
        if delay:
            own = np.flatnonzero(has_forward[lo:hi])
            reported = forward.q.copy()
            forward.q[own] = lead(forward.q[own], gyro[lo + own], forward.bias[own], -delay)
        add_alignment(forward.q, -alignment, right, forward.cov)
        order = np.arange(hi - 1, lo - 1, -1)
        # the gyro sample that covers (t_k, t_k+1] is t_k+1's: the backward pass,
        # stepping from t_k+1 back to t_k, takes that one
        following = np.minimum(order + 1, n - 1)
        out = backward.update_batch(
            t_last - t[order],
            -gyro[following],
            accel[order],
            None if mag_array is None else mag_array[order],
            None if linear is None else linear[order],
        )
        referenced = ((out.flags & StepFlags.HEADING_ALIGNED) != 0) | out.mag_used
        started = (out.flags & StepFlags.INITIALISED) != 0
        backward_heading_at, backward_heading = _referenced_since_start(
            referenced, started, backward_heading
        )
        backward_heading_at = backward_heading_at[::-1]
        # in time order from here
        flags_b = out.flags[::-1]
        flags_next = np.append(flags_b[1:], after_flags)
        measured = ((flags_b & StepFlags.BETWEEN_UPDATES) == 0) | out.mag_used[::-1]
        fused = (
            has_forward[lo:hi]
            & ((flags_b & (NO_ESTIMATE | _RESTARTS)) == 0)
            & (~measured | ((flags_next & NO_ESTIMATE) == 0))
        )
        following = following[::-1]
        with np.errstate(invalid="ignore"):  # (∞ − ∞ at a last sample of time ∞: unused)
            dt = t[following] - t[lo:hi]
        fuse_block(
            forward.q,
            forward.bias,
            forward.cov,
            out.q,
            out.bias,
            out.cov,
            after_q,
            after_b,
            after_P,
            -gyro[following],
            dt,
            fused,
            measured,
            _heading_fused(forward_heading[lo:hi], backward_heading_at),
            right,
            config.gyro_noise_density,
            config.gyro_scale_noise_density,
            config.gyro_bias_random_walk,
        )
        after_flags = out.flags[-1]
        after_q, after_b, after_P = out.q[-1].copy(), out.bias[-1].copy(), out.cov[-1].copy()
        add_alignment(forward.q, alignment, right, forward.cov)
        if delay:
            forward.q[own] = lead(forward.q[own], gyro[lo + own], forward.bias[own], delay)
            forward.q[~fused] = reported[~fused]
        yield lo, forward


def _referenced_since_start(
    referenced: np.ndarray, started: np.ndarray, before: bool
) -> tuple[np.ndarray, bool]:
    """Per sample of a pass (in its order), whether its heading has been referenced (the
    magnetometer, or a known heading) since it last started afresh (``started``: its
    attitude from that sample's accelerometer alone, heading free; a sample may start
    and be referenced at once), with ``before`` whether it was at the sample before the
    first; and whether it is at the last sample (the next call's ``before``)."""
    index = np.arange(referenced.shape[0])
    last_referenced = np.maximum.accumulate(np.where(referenced, index, -1))
    last_start = np.maximum.accumulate(np.where(started, index, -1))
    out = (last_referenced >= last_start) & ((last_referenced >= 0) | before)
    return out, bool(out[-1]) if out.shape[0] else before


def _heading_fused(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """What of the backward prior each sample fuses (:data:`~mavest.estimator.fusion.TILT`
    and the rest), by which passes reference heading there."""
    fused = np.full(forward.shape, TILT, dtype=np.int64)
    fused[backward] = BACKWARD_HEADING
    fused[backward & forward] = TILT_AND_HEADING
    return fused
