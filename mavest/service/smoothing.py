"""A replay's streams smoothed: each sample's attitude given the whole log (``--smooth``).

While the log replays, each estimated stream keeps exactly what its online filter
took, sample by sample (:class:`RecordedInputs`): the time, the gyro, the specific
force after the pipeline's checks and corrections (the airspeed's centripetal term
removed where it was), the magnetometer reading where one was usable, the vehicle's
acceleration from GPS velocity where it was known. Both replay paths book their
samples there, so the smoothed result does not depend on the path. Its comparisons
with the autopilot and the truth (:class:`RecordedComparison`) keep the references
where they came among the estimates; scored again with the smoothed angles in place
of the online ones, the figures are over the same samples, with the same settle time.

After the replay, :func:`smooth_stream` runs the smoother over each stream's inputs,
a segment per timeline (a reboot starts a new one, as it re-initialises the filter),
with the stream's own filter configuration and the declination it ended with.

The inputs are float64 arrays, filled a chunk at a time (13 numbers, 104 bytes a
sample: a 1-hour 1 kHz stream holds 0.37 GB); without ``--smooth`` nothing is kept.
They are smoothed a block at a time (``smoother.smooth_blocks``, the same estimates
as ``mavest.smooth``), keeping of each block what the outputs show (128 bytes a
sample), not its covariances: an hour's autopilot log at 1 kHz replays and smooths in
1.2 GB. A simulator's log with its truth at every sample holds about 150 bytes a sample
more: the truth's references, kept to score the smoothed estimate against them.
"""

from __future__ import annotations

import logging
import math
import mmap
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mavest import so3
from mavest.estimator import EstimateSeries, InputError, StepFlags
from mavest.estimator.smoother import NO_ESTIMATE, smooth_blocks
from mavest.evaluation.online import ESTIMATE, REFERENCE, ComparisonResult, EulerComparison

if TYPE_CHECKING:
    from mavest.service.pipeline import Stream

log = logging.getLogger("mavest")

# Samples per chunk of a stream's inputs (6.8 MB): growing costs a chunk, never a copy.
CHUNK = 65536
# Estimates scored per call when a comparison is run again (bounds its arrays).
_SCORE_PIECE = 1 << 20

Vector = tuple[float, float, float]


def _mapped(shape: tuple[int, ...]) -> np.ndarray:
    """An empty float64 array in pages of its own (an anonymous mapping), which go back to
    the system when the array goes. A chunk from the allocator instead (a megabyte or so)
    stays in the process when freed, kept for reuse: the chunks :meth:`_Columns.take`
    frees as it copies them would stay beside the copy (360 MB for an hour at 1 kHz)."""
    size = math.prod(shape) * np.dtype(np.float64).itemsize
    return np.frombuffer(mmap.mmap(-1, size), dtype=np.float64).reshape(shape)


class _Columns:
    """Float64 columns (width 1: a number a row, else a vector) filled a row or many rows
    at a time, into chunks of :data:`CHUNK` rows: growing costs a chunk, never a copy."""

    def __init__(self, widths: tuple[int, ...]) -> None:
        self._shapes = [(CHUNK,) if width == 1 else (CHUNK, width) for width in widths]
        self._chunks: list[list[np.ndarray]] = []
        self._filled = CHUNK  # rows used in the last chunk (none yet: full)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def _room(self) -> list[np.ndarray]:
        if self._filled == CHUNK:
            self._chunks.append([_mapped(shape) for shape in self._shapes])
            self._filled = 0
        return self._chunks[-1]

    def add_row(self, *values: Any) -> None:
        chunk = self._room()
        k = self._filled
        for into, value in zip(chunk, values, strict=True):
            into[k] = value
        self._filled = k + 1
        self._count += 1

    def add_rows(self, *columns: np.ndarray) -> None:
        n = columns[0].shape[0]
        done = 0
        while done < n:
            chunk = self._room()
            k = self._filled
            take = min(n - done, CHUNK - k)
            for into, values in zip(chunk, columns, strict=True):
                into[k : k + take] = values[done : done + take]
            self._filled = k + take
            done += take
        self._count += n

    def take(self, keep: bool = False) -> list[np.ndarray]:
        """The columns whole. Unless ``keep``, each chunk goes once copied, leaving none:
        the memory in use grows by a chunk at most (the whole arrays' pages are touched
        as the chunks go)."""
        n = self._count
        whole = [np.empty((n, *shape[1:])) for shape in self._shapes]
        chunks = list(self._chunks) if keep else self._chunks
        # the newest first: freed from the top of the heap, the memory goes back at once
        # (freed from the bottom, the allocator keeps it: the copy would double it)
        while chunks:
            start = (len(chunks) - 1) * CHUNK
            stop = min(start + CHUNK, n)
            chunk = chunks.pop()
            for into, values in zip(whole, chunk, strict=True):
                into[start:stop] = values[: stop - start]
            del chunk
        if not keep:
            self._filled, self._count = CHUNK, 0
        return whole


