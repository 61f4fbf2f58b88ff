"""What the filter is doing, as a Rerun recording: attitude, uncertainty, bias, innovations.

Per IMU stream (root ``vehicle_<sys>_<comp>/<message>_<instance>``):

- ``attitude/{roll,pitch,yaw}/mavest`` in degrees, with ``…/mavest_3sigma``
  (two series: ±3σ from the covariance, the world-frame attitude error mapped
  through the ZYX Euler kinematics); ``…/autopilot`` and ``…/truth`` beside;
- ``error/{roll,pitch,yaw}/{vs_autopilot,vs_truth}``: ours minus theirs at
  their times (ours interpolated); references faster than ``slow_rate`` (a
  simulator's truth at the IMU rate) are plotted at ``slow_rate``;
- ``bias/{x,y,z}`` in °/s: the estimate and ±1σ (bias and bounds change
  slowly and are logged at up to ``slow_rate``, 100 Hz);
- ``imu/gyro`` (°/s), ``imu/accel`` (m/s²): what came in, x, y, z;
- ``innovation`` (°, x, y) and ``nis/value`` with ``nis/chi2_band`` (χ², 2 dof,
  the central 90 % band): one sample per ``slow_rate`` slot (each still a
  single update's, so the band stays right; between the filter's updates a sample
  shows the last update's); ``accel`` (the fraction of the slot's update samples
  whose accelerometer was used, and disturbed, for the slots that hold one), so
  that not one rejection is hidden by the thinning;
- ``timing/processing_us``: decode to estimate, per sample;
- ``world/<root>/{mavest,autopilot,truth}``: the vehicle body in 3-D (NED),
  side by side, posed at up to ``pose_rate`` Hz;
- with ``replay --smooth``, once the log is replayed: ``attitude/{roll,pitch,yaw}/smoothed``
  (the smoothed estimate, at every sample) and ``…/smoothed_3sigma`` (its ±3σ, at up
  to ``slow_rate``), beside the online estimate, on ``vehicle_time`` only.

Two timelines: ``vehicle_time`` (the flight controller's clock, s since boot)
and ``receive_time`` (when the sample arrived; the tlog's record time on replay).

Rows are buffered and sent with ``send_columns`` (one call per entity per
batch, never a ``log()`` per sample); what a recording costs at 1 kHz is
measured by ``tools/service_bench.py``.
"""

from __future__ import annotations

import functools
import math
import operator
import time
from dataclasses import dataclass, field
from itertools import chain
from typing import Any

import numpy as np
import rerun as rr

from mavest import so3
from mavest.estimator.layout import StepFlags
from mavest.evaluation.metrics import wrap_angles
from mavest.so3 import euler_sigmas

VEHICLE_TIME = "vehicle_time"
RECEIVE_TIME = "receive_time"

# χ² with 2 degrees of freedom: 5 % and 95 % points (the NIS of a consistent filter
# falls between them 90 % of the time).
CHI2_2_LOW = 0.1026
CHI2_2_HIGH = 5.9915

COLORS = {
    "mavest": (31, 119, 180),
    "autopilot": (255, 127, 14),
    "truth": (44, 160, 44),
    "bound": (150, 190, 230),
    "smoothed": (148, 103, 189),
    "smoothed_bound": (205, 185, 225),
}
# Where each body sits in the 3-D view (m, NED), so the three do not overlap.
BODY_OFFSETS = {"mavest": (0.0, 0.0, 0.0), "autopilot": (0.0, 3.0, 0.0), "truth": (0.0, -3.0, 0.0)}


def stream_root(key: Any) -> str:
    """The entity path under which one IMU stream's recording lives."""
    return f"vehicle_{key.system}_{key.component}/{key.message.lower()}_{key.instance}"


# What the recorder keeps of a sample until its batch is sent: a row of floats (vehicle
# time, receive time (s), processing (s), roll, pitch, yaw, gyro x y z, accel x y z, whether
# the accelerometer was used, the step's flags), built per sample as a tuple (the cheapest
# thing to make in Python) and packed into a numpy block every _BLOCK rows, while the tuples
# are still in the cache: 112 bytes a row, where the tuple and the floats it holds alive
# take ~4× that, and the estimate (its covariance, ...) ~10×.
_T, _RX, _PROCESSING, _USED, _FLAGS = 0, 1, 2, 12, 13
_EULER, _GYRO, _ACCEL = slice(3, 6), slice(6, 9), slice(9, 12)
_FIELDS = 14
_BLOCK = 64