class RecordedInputs:
    """The inputs a stream's filter took, in order, and where its timelines begin."""

    def __init__(self) -> None:
        # t, gyro, accel, mag (NaN: none), linear_accel (NaN: not known)
        self._columns = _Columns((1, 3, 3, 3, 3))
        self.segments: list[int] = [0]  # index of each timeline's first sample

    def __len__(self) -> int:
        return len(self._columns)

    def add(
        self,
        t: float,
        gyro: Vector,
        accel: Vector,
        mag: Vector | None,
        linear_accel: Vector | None,
    ) -> None:
        """One sample the filter took (``mag``, ``linear_accel``: None when it had none)."""
        self._columns.add_row(
            t,
            gyro,
            accel,
            math.nan if mag is None else mag,
            math.nan if linear_accel is None else linear_accel,
        )

    def add_many(
        self,
        t: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        mag: np.ndarray,
        linear_accel: np.ndarray,
        flags: np.ndarray,
    ) -> None:
        """Samples given to the filter at once (NaN rows: no magnetometer, no known
        acceleration), with the flags of its steps: those it skipped are not kept."""
        columns = (t, gyro, accel, mag, linear_accel)
        kept = (flags & StepFlags.SKIPPED) == 0
        if not kept.all():
            columns = tuple(values[kept] for values in columns)
        self._columns.add_rows(*columns)

    def restart(self) -> None:
        """The filter was re-initialised for a new timeline (a reboot), or lost its
        attitude (a clipped gyro): the smoother carries none across."""
        if len(self) > self.segments[-1]:
            self.segments.append(len(self))

    def take(self) -> list[np.ndarray]:
        """[t, gyro, accel, mag, linear_accel], whole (none are kept after)."""
        return self._columns.take()


_RESTART = -1.0  # an event's kind (beside REFERENCE)


class RecordedComparison(EulerComparison):
    """An :class:`EulerComparison` that also keeps its references where they came among
    the estimates (and its restarts), so that the same comparison can be made again
    with other estimates of the same samples (:meth:`again`)."""

    def __init__(self, settle_time: float = 10.0) -> None:
        super().__init__(settle_time)
        self.estimates = 0
        # per event: how many estimates came before it, its kind (REFERENCE or _RESTART),
        # its time and angles
        self._events = _Columns((1, 1, 1, 3))

    def restart(self) -> None:
        super().restart()
        self._events.add_row(self.estimates, _RESTART, 0.0, 0.0)

    def add_estimate(self, t: float, euler: Vector) -> None:
        super().add_estimate(t, euler)
        self.estimates += 1

    def add_reference(self, t: float, euler: Vector) -> None:
        super().add_reference(t, euler)
        self._events.add_row(self.estimates, REFERENCE, t, euler)

    def add_many(self, kinds: np.ndarray, t: np.ndarray, euler: np.ndarray) -> None:
        super().add_many(kinds, t, euler)
        estimate = kinds == ESTIMATE
        references = np.flatnonzero(~estimate)
        if references.shape[0]:
            before = self.estimates + np.cumsum(estimate) - estimate
            self._events.add_rows(
                before[references].astype(np.float64),
                np.full(references.shape[0], float(REFERENCE)),
                t[references],
                euler[references],
            )
        self.estimates += int(np.count_nonzero(estimate))

    def again(self, t: np.ndarray, euler: np.ndarray) -> ComparisonResult:
        """The comparison made again with other estimates of the same samples (``t``,
        ``euler`` (N, 3) rad: every estimate this one took, in order), the same
        references among them and the same restarts."""
        if t.shape[0] != self.estimates:
            raise ValueError(f"{t.shape[0]} estimates for a comparison of {self.estimates}")
        comparison = EulerComparison(self.settle_time, max_span=self.max_span)
        place, kind, times, angles = self._events.take(keep=True)
        start = 0  # the next estimate
        first = 0  # the next event
        for restart in [*np.flatnonzero(kind == _RESTART).tolist(), place.shape[0]]:
            stop = int(place[restart]) if restart < place.shape[0] else t.shape[0]
            # the estimates before the restart, with the references among (and after) them
            while True:
                end = min(stop, start + _SCORE_PIECE)
                last = restart if end == stop else int(np.searchsorted(place, end, "left"))
                last = max(last, first)
                _score(comparison, t, euler, start, end, place, times, angles, first, last)
                start, first = end, last
                if end == stop:
                    break
            if restart < place.shape[0]:
                comparison.restart()
                first = restart + 1
        return comparison.result()


def _score(
    comparison: EulerComparison,
    t: np.ndarray,
    euler: np.ndarray,
    start: int,
    end: int,
    place: np.ndarray,
    times: np.ndarray,
    angles: np.ndarray,
    first: int,
    last: int,
) -> None:
    """Estimates [start, end) and references [first, last) into a comparison, in the
    order they came (a reference after the ``place`` estimates before it)."""
    n, m = end - start, last - first
    if not n + m:
        return
    kinds = np.concatenate([np.full(n, ESTIMATE), np.full(m, REFERENCE)]).astype(np.int64)
    order = np.argsort(
        np.concatenate([2 * np.arange(start, end) + 1, 2 * place[first:last].astype(np.int64)]),
        kind="stable",
    )
    # (a timeline the smoother refused is NaN: no estimate there to compare)
    estimated = np.concatenate([np.all(np.isfinite(euler[start:end]), axis=1), np.ones(m, bool)])
    order = order[estimated[order]]
    comparison.add_many(
        kinds[order],
        np.concatenate([t[start:end], times[first:last]])[order],
        np.concatenate([euler[start:end], angles[first:last]])[order],
    )


@dataclass
class SmoothedStream:
    """One stream smoothed: per estimated sample, in the order they were estimated."""

    t: np.ndarray  # (N,) s, the stream's vehicle time
    q: np.ndarray  # (N, 4) body → NED, w x y z
    euler: np.ndarray  # (N, 3) rad, ZYX roll, pitch, yaw
    sigma: np.ndarray  # (N, 3) rad, their 1σ
    bias: np.ndarray  # (N, 3) rad/s
    bias_sigma: np.ndarray  # (N, 3) rad/s
    # the comparisons of the online estimate made again with the smoothed one (None: the
    # stream had no such comparison)
    vs_truth: ComparisonResult | None = None
    vs_autopilot: ComparisonResult | None = None
    refused: int = 0  # samples of the timelines the smoother refused (NaN)

    def __len__(self) -> int:
        return self.t.shape[0]


def measured_interval_acceleration(linear_accel: np.ndarray) -> np.ndarray:
    """The GPS acceleration over the interval it was measured on, for the smoother.

    Online, a velocity difference arrives at the end of the interval it averages and is
    held until the next: on the samples it is given to, it lags by about one report
    interval (0.1 s at 10 Hz), which a filter in a turn must live with. The smoother has
    the whole log, so each held value is moved to the samples of the interval before it
    (where the previous value was held), when both are known; a value whose successor
    is unknown (the last, or GPS lost) stays where it was, and unknown rows stay so.
    """
    n = linear_accel.shape[0]
    if n < 2:
        return linear_accel
    a = linear_accel
    same = np.all((a[1:] == a[:-1]) | (np.isnan(a[1:]) & np.isnan(a[:-1])), axis=1)
    starts = np.flatnonzero(np.r_[True, ~same])  # where each held value begins
    run = np.cumsum(np.r_[True, ~same]) - 1  # each sample's held value, by number
    following = np.r_[starts[1:], n]  # where the next one begins (n: none)
    has_next = following < n
    next_value = np.full((len(starts), 3), math.nan)
    next_value[has_next] = a[following[has_next]]
    known = np.all(np.isfinite(a[starts]), axis=1) & np.all(np.isfinite(next_value), axis=1)
    out = a.copy()
    moved = known[run]
    out[moved] = next_value[run[moved]]
    return out