# The filter's health events (StepFlags): level and line in the recording's event log.
_EVENTS = (
    (StepFlags.TILT_REOPENED, "INFO", "accelerometer disturbed too long: tilt uncertain again"),
    (StepFlags.DIVERGED, "WARN", "diverged (contradicted again soon after): re-initialised"),
    (StepFlags.UNHEALTHY_RESET, "WARN", "state failed its health check: re-initialised"),
    (StepFlags.CLIP_REALIGNED, "WARN", "calm again after the gyro clipped: tilt re-aligned"),
)
_EVENT_BITS = functools.reduce(operator.or_, (bit for bit, _, _ in _EVENTS))


class _Slots:
    """Which samples of a series start a ``slow_rate`` slot and a ``pose_rate`` slot.

    A slot is floor(t / period); a sample starts one when its own differs from the
    previous sample's: at most one sample per slot, the first in it, keeping the original
    samples (a decimation that does not resample). The caller tests ``since <= t < until``
    inline (inside both current slots: most samples, and no call) and calls ``advance``
    only otherwise.
    """

    __slots__ = ("pose", "pose_period", "since", "slow", "slow_period", "until")

    def __init__(self, slow_period: float, pose_period: float) -> None:
        self.slow_period = slow_period
        self.pose_period = pose_period
        # NaN before the first sample: it differs from every slot, so the first sample
        # starts both; an empty interval sends it to ``advance``
        self.slow = self.pose = math.nan
        self.since, self.until = math.inf, -math.inf

    def advance_many(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`advance` for each of these times in turn: which start a slow slot, a
        pose slot (as booleans); the slots become the last one's."""
        if not t.shape[0]:
            empty = np.zeros(0, dtype=bool)
            return empty, empty
        slow = (t / self.slow_period) // 1.0
        pose = (t / self.pose_period) // 1.0
        # NaN (before the first sample, or a time not finite) differs from every slot
        starts_slow = slow != np.concatenate(([self.slow], slow[:-1]))
        starts_pose = pose != np.concatenate(([self.pose], pose[:-1]))
        self.advance(float(t[-1]))
        return starts_slow, starts_pose

    def advance(self, t: float) -> tuple[bool, bool]:
        """Whether the sample at t starts a slow slot, a pose slot; the slots become its."""
        slow = (t / self.slow_period) // 1.0  # floor, and NaN (no error) if not finite
        pose = (t / self.pose_period) // 1.0
        starts = (slow != self.slow, pose != self.pose)
        self.slow, self.pose = slow, pose
        since = max(slow * self.slow_period, pose * self.pose_period)
        until = min((slow + 1.0) * self.slow_period, (pose + 1.0) * self.pose_period)
        # Kept inside by far more than the division's rounding (a few ulp of t): a sample
        # within the margin of a boundary calls ``advance``, which decides by division.
        margin = 1e-12 * max(abs(since), abs(until))
        self.since, self.until = since + margin, until - margin
        return starts


@dataclass
class _References:
    """One reference's attitudes (the autopilot's, the truth) since the last batch: only
    those that start a slow_rate or a pose_rate slot, the only ones shown."""

    slots: _Slots
    # (t, receive s, roll, pitch, yaw, starts a slow slot, starts a pose slot)
    rows: list[tuple[float, ...]] = field(default_factory=list)


@dataclass
class _StreamBuffer:
    root: str
    slots: _Slots  # of our estimates
    error: str  # the estimator's error side: the frame of its attitude covariance
    rows: list[tuple[float, ...]] = field(default_factory=list)  # < _BLOCK rows, as tuples
    blocks: list[np.ndarray] = field(default_factory=list)  # the batch's rows, packed
    packed: int = 0  # rows in blocks
    # (row, estimate) of the samples that start a slow_rate slot, (row, q) of those that
    # start a pose_rate slot, chosen as they come: the covariance, bias and update of the
    # others are never shown, so their estimates are not kept
    slow: list[tuple[int, Any]] = field(default_factory=list)
    poses: list[tuple[int, np.ndarray]] = field(default_factory=list)
    references: dict[str, _References] = field(default_factory=dict)  # by source
    # our last estimate already sent: the anchor for references just after a batch
    anchor: tuple[float, float, float, float] | None = None
    bodies: set[str] = field(default_factory=set)  # bodies already given their shapes


class RerunRecorder:
    """An estimate sink writing to a Rerun recording stream (file, viewer, or both)."""

    def __init__(
        self,
        recording: rr.RecordingStream,
        batch_rows: int = 32768,  # a multiple of 64 (others are rounded up)
        batch_seconds: float = 2.0,  # of the machine's clock; see ``for_viewer``
        pose_rate: float = 50.0,
        slow_rate: float = 100.0,
    ) -> None:
        self.recording = recording
        self.batch_rows = batch_rows
        self.batch_seconds = batch_seconds
        self.pose_period = 1.0 / pose_rate
        self.slow_period = 1.0 / slow_rate
        self._streams: dict[Any, _StreamBuffer] = {}
        self._last_flush = time.monotonic()
        self.on_new_stream: list[Any] = []  # callbacks(root) when a stream appears
        self._last_key: Any = None
        self._last: _StreamBuffer | None = None

    @classmethod
    def for_viewer(cls, recording: rr.RecordingStream, live: bool) -> RerunRecorder:
        """Batches of 0.25 s for a live viewer (it should feel live); for a file only, of
        32768 rows, whatever the time.

        A file's batches may be large: each costs ~8 ms (~30 ``send_columns`` calls, as
        many chunks to encode) whatever its size, while a row waiting costs 112 bytes. No
        clock for a file: ``mavest run`` sends a file-only recording every 10 s anyway
        (``runners.FILE_ONLY_FLUSH_PERIOD``), and a replay's batches then do not depend
        on how fast the machine is (so that
        ``tools/service_bench.py --instructions`` counts the same work under valgrind).
        """
        if live:
            return cls(recording, batch_rows=4096, batch_seconds=0.25)
        return cls(recording, batch_rows=32768, batch_seconds=math.inf)

    # ------------------------------------------------------------ sink interface

    def _switch(self, stream: Any) -> _StreamBuffer:
        self._last_key = stream.key
        self._last = self._buffer(stream)
        return self._last

    def _buffer(self, stream: Any) -> _StreamBuffer:
        buffer = self._streams.get(stream.key)
        if buffer is None:
            buffer = _StreamBuffer(
                stream_root(stream.key), self._slots(), stream.estimator.config.error
            )
            self._streams[stream.key] = buffer
            self._log_static(buffer.root)
            for callback in self.on_new_stream:
                callback(buffer.root)
        return buffer

    def _slots(self) -> _Slots:
        return _Slots(self.slow_period, self.pose_period)

    def on_estimate(
        self,
        stream: Any,
        sample: Any,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None:
        # At the IMU rate: a tuple per sample, the slot tests; the rest per block or batch.
        buffer = self._last if stream.key is self._last_key else self._switch(stream)
        rows = buffer.rows
        t = estimate.t
        slots = buffer.slots
        if not slots.since <= t < slots.until:
            slow, pose = slots.advance(t)
            if slow:
                buffer.slow.append((buffer.packed + len(rows), estimate))
            if pose:
                buffer.poses.append((buffer.packed + len(rows), estimate.q))
        gyro, accel = sample.gyro, sample.accel
        rows.append(
            (
                t,
                receive_us * 1e-6,
                processing_s,
                *euler,
                *gyro,
                *accel,
                estimate.accel_used,
                estimate.flags,
            )
        )
        if len(rows) == _BLOCK:
            self._pack(buffer)

    def on_estimates(
        self,
        stream: Any,
        t: np.ndarray,
        euler: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        accel_used: np.ndarray,
        flags: np.ndarray,
        q: np.ndarray,
        series: Any,
        index: np.ndarray,
        receive_us: np.ndarray,
        processing_s: float,
    ) -> None:
        """Many estimates of one stream, in order (the replay's fast path): as
        :meth:`on_estimate` for each. The i-th is ``series[index[i]]`` (of an
        :class:`~mavest.estimator.EstimateSeries`; made into an Estimate only for those
        that start a slow_rate slot); ``processing_s`` is the time per sample, the
        batch's divided among its samples."""
        n = t.shape[0]
        if not n:
            return
        buffer = self._last if stream.key is self._last_key else self._switch(stream)
        if buffer.rows:  # the rows taken one by one come first
            buffer.blocks.append(_packed(buffer.rows))
            buffer.packed += len(buffer.rows)
            buffer.rows.clear()
        starts_slow, starts_pose = buffer.slots.advance_many(t)
        first = buffer.packed
        buffer.slow.extend((first + i, series[int(index[i])]) for i in np.flatnonzero(starts_slow))
        buffer.poses.extend((first + i, q[i]) for i in np.flatnonzero(starts_pose))
        block = np.empty((n, _FIELDS))
        block[:, _T] = t
        block[:, _RX] = receive_us * 1e-6
        block[:, _PROCESSING] = processing_s
        block[:, _EULER] = euler
        block[:, _GYRO] = gyro
        block[:, _ACCEL] = accel
        block[:, _USED] = accel_used
        block[:, _FLAGS] = flags
        buffer.blocks.append(block.reshape(-1))
        buffer.packed += n
        self._flush_if_due(buffer)

    def on_references(
        self, stream: Any, source: str, t: np.ndarray, euler: np.ndarray, receive_us: np.ndarray
    ) -> None:
        """Many references of one source, in order: as :meth:`on_reference` for each."""
        if not t.shape[0]:
            return
        references = self._references(stream, source)
        starts_slow, starts_pose = references.slots.advance_many(t)
        for i in np.flatnonzero(starts_slow | starts_pose).tolist():
            references.rows.append(
                (
                    float(t[i]),
                    float(receive_us[i]) * 1e-6,
                    *(float(x) for x in euler[i]),
                    bool(starts_slow[i]),
                    bool(starts_pose[i]),
                )
            )

    def on_smoothed(self, stream: Any, t: np.ndarray, euler: np.ndarray, sigma: np.ndarray) -> None:
        """A stream's smoothed estimate, whole (after a replay): its (N,) times, (N, 3)
        ZYX angles and their 1σ (rad), sent at once in batches of ``batch_rows``."""
        root = self._buffer(stream).root
        rec = self.recording
        bound = COLORS["smoothed_bound"]
        for axis in ("roll", "pitch", "yaw"):
            entity = f"{root}/attitude/{axis}/smoothed"
            rec.log(
                entity, rr.SeriesLines(colors=[COLORS["smoothed"]], names=["smoothed"]), static=True
            )
            rec.log(
                f"{entity}_3sigma",
                rr.SeriesLines(colors=[bound, bound], names=["smoothed +3σ", "smoothed −3σ"]),
                static=True,
            )
        # the band as the online one: the first sample of each slow_rate slot
        starts_slow, _ = self._slots().advance_many(t)
        for start in range(0, t.shape[0], self.batch_rows):
            part = slice(start, start + self.batch_rows)
            angle = np.degrees(euler[part])
            slow = np.flatnonzero(starts_slow[part])
            band = 3.0 * np.degrees(sigma[part][slow])
            index, slow_index = self._index(t[part], None), self._index(t[part][slow], None)
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                self._send(f"{root}/attitude/{axis}/smoothed", index, angle[:, i])
                bounds = np.column_stack([angle[slow, i] + band[:, i], angle[slow, i] - band[:, i]])
                self._send(f"{root}/attitude/{axis}/smoothed_3sigma", slow_index, bounds)

    def _pack(self, buffer: _StreamBuffer) -> None:
        """The rows made into a block; the batch sent when full or old enough."""
        buffer.blocks.append(_packed(buffer.rows))
        buffer.packed += len(buffer.rows)
        buffer.rows.clear()
        self._flush_if_due(buffer)

    def _flush_if_due(self, buffer: _StreamBuffer) -> None:
        if (
            buffer.packed >= self.batch_rows
            or time.monotonic() - self._last_flush >= self.batch_seconds
        ):
            self.flush()

    def _references(self, stream: Any, source: str) -> _References:
        buffer = self._last if stream.key is self._last_key else self._switch(stream)
        references = buffer.references.get(source)
        if references is None:
            references = buffer.references[source] = _References(self._slots())
        return references

    def on_reference(
        self, stream: Any, source: str, t: float, euler: tuple, receive_us: int = 0
    ) -> None:
        # at the IMU rate for a simulator's truth: kept only if it starts a slot
        references = self._references(stream, source)
        slots = references.slots
        if not slots.since <= t < slots.until:
            slow, pose = slots.advance(t)
            if slow or pose:
                references.rows.append((t, receive_us * 1e-6, *euler, slow, pose))

    # ------------------------------------------------------------ sending

    def _log_static(self, root: str) -> None:
        """Series names and colours, and the bodies' shapes, once per stream."""
        rec = self.recording

        def style(entity: str, colors: list[tuple[int, int, int]], names: list[str]) -> None:
            rec.log(entity, rr.SeriesLines(colors=colors, names=names), static=True)

        bound = COLORS["bound"]
        for axis in ("roll", "pitch", "yaw"):
            style(f"{root}/attitude/{axis}/mavest", [COLORS["mavest"]], ["mavest"])
            style(f"{root}/attitude/{axis}/mavest_3sigma", [bound, bound], ["+3σ", "−3σ"])
            for source in ("autopilot", "truth"):
                style(f"{root}/attitude/{axis}/{source}", [COLORS[source]], [source])
                style(f"{root}/error/{axis}/vs_{source}", [COLORS[source]], [f"mavest − {source}"])
        for axis in "xyz":
            style(
                f"{root}/bias/{axis}",
                [COLORS["mavest"], bound, bound],
                [f"bias {axis}", "+1σ", "−1σ"],
            )
        xyz = [(220, 40, 40), (40, 160, 40), (40, 90, 230)]
        style(f"{root}/imu/gyro", xyz, ["x", "y", "z"])
        style(f"{root}/imu/accel", xyz, ["x", "y", "z"])
        style(f"{root}/innovation", xyz[:2], ["x", "y"])
        style(f"{root}/nis/chi2_band", [bound, bound], ["χ² 5 %", "χ² 95 %"])
        rec.log(
            f"{root}/nis/value",
            rr.SeriesPoints(colors=[COLORS["mavest"]], names=["NIS"], marker_sizes=[1.5]),
            static=True,
        )
        style(
            f"{root}/accel",
            [COLORS["truth"], COLORS["autopilot"]],
            ["fraction used", "fraction disturbed"],
        )
        style(f"{root}/timing/processing_us", [COLORS["mavest"]], ["µs per sample"])
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)  # NED

    def _log_body(self, buffer: _StreamBuffer, source: str) -> None:
        """A body in the 3-D view, the first time its source has an attitude to show."""
        rec = self.recording
        body = f"world/{buffer.root}/{source}"
        rec.log(body, rr.Transform3D(translation=BODY_OFFSETS[source]), static=True)
        rec.log(
            f"{body}/attitude/airframe",
            rr.Boxes3D(
                half_sizes=[[0.9, 0.08, 0.08], [0.12, 1.1, 0.02], [0.08, 0.35, 0.02]],
                centers=[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [-0.8, 0.0, 0.0]],
                colors=[COLORS[source]] * 3,
                fill_mode="solid",
            ),
            static=True,
        )
        rec.log(
            f"{body}/attitude/axes",
            rr.Arrows3D(
                vectors=[[1.4, 0, 0], [0, 1.4, 0], [0, 0, 1.0]],
                colors=[(220, 40, 40), (40, 160, 40), (40, 90, 230)],
                labels=["forward", "right", "down"] if source == "mavest" else None,
            ),
            static=True,
        )
        rec.log(f"{body}/label", rr.Points3D([[0, 0, -1.2]], labels=[source]), static=True)

    @staticmethod
    def _index(times: np.ndarray, receive: np.ndarray | None) -> list[rr.TimeColumn]:
        """The time columns of some rows (built once and shared by the entities that have
        the same rows: a batch's full-rate series, its slow_rate series)."""
        index = [rr.TimeColumn(VEHICLE_TIME, duration=times)]
        if receive is not None:
            index.append(rr.TimeColumn(RECEIVE_TIME, timestamp=receive))
        return index

    def _send(self, entity: str, index: list[rr.TimeColumn], values: np.ndarray) -> None:
        """One entity's rows; (N, k) values are k series of one entity."""
        columns = rr.Scalars.columns(scalars=values.reshape(-1))
        if values.ndim == 2:
            columns = columns.partition(np.full(len(values), values.shape[1]))
        rr.send_columns(entity, indexes=index, columns=columns, recording=self.recording)

    def _flush_stream(self, buffer: _StreamBuffer) -> None:
        root = buffer.root
        blocks = buffer.blocks
        if buffer.rows:
            blocks.append(_packed(buffer.rows))
            buffer.rows.clear()
        buffer.blocks, buffer.packed = [], 0
        n = sum(len(block) for block in blocks) // _FIELDS
        if n:
            data = np.concatenate(blocks).reshape(n, _FIELDS)
            t, rx = data[:, _T], data[:, _RX]
            euler = data[:, _EULER]
            index = self._index(t, rx)
            angle = np.degrees(euler)
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                self._send(f"{root}/attitude/{axis}/mavest", index, angle[:, i])
            # Uncertainty and bias change slowly: at up to slow_rate, from those samples only.
            slow_rows, buffer.slow = buffer.slow, []
            slow = np.fromiter((row for row, _ in slow_rows), np.intp, len(slow_rows))
            estimates = [estimate for _, estimate in slow_rows]
            if len(slow):
                slow_index = self._index(t[slow], rx[slow])
                covariance = np.array([estimate.cov for estimate in estimates])
                q = np.array([estimate.q for estimate in estimates])
                sigma = euler_sigmas(q, covariance[:, :3, :3], buffer.error)
                band = 3.0 * np.degrees(sigma)
                for i, axis in enumerate(("roll", "pitch", "yaw")):
                    bounds = np.column_stack(
                        [angle[slow, i] + band[:, i], angle[slow, i] - band[:, i]]
                    )
                    self._send(f"{root}/attitude/{axis}/mavest_3sigma", slow_index, bounds)
                bias = np.degrees(np.array([estimate.bias for estimate in estimates]))
                bias_variance = np.diagonal(covariance[:, 3:, 3:], axis1=1, axis2=2)
                bias_sigma = np.degrees(np.sqrt(np.maximum(bias_variance, 0.0)))
                for i, axis in enumerate("xyz"):
                    series = np.column_stack(
                        [bias[:, i], bias[:, i] + bias_sigma[:, i], bias[:, i] - bias_sigma[:, i]]
                    )
                    self._send(f"{root}/bias/{axis}", slow_index, series)
                self._send_update(root, data, estimates, slow, slow_index)
            self._send(f"{root}/imu/gyro", index, np.degrees(data[:, _GYRO]))
            self._send(f"{root}/imu/accel", index, data[:, _ACCEL])
            self._send(f"{root}/timing/processing_us", index, 1e6 * data[:, _PROCESSING])
            self._send_events(root, data)
            pose_rows, buffer.poses = buffer.poses, []
            posed = [row for row, _ in pose_rows]
            self._send_poses(buffer, "mavest", t[posed], np.array([q for _, q in pose_rows]))
            buffer.anchor = (t[-1], *euler[-1])
        for source, references in buffer.references.items():
            if not references.rows:
                continue
            kept = np.array(references.rows)  # t, receive, roll, pitch, yaw, slow, pose
            references.rows.clear()
            posed = kept[kept[:, 6] != 0]
            self._send_poses(buffer, source, posed[:, 0], so3.quats_from_euler_zyx(posed[:, 2:5]))
            # a reference at the IMU rate (a simulator's truth) is plotted at up to slow_rate
            data = kept[kept[:, 5] != 0]
            if not len(data):
                continue
            receive = data[:, 1] if np.all(data[:, 1] > 0) else None
            reference_index = self._index(data[:, 0], receive)
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                self._send(
                    f"{root}/attitude/{axis}/{source}",
                    reference_index,
                    np.degrees(data[:, 2 + i]),
                )
            if n:
                self._send_differences(buffer, source, t, euler, data)

    def _send_update(
        self,
        root: str,
        data: np.ndarray,
        estimates: list[Any],
        slow: np.ndarray,
        slow_index: list[rr.TimeColumn],
    ) -> None:
        """The accelerometer update, per ``slow_rate`` slot (``slow``: each slot's first row
        in ``data``, ``estimates`` its estimate)."""
        innovation = np.array([estimate.innovation for estimate in estimates])
        self._send(f"{root}/innovation", slow_index, np.degrees(innovation))
        ts, rxs = data[slow, _T], data[slow, _RX]
        nis = np.fromiter((estimate.nis for estimate in estimates), float, len(estimates))
        measured = np.isfinite(nis)
        if np.any(measured):
            self._send(f"{root}/nis/value", self._index(ts[measured], rxs[measured]), nis[measured])
        ends = [0, len(slow) - 1] if len(slow) > 1 else [0]  # a constant band: its ends
        self._send(
            f"{root}/nis/chi2_band",
            self._index(ts[ends], rxs[ends]),
            np.tile([CHI2_2_LOW, CHI2_2_HIGH], (len(ends), 1)),
        )
        used = data[:, _USED]
        flags = data[:, _FLAGS].astype(np.int64)
        disturbed = ((flags & StepFlags.ACCEL_DISTURBED) != 0).astype(float)
        updates = ((flags & StepFlags.BETWEEN_UPDATES) == 0).astype(float)
        # fractions of each slot's update samples (the others measure nothing), for the
        # slots that hold one; the first slot may have begun in the previous batch
        counts = np.add.reduceat(updates, slow)
        holds = counts > 0
        shares = np.column_stack([np.add.reduceat(used, slow), np.add.reduceat(disturbed, slow)])
        fractions = shares[holds] / counts[holds, None]
        if np.any(holds):
            self._send(f"{root}/accel", self._index(ts[holds], rxs[holds]), fractions)

    def _send_events(self, root: str, data: np.ndarray) -> None:
        """What the filter's health checks did, as log lines at the samples they did it."""
        flags = data[:, _FLAGS].astype(np.int64)
        if not np.any(flags & _EVENT_BITS):
            return
        events = sorted(
            (row, level, text)
            for bit, level, text in _EVENTS
            for row in np.flatnonzero(flags & bit)
        )
        rows = np.array([row for row, _, _ in events])
        rr.send_columns(
            f"{root}/events",
            indexes=self._index(data[rows, _T], data[rows, _RX]),
            columns=rr.TextLog.columns(
                text=[text for _, _, text in events], level=[level for _, level, _ in events]
            ),
            recording=self.recording,
        )

    def _send_differences(
        self,
        buffer: _StreamBuffer,
        source: str,
        t: np.ndarray,
        euler: np.ndarray,
        references: np.ndarray,
    ) -> None:
        """Ours minus theirs at their times, ours interpolated between the samples around.

        References later than this batch's last estimate are left out (rare: a
        reference arriving before the IMU sample of its time); earlier ones down to
        the previous batch's last estimate are covered by its anchor.
        """
        times = t
        angles = euler
        if buffer.anchor is not None and buffer.anchor[0] < t[0]:
            times = np.concatenate([[buffer.anchor[0]], t])
            angles = np.vstack([buffer.anchor[1:], euler])
        inside = (references[:, 0] >= times[0]) & (references[:, 0] <= times[-1])
        if not np.any(inside):
            return
        at = references[inside, 0]
        unwrapped = np.unwrap(angles, axis=0)
        ours = np.column_stack([np.interp(at, times, unwrapped[:, i]) for i in range(3)])
        difference = ours - references[inside, 2:5]
        difference[:, [0, 2]] = wrap_angles(difference[:, [0, 2]])
        index = self._index(at, None)
        for i, axis in enumerate(("roll", "pitch", "yaw")):
            self._send(
                f"{buffer.root}/error/{axis}/vs_{source}", index, np.degrees(difference[:, i])
            )

    def _send_poses(self, buffer: _StreamBuffer, body: str, t: np.ndarray, q: np.ndarray) -> None:
        """Body poses, already thinned to ``pose_rate`` (3-D needs no more than the eye
        sees); ``q``: (N, 4) w, x, y, z. The body's shapes go first, once."""
        if body not in buffer.bodies:
            buffer.bodies.add(body)
            self._log_body(buffer, body)
        if not len(t):
            return
        rr.send_columns(
            f"world/{buffer.root}/{body}/attitude",
            indexes=[rr.TimeColumn(VEHICLE_TIME, duration=t)],
            columns=rr.Transform3D.columns(quaternion=q[:, [1, 2, 3, 0]]),  # x, y, z, w
            recording=self.recording,
        )

    def flush(self) -> None:
        for buffer in self._streams.values():
            self._flush_stream(buffer)
        self._last_flush = time.monotonic()

    def close(self) -> None:
        """Send what is buffered (the recording stream itself is closed by its owner)."""
        self.flush()


def _packed(rows: list[tuple[float, ...]]) -> np.ndarray:
    """Sample rows as one flat float array (row after row)."""
    return np.fromiter(chain.from_iterable(rows), float, len(rows) * _FIELDS)