def _kept_of(
    blocks: Iterator[tuple[int, EstimateSeries]], n: int, error: str
) -> tuple[np.ndarray, ...]:
    """What a smoothed stream keeps of the smoother's result (``blocks``: n samples'
    worth from :func:`~mavest.estimator.smoother.smooth_blocks`), filled a block at a
    time: q, the angles and their σ, the bias and its σ (128 bytes a sample, where the
    result with its covariances is 401)."""
    q = np.empty((n, 4))
    euler, sigma, bias, bias_sigma = (np.empty((n, 3)) for _ in range(4))
    kept = (q, euler, sigma, bias, bias_sigma)
    for lo, series in blocks:
        rows = slice(lo, lo + len(series))
        q[rows] = series.q
        bias[rows] = series.bias
        euler[rows] = so3.euler_zyx_from_quats(series.q)
        sigma[rows] = so3.euler_sigmas(series.q, series.cov[:, :3, :3], error)
        bias_variance = np.diagonal(series.cov[:, 3:, 3:], axis1=1, axis2=2)
        bias_sigma[rows] = np.sqrt(np.maximum(bias_variance, 0.0))
        # where the smoother has no estimate (its filter not yet started) its rows hold
        # placeholders (identity, the initial σ), not an attitude: none is shown
        none = lo + np.flatnonzero((series.flags & NO_ESTIMATE) != 0)
        for values in kept:
            values[none] = math.nan
    return kept


def smooth_stream(stream: Stream) -> SmoothedStream | None:
    """A stream's recorded inputs smoothed, a segment per timeline; its comparisons made
    again with the result. A segment the smoother refuses (nothing in it could start the
    filter) is NaN, said in one line, and so is every one if it refuses them all (the
    outputs keep their smoothed columns). None: no inputs kept."""
    inputs = stream.inputs
    if inputs is None or not len(inputs):
        return None
    estimator = stream.estimator
    # the declination it ended with: the vehicle's COMPASS_DEC, which a log gives early
    config = estimator.config.replace(compass_dec=estimator.declination)
    log.info("%s: smoothing %d samples", stream.key, len(inputs))
    segments = inputs.segments
    t, gyro, accel, mag, linear_accel = inputs.take()
    linear_accel = measured_interval_acceleration(linear_accel)
    n = t.shape[0]
    parts: list[tuple[np.ndarray, ...]] = []  # per timeline: q, euler, sigma, bias, bias σ
    refused = 0
    for first, end in zip(segments, [*segments[1:], n], strict=True):
        part = slice(first, end)
        try:
            blocks = smooth_blocks(
                t[part], gyro[part], accel[part], mag[part], config, linear_accel[part]
            )
            kept = _kept_of(blocks, end - first, config.error)
        except InputError as error:
            where = (
                f" (samples {first + 1}–{end} of {n}, one of its {len(segments)} timelines:"
                " a reboot or a clipped gyro starts one)"
                if len(segments) > 1
                else ""
            )
            log.warning("%s: not smoothed%s: %s", stream.key, where, error)
            refused += end - first
            parts.append(tuple(np.full((end - first, k), math.nan) for k in (4, 3, 3, 3, 3)))
            continue
        parts.append(kept)
    del gyro, accel, mag, linear_accel  # (t is all that is needed from here)
    q, euler, sigma, bias, bias_sigma = (
        parts[0][i] if len(parts) == 1 else np.concatenate([p[i] for p in parts]) for i in range(5)
    )
    del parts
    smoothed = SmoothedStream(t, q, euler, sigma, bias, bias_sigma, refused=refused)
    for name in ("vs_truth", "vs_autopilot"):
        comparison = getattr(stream, name)
        if isinstance(comparison, RecordedComparison):
            setattr(smoothed, name, comparison.again(t, euler))
    return smoothed
