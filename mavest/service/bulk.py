"""The replay's fast path: runs of clean tlog records through the pipeline at once.

:class:`~mavest.service.pipeline.Pipeline` takes one message at a time, which
is what a live link gives; a replay has the whole file and pays pymavlink's
tens of µs per message for nothing. :class:`BulkFeed` does what the pipeline
would do for the records of a clean stretch (:meth:`TlogReader.scan`), with the
same state (streams, clocks, estimators, comparisons, encoders' sequence
numbers, the output tlog, the Rerun recorder), in compiled loops over arrays:

* IMU samples of the stream being estimated are decoded in bulk, and a
  stretch of them that the pipeline would take plainly (valid values, the
  clock's plain next sample, no airspeed correction, which needs the bias
  sample by sample) goes through :meth:`Estimator.update_batch`. The GPS and
  airspeed messages among them are decoded in bulk and followed on a copy of the
  vehicle's aiding state to give each sample the inputs the pipeline would give it;
* a step after which those inputs may change (heading set or lost, a
  re-initialisation) ends the batch: the samples after it are taken again;
* SIMSTATE truth and the autopilot's ATTITUDE go into the comparisons with the
  estimates, in order; the vehicle's GPS and airspeed messages change its aiding
  state, each at the vehicle time where it stands (the same rules, on the fields
  decoded in bulk); others' GPS and airspeed, and a HEARTBEAT that changes
  nothing the stretch depends on, go through :meth:`Pipeline.on_message` in
  their place between the steps;
* the answers are packed in bulk and written with the input records, each
  after its IMU record, as the pipeline writes them, and our HEARTBEAT after
  the record where the replay loop would send it;
* anything else (a sample the clock or the checks single out, a new stream,
  a new vehicle's HEARTBEAT, PARAM_VALUE, …) is one record through
  :meth:`Pipeline.on_message`, decoded by pymavlink, where it stands.

It applies the pipeline's rules by calling them (the table in
:mod:`mavest.service.pipeline` names each one's home), on a block's arrays where
the rule takes them (:func:`~mavest.service.pipeline.count_estimated`,
:func:`~mavest.service.pipeline.answerable`, …) and on the few steps that are news
one at a time (:func:`~mavest.service.pipeline.book_step`). What is its own is
how it holds the pipeline's state across a block: each record's place among the
estimates gives the time the pipeline would hold there (:func:`_time_at`), which
times the truth, the autopilot's ATTITUDE and the aiding messages as
``Vehicle.last_t`` and ``StreamStats.last_t`` do.

So the outcome is the pipeline's, byte for byte: ``tests/test_bulk.py``
replays files both ways (clean and damaged, rebooting, with GPS, airspeed,
magnetometer and truth, the shared real tlogs) and compares the output tlogs,
every counter and the recordings.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np

from mavest.estimator.layout import StepFlags
from mavest.evaluation.online import ESTIMATE, REFERENCE
from mavest.mavlink import bulk, framing, wire
from mavest.mavlink.messages import (
    IMU_FORMATS,
    IMU_MESSAGES,
    MAVLink,
    StreamKey,
    is_mavlink1,
    mavlink2,
    time_boot_ms_many,
)
from mavest.mavlink.tlog import TlogWriter
from mavest.service.aiding import airspeed_fresh, gps_acceleration_at
from mavest.service.pipeline import (
    AIDING_FIELDS,
    AidingFields,
    ImuRoute,
    Pipeline,
    Stream,
    Vehicle,
    answerable,
    answers_due,
    autopilot_restarted,
    autopilot_time,
    book_step,
    count_estimated,
    heading_source_due,
    heartbeats_after,
    is_fixed_wing,
    is_news,
    reject_sample,
    report_accel_unit,
    report_clipped,
    usable_mag,
    usable_reference,
    valid_sample,
)

# What a record is to the pipeline (by message id).
PASSIVE = 0  # not decoded: copied to the output tlog only
IMU = 1
TRUTH = 2  # SIMSTATE
# Decoded in bulk, taken in its place among the steps: GPS and airspeed change only
# the aiding state, which the fast path follows (a copy of it decides each sample's
# inputs); the autopilot's attitude goes into the comparison with the estimates.
INLINE = 3
OTHER = 4  # decoded and handled one at a time, ending the stretch
# A vehicle's HEARTBEAT: handled where it stands like INLINE when it changes nothing
# the stretch depends on (the vehicle is known and stays a fixed wing or not), else
# it ends the stretch like OTHER.
BEAT = 5

_INLINE_MESSAGES = (*AIDING_FIELDS, "ATTITUDE")
_ATTITUDE = mavlink2.MAVLINK_MSG_ID_ATTITUDE
_HEARTBEAT = mavlink2.MAVLINK_MSG_ID_HEARTBEAT
# the fields taken of each message AIDING_FIELDS names, by its id; and its wire type
_AIDING_TAKEN = {
    getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"): fields for name, fields in AIDING_FIELDS.items()
}
_AIDING_DTYPES = {
    message_id: bulk.wire_dtype(mavlink2.mavlink_map[message_id]) for message_id in _AIDING_TAKEN
}

_SIMSTATE = mavlink2.MAVLINK_MSG_ID_SIMSTATE
_IMU_IDS = {getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"): name for name in IMU_MESSAGES}
_SIMSTATE_DTYPE = bulk.wire_dtype(mavlink2.mavlink_map[_SIMSTATE])
_IMU_DTYPES = {
    message_id: bulk.wire_dtype(mavlink2.mavlink_map[message_id]) for message_id in _IMU_IDS
}

# Samples per part of a batch: the filter runs one part on its thread while the
# replay takes the part before (books, compares, packs and writes it). The first part
# is smaller, as the replay waits for it; each after it half as large again as the
# one before, up to _PART: the replay takes a part in about one and a half times the
# filter's time for as many samples, so the next part is ready about when the replay
# wants it (parts twice the one before kept it waiting 34 ms over a 300 s 1 kHz tlog,
# tools/replay_split.py's; 20 ms so, nearly all of it for first parts). Each part
# costs the replay over half a millisecond whatever its size, so parts are large:
# 1024 samples first made that replay 35 ms slower. With sinks (a recording), at most
# about a second of the stream's samples: they take the estimates a part at a time,
# and the recording's disk is checked after each.
_FIRST_PART = 2048
_PART = 8192
_PART_SECONDS = 1.0

# Samples whose aiding is decided at once: the batch ends at the first that needs the
# airspeed correction, and the samples decided past it are decided again.
_AIDING_WINDOW = 1024

# A step with one of these may change whether heading is referenced (and so whether
# GPS aiding applies to the next sample): a batch is cut after it.
_REGIME_EVENTS = (
    StepFlags.INITIALISED
    | StepFlags.GAP_REALIGNED
    | StepFlags.HEADING_ALIGNED
    | StepFlags.HEADING_REOPENED
    | StepFlags.MAG_REFERENCE_CHANGED
    | StepFlags.TILT_REOPENED
    | StepFlags.UNHEALTHY_RESET
    | StepFlags.DIVERGED
    | StepFlags.CLIP_REALIGNED
    | StepFlags.SKIPPED
)


def record_kinds(wanted: frozenset[int]) -> np.ndarray:
    """Per message id, what the pipeline does with it (PASSIVE … OTHER)."""
    kinds = np.zeros(framing.CRC_EXTRA.shape[0], dtype=np.int8)
    for message_id in wanted:
        kinds[message_id] = OTHER
    for name in _INLINE_MESSAGES:
        message_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")
        if message_id in wanted:
            kinds[message_id] = INLINE
    if _HEARTBEAT in wanted:
        kinds[_HEARTBEAT] = BEAT
    for message_id in _IMU_IDS:
        kinds[message_id] = IMU
    if _SIMSTATE in wanted:
        kinds[_SIMSTATE] = TRUTH
    return kinds


def usable(pipeline: Pipeline) -> bool:
    """Whether the fast path gives this pipeline's outcome: every sink takes estimates
    in bulk too (the Rerun recorder does), nothing is signed, nothing is sent on a link."""
    return (
        all(hasattr(sink, "on_estimates") for sink in pipeline.sinks)
        and pipeline.signing is None
        and not pipeline.links
    )


class _Decoded:
    """The IMU and SIMSTATE records of a run, decoded, one row per record of the run."""

    def __init__(self, data: np.ndarray, records: framing.RecordIndex, kinds: np.ndarray) -> None:
        n = len(records)
        self.kind = kinds[records.message_id]
        self.gyro = np.empty((n, 3))
        self.accel = np.empty((n, 3))
        self.mag = np.empty((n, 3))
        self.ticks = np.zeros(n, dtype=np.int64)
        self.tick = np.zeros(n)
        self.mag_fresh = np.zeros(n, dtype=bool)
        self.inertial_fresh = np.zeros(n, dtype=bool)
        self.saturated = np.zeros(n, dtype=bool)
        self.instance = np.zeros(n, dtype=np.int64)
        self.truth = np.empty((n, 3))
        for message_id, name in _IMU_IDS.items():
            rows = np.flatnonzero(records.message_id == message_id)
            if not rows.shape[0]:
                continue
            payloads = bulk.decode_payloads(data, records.part(rows), _IMU_DTYPES[message_id])
            fields = bulk.imu_fields(name, payloads)
            self.ticks[rows] = fields.ticks
            self.tick[rows] = IMU_FORMATS[name].time_scale
            self.gyro[rows] = fields.gyro
            self.accel[rows] = fields.accel
            self.mag[rows] = fields.mag
            self.mag_fresh[rows] = fields.mag_fresh
            self.inertial_fresh[rows] = fields.inertial_fresh
            self.saturated[rows] = fields.saturated
            self.instance[rows] = fields.instance
        rows = np.flatnonzero(self.kind == TRUTH)
        if rows.shape[0]:
            payloads = bulk.decode_payloads(data, records.part(rows), _SIMSTATE_DTYPE)
            self.truth[rows] = bulk.simstate_euler(payloads)
        # the fields of GPS and airspeed messages that the aiding state takes
        # (AIDING_FIELDS), a column each, as on the wire (pymavlink's numbers: ints, and
        # float32 widened exactly)
        self.aiding: dict[str, np.ndarray] = {}
        for message_id, fields in _AIDING_TAKEN.items():
            dtype = _AIDING_DTYPES[message_id]
            for field in fields:
                wide = np.float64 if dtype[field].kind == "f" else np.int64
                self.aiding[field] = np.zeros(n, dtype=wide)
            rows = np.flatnonzero(records.message_id == message_id)
            if not rows.shape[0] or kinds[message_id] != INLINE:
                continue
            payloads = bulk.decode_payloads(data, records.part(rows), dtype)
            for field in fields:
                self.aiding[field][rows] = payloads[field]
        # the autopilot's ATTITUDE: its time_boot_ms and angles (float32 widened exactly)
        self.attitude_ms = np.zeros(n, dtype=np.int64)
        self.attitude = np.empty((n, 3))
        rows = np.flatnonzero(records.message_id == _ATTITUDE)
        if rows.shape[0] and kinds[_ATTITUDE] == INLINE:
            payloads = bulk.decode_payloads(data, records.part(rows), bulk.ATTITUDE_DTYPE)
            self.attitude_ms[rows] = payloads["time_boot_ms"]
            self.attitude[rows] = bulk.simstate_euler(payloads)  # (its roll, pitch, yaw)


# What the pipeline does with an IMU record, by its stream.
_ESTIMATED = 0  # the stream estimated in bulk
_PASSED_BY = 1  # a stream not followed (or a HIGHRES_IMU without fresh data): nothing
_ALONE = 2  # a new stream, another system, a second followed stream: one at a time


class _Steps:
    """Samples estimated in bulk: their rows in the run and what the estimator gave."""

    def __init__(
        self,
        rows: np.ndarray,
        series: Any,
        usable_mag: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        processing: float,
        accel_unit_problem: str | None,
    ) -> None:
        self.rows = rows
        self.series = series
        self.accel = accel  # as the sample carried it (for the recording)
        self.processing = processing  # s per sample: the batch's time divided among them
        self.t = series.t
        self.q = series.q
        # ZYX angles, once: the comparisons, the recording and the answers all take them
        self.euler = bulk.euler_rows(series.q)
        self.bias = series.bias
        self.flags = series.flags
        self.usable_mag = usable_mag
        self.gyro = gyro  # for the answers' rates
        # Estimator.accel_unit_problem after the steps: read on the filter's thread, which
        # is on to the next part by the time they are booked
        self.accel_unit_problem = accel_unit_problem


class BulkFeed:
    """Feeds runs of clean records to a pipeline, as the replay would one by one."""

    def __init__(
        self,
        pipeline: Pipeline,
        data: np.ndarray,
        wanted: frozenset[int],
        tlog: TlogWriter | None,
        after_stretch: Callable[[], None] | None = None,
    ) -> None:
        self.pipeline = pipeline
        pipeline.batch_fed = True
        self.data = data
        self.tlog = tlog
        # called after each stretch taken in bulk (and each second of it, where our
        # HEARTBEATs go out), as the replay loop calls its checks (the recording's disk
        # space) every few hundred records
        self.after_stretch = after_stretch
        self.kinds = record_kinds(wanted)  # per message id: PASSIVE … OTHER
        self._mav = MAVLink(None)  # decodes the records handled one at a time
        self.bulk_samples = 0  # IMU samples estimated in bulk (for the tests)
        self._decoded: dict[int, Any] = {}  # row → message, within one feed
        # mavest's HEARTBEAT, sent after the first record at or past the time it is due,
        # then due a period after that record (µs of record time; period 0: never)
        self._beat_period_us = 0
        self._next_beat_us = 0
        self._executor: ThreadPoolExecutor | None = None  # the filter's thread

    def feed(
        self, records: framing.RecordIndex, beat_period_us: int = 0, next_beat_us: int = 0
    ) -> int:
        """Handle these records (clean, in file order) as the replay loop would, with
        a HEARTBEAT of ours after a record once one is due (as the loop sends them).
        Returns when the next one is due."""
        self._beat_period_us = beat_period_us
        self._next_beat_us = next_beat_us
        decoded = _Decoded(self.data, records, self.kinds)
        self._decoded.clear()
        cuts = np.flatnonzero(decoded.kind == OTHER)
        start = 0
        while start < len(records):
            start = self._run(records, decoded, cuts, start)
        return self._next_beat_us

    def _beats(self, stamps: np.ndarray) -> list[int]:
        """Of records with these times (handled in bulk, in order), those after which a
        HEARTBEAT of ours goes out; moves the next one's due time past them."""
        if not self._beat_period_us or not self.pipeline.vehicles:
            return []  # (a vehicle comes only with a record handled alone)
        beats, self._next_beat_us = heartbeats_after(
            stamps, self._next_beat_us, self._beat_period_us
        )
        return beats

    # ---------------------------------------------------------------- one run

    def _run(
        self, records: framing.RecordIndex, decoded: _Decoded, cuts: np.ndarray, start: int
    ) -> int:
        """Handle records from ``start``: a stretch in bulk, or one record alone.
        Returns where the next run starts."""
        following = int(np.searchsorted(cuts, start))
        end = int(cuts[following]) if following < cuts.shape[0] else len(records)
        imu_rows = start + np.flatnonzero(decoded.kind[start:end] == IMU)
        status, stream = self._imu_status(records, decoded, imu_rows)
        alone = imu_rows[status == _ALONE]
        if alone.shape[0]:
            end = int(alone[0])
        end = self._truth_end(records, decoded, start, end, stream)
        end = self._beats_end(records, decoded, start, end)
        if end == start:
            self._alone(records, start)
            return start + 1
        rows = imu_rows[(imu_rows < end) & (status == _ESTIMATED)]
        if stream is None or not rows.shape[0]:
            self._take(records, decoded, start, end, stream)
            return end
        return self._estimate(records, decoded, start, end, rows, stream)

    def _imu_status(
        self, records: framing.RecordIndex, decoded: _Decoded, rows: np.ndarray
    ) -> tuple[np.ndarray, Stream | None]:
        """Per IMU record, what the pipeline does with it (Pipeline.route_imu, once per
        stream and freshness); the stream estimated in bulk."""
        status = np.full(rows.shape[0], _ALONE, dtype=np.int8)
        if not rows.shape[0]:
            return status, None
        pipeline = self.pipeline
        # one integer per (system, component, message, instance)
        code = (
            (records.system[rows] << 40)
            | (records.component[rows] << 32)
            | (records.message_id[rows] << 8)
            | (decoded.instance[rows] & 0xFF)
        )
        fresh = decoded.inertial_fresh[rows]
        stream: Stream | None = None
        for value in _distinct(code):  # (nearly always one stream)
            key = StreamKey(
                (value >> 40) & 0xFF,
                (value >> 32) & 0xFF,
                _IMU_IDS[(value >> 8) & 0xFFFFFF],
                value & 0xFF,
            )
            mine = code == value
            for is_fresh in (False, True):
                route, known = pipeline.route_imu(key, is_fresh)
                these = mine & (fresh == is_fresh)
                if route is ImuRoute.PASSED_BY:
                    status[these] = _PASSED_BY
                elif route is ImuRoute.ESTIMATED and (stream is None or known is stream):
                    stream = known
                    status[these] = _ESTIMATED
                # else the pipeline's own, one at a time: ignored (it counts them), new,
                # or a second stream estimated
        return status, stream

    def _truth_end(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        start: int,
        end: int,
        stream: Stream | None,
    ) -> int:
        """``end``, or the first SIMSTATE before it that is not the bulk stream's truth."""
        truth_rows = start + np.flatnonzero(decoded.kind[start:end] == TRUTH)
        if not truth_rows.shape[0]:
            return end
        pipeline = self.pipeline
        foreign = np.ones(truth_rows.shape[0], dtype=bool)
        if stream is not None and stream.primary:
            for system in _distinct(records.system[truth_rows]):
                # the vehicle a SIMSTATE is for, as Pipeline.on_message finds it
                vehicle = pipeline.truth_vehicle(system)
                if vehicle is not None and vehicle.primary == stream.key:
                    foreign[records.system[truth_rows] == system] = False
        if foreign.any():
            return int(truth_rows[np.argmax(foreign)])
        return end

    def _beats_end(
        self, records: framing.RecordIndex, decoded: _Decoded, start: int, end: int
    ) -> int:
        """``end``, or the first HEARTBEAT before it that changes what the pipeline knows
        of a vehicle (a new one, its fixed wing, its MAVLink version), which the stretch
        depends on."""
        pipeline = self.pipeline
        for row in (start + np.flatnonzero(decoded.kind[start:end] == BEAT)).tolist():
            message = self._decode(records, row)
            header = message._header
            system, component = header.srcSystem, header.srcComponent
            if pipeline.is_ours(system, component) or not pipeline.is_vehicles_heartbeat(
                system, message
            ):
                continue  # Pipeline.on_message leaves it there
            vehicle = pipeline.vehicles.get((system, component))
            if (
                vehicle is None
                or vehicle.fixed_wing != is_fixed_wing(message.type)
                or vehicle.mavlink1 != is_mavlink1(message)  # what our HEARTBEAT speaks
            ):
                return row
        return end

    def _packet(self, records: framing.RecordIndex, row: int) -> bytes:
        return self.data[int(records.start[row]) + 8 : int(records.end[row])].tobytes()

    def _decode(self, records: framing.RecordIndex, row: int) -> Any:
        """The message of a record handled one at a time (each decoded once per feed)."""
        message = self._decoded.get(row)
        if message is None:
            packet = self._packet(records, row)
            # the scan checked the record: a one-packet "datagram" (the messages
            # pymavlink's decode makes), unless the message has arrays or text
            messages = wire.decode_datagram(packet)
            message = messages[0] if messages else self._mav.decode(bytearray(packet))
            self._decoded[row] = message
        return message

    def _alone(self, records: framing.RecordIndex, row: int) -> None:
        """One record the way the replay loop takes it: written, decoded, handled, and
        a HEARTBEAT of ours after it if one is due."""
        stamp = int(records.stamp[row])
        if self.tlog is not None:
            self.tlog.write(stamp, self._packet(records, row))
        self.pipeline.on_message(self._decode(records, row), stamp)
        if self._beats(records.stamp[row : row + 1]):
            self.pipeline.heartbeat()

    # ---------------------------------------------------------------- estimation

    def _estimate(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        start: int,
        end: int,
        rows: np.ndarray,
        stream: Stream,
    ) -> int:
        """Estimate the leading plain samples of ``rows`` in bulk, or let the first go
        alone if it is not plain. Returns where the next run starts."""
        began = time.perf_counter()
        gyro, accel = decoded.gyro[rows], decoded.accel[rows]
        time_s = decoded.ticks[rows] * decoded.tick[rows]
        valid = valid_sample(tuple(gyro.T), tuple(accel.T), decoded.saturated[rows], time_s)
        plain = int(np.argmin(valid)) if not valid.all() else rows.shape[0]
        tick = float(decoded.tick[rows[0]])
        ticks = decoded.ticks[rows[:plain]]
        t = stream.clock.read_run(ticks, tick)
        linear_accel, needs_airspeed = self._aiding(records, decoded, start, stream, rows, t)
        count = int(np.argmax(needs_airspeed)) if needs_airspeed.any() else t.shape[0]
        # (the answers end at the first sample that needs airspeed, if one does)
        if count == 0:  # records before the sample in bulk, the sample alone
            first = int(rows[0])
            self._take(records, decoded, start, first, stream)
            self._alone(records, first)
            return first + 1
        mag = decoded.mag[rows[:count]]
        mag_usable = decoded.mag_fresh[rows[:count]] & usable_mag(tuple(mag.T))
        mag[~mag_usable] = math.nan
        # The batch in parts, each run on the filter's thread while this one takes the
        # part before (the compiled filter does not hold the interpreter). Exact: the
        # parts run in order, as consecutive batches would, on inputs all decided
        # already; meanwhile this thread touches the clock and what it takes, never
        # the estimator.
        plain_count = count
        inputs = (t[:count], gyro[:count], accel[:count], mag, linear_accel[:count])
        worker = self._worker()
        most = _PART
        if self.pipeline.sinks:
            most = min(most, max(64, round(_PART_SECONDS * stream.rate)))
        size = min(_FIRST_PART, most)
        part = worker.submit(self._update, stream, *_part(inputs, 0, size, plain_count))
        done = 0  # samples estimated
        taken = start  # records taken
        while True:
            series, count, cut, accel_unit_problem = part.result()
            first, done = done, done + count
            if stream.inputs is not None:  # kept to be smoothed (as the pipeline keeps them)
                stream.inputs.add_many(*(x[first:done] for x in inputs), series.flags[:count])
            ended = cut or done == plain_count
            if not ended:
                size = min(size * 3 // 2, most)
                inputs_after = _part(inputs, done, size, plain_count)
                part = worker.submit(self._update, stream, *inputs_after)
            stream.clock.take_run(ticks[first:], tick, count)
            self.bulk_samples += count
            stop = int(rows[done]) if done < rows.shape[0] else end
            now = time.perf_counter()
            processing, began = (now - began) / count, now
            steps = _Steps(
                rows[first:done],
                series,
                mag_usable[first:done],
                gyro[first:done],
                accel[first:done],
                processing,
                accel_unit_problem,
            )
            self._take(records, decoded, taken, stop, stream, steps)
            taken = stop
            if ended:
                break
        count = done
        if count == plain_count and count < rows.shape[0]:
            # the sample after the batch is not plain (or needs airspeed): it goes
            # alone now, as the next run would send it (without looking ahead again)
            self._alone(records, stop)
            return stop + 1
        return stop

    def _worker(self) -> ThreadPoolExecutor:
        """The thread the filter runs on (one: the parts of a batch run in order)."""
        if self._executor is None:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="mavest-filter")
        return self._executor

    def close(self) -> None:
        """End the filter's thread (the feed takes nothing more)."""
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None

    def _update(
        self,
        stream: Stream,
        t: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        mag: np.ndarray,
        linear_accel: np.ndarray,
        last: bool,
    ) -> tuple[Any, int, bool, str | None]:
        """Run the estimator over the samples (the ``last`` part of a batch, or not), up
        to and including the first whose step may change what the next sample's inputs
        are (whether GPS aiding applies): (the estimates, how many, whether the batch
        ends there, the estimator's accelerometer-unit problem after them)."""
        estimator = stream.estimator
        before = estimator.snapshot()
        series = estimator.update_batch(t, gyro, accel, mag, linear_accel)
        # (after the batch's last step the next inputs are decided anew anyway)
        events = np.flatnonzero(series.flags[: -1 if last else None] & _REGIME_EVENTS)
        count, cut = t.shape[0], False
        if events.shape[0]:
            count, cut = int(events[0]) + 1, True  # later steps took inputs decided too early
            if count < t.shape[0]:
                estimator.restore(before)
                series = estimator.update_batch(
                    t[:count], gyro[:count], accel[:count], mag[:count], linear_accel[:count]
                )
        return series, count, cut, estimator.accel_unit_problem

    def _aiding(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        start: int,
        stream: Stream,
        rows: np.ndarray,
        t: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per sample, the known acceleration (NaN rows: none) and whether the airspeed
        correction applies, as the pipeline would decide them: GPS and airspeed
        messages among the samples are followed on a copy of the vehicle's state,
        each at the time of the sample before it.

        Decided a window of samples at a time, up to the window with the first sample
        that needs the airspeed correction (the batch ends before it: what comes after
        is decided again, from the state the pipeline then has); so the answers may be
        shorter than ``t``."""
        pipeline = self.pipeline
        vehicle = pipeline.vehicles[(stream.key.system, stream.key.component)]
        n = t.shape[0]
        rows = rows[:n]
        end = int(rows[n - 1]) if n else start
        messages = _aiding_rows(records, decoded, start, end, vehicle)
        message_ids = records.message_id[messages]
        times = _as_times(_time_at(rows, t, messages, vehicle.last_t))
        state = copy.copy(vehicle)
        state.gps = copy.copy(vehicle.gps)
        gps_aiding = pipeline.gps_aiding(stream)
        airspeed_aiding = pipeline.airspeed_aiding(vehicle)
        linear_accel = np.full((n, 3), math.nan)
        needs_airspeed = np.zeros(n, dtype=bool)
        decided = 0  # samples
        followed = 0  # messages
        while decided < n:
            window = slice(decided, min(n, decided + _AIDING_WINDOW))
            upto = int(np.searchsorted(messages, rows[window.stop - 1]))  # messages before
            part = slice(followed, upto)
            history = _follow_many(state, decoded, message_ids[part], messages[part], times[part])
            met = np.searchsorted(messages[part], rows[window])  # the state each sample meets
            if gps_aiding:
                linear_accel[window] = gps_acceleration_at(
                    history.accel[met], history.accel_t[met], history.fix_t[met], t[window]
                )
            if airspeed_aiding:
                unknown = np.isnan(linear_accel[window, 0])
                fresh = airspeed_fresh(t[window], history.airspeed_t[met])
                needs_airspeed[window] = unknown & fresh
                if needs_airspeed[window].any():
                    return linear_accel[: window.stop], needs_airspeed[: window.stop]
            decided, followed = window.stop, upto
        return linear_accel, needs_airspeed

    # ---------------------------------------------------------------- the outcome

    def _take(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        start: int,
        stop: int,
        stream: Stream | None,
        steps: _Steps | None = None,
    ) -> None:
        """Records [start, stop) as the pipeline takes them, in order: the steps booked
        and compared with the truth and the autopilot's ATTITUDE between them, each GPS
        or airspeed message handled where it stands; then the answers packed and all of
        it written to the output tlog, with our HEARTBEATs where they fall due."""
        if stop <= start:
            return
        pipeline = self.pipeline
        record_us_before = pipeline.record_us
        kind = decoded.kind[start:stop]
        # (every HEARTBEAT here is one that changes nothing the stretch depends on)
        inline = start + np.flatnonzero((kind == INLINE) | (kind == BEAT))
        # The autopilot's ATTITUDE goes into the comparisons with the steps, in bulk; while
        # no stream is known, alone (the pipeline notes what it hears before any IMU).
        attitudes = inline[records.message_id[inline] == _ATTITUDE]
        if pipeline.streams and attitudes.shape[0]:
            inline = np.setdiff1d(inline, attitudes, assume_unique=True)
        else:
            attitudes = attitudes[:0]
        vehicle = (
            pipeline.vehicles[(stream.key.system, stream.key.component)]
            if stream is not None
            else None
        )
        last_t = vehicle.last_t if vehicle is not None else None  # before the stretch
        estimated_at = (
            np.flatnonzero((steps.flags & StepFlags.SKIPPED) == 0)
            if steps is not None
            else np.empty(0, dtype=np.int64)
        )
        if vehicle is not None:
            # the vehicle's own GPS and airspeed messages change only its aiding state:
            # followed in bulk, each at the vehicle's time where it stands
            followed = _aiding_rows(records, decoded, start, stop, vehicle)
            if followed.shape[0]:
                inline = np.setdiff1d(inline, followed, assume_unique=True)
                times = _vehicle_times(steps, estimated_at, followed, last_t)
                _follow_many(vehicle, decoded, records.message_id[followed], followed, times)
                pipeline.messages_in += followed.shape[0]
        # The rest (others' GPS and airspeed, HEARTBEATs) one by one, each with the
        # vehicle's time where it stands; none of them touches what the steps are booked
        # and compared into, which is done after them.
        times = _vehicle_times(steps, estimated_at, inline, last_t)
        for row, t in zip(inline.tolist(), times, strict=True):
            if vehicle is not None:
                vehicle.last_t = t
            pipeline.on_message(self._decode(records, row), int(records.stamp[row]))
        kept = self._book_and_compare(
            records, decoded, start, stop, stream, steps, attitudes, last_t
        )
        pipeline.messages_in += int((kind == IMU).sum() + (kind == TRUTH).sum())
        pipeline.messages_in += attitudes.shape[0]
        answered = np.empty(0, dtype=np.int64)  # indices of the steps answered
        if stream is not None and steps is not None and stream.primary and kept is not None:
            with_attitude = kept[answerable(steps.flags[kept])]
            rate = self.pipeline.config.output.attitude_rate
            due, stream.next_output = answers_due(steps.t[with_attitude], stream.next_output, rate)
            answered = with_attitude[due]
        answered_rows = steps.rows[answered] if steps is not None else answered
        # Written in pieces, each up to a record after which a HEARTBEAT of ours goes
        # out: its packets take the encoder's sequence numbers between the answers.
        # Packets sent are recorded at the time of the last decoded message before them.
        decoded_rows = start + np.flatnonzero(kind != PASSIVE)
        beats = [start + beat + 1 for beat in self._beats(records.stamp[start:stop])]
        answers = None  # packed for the whole stretch at once, written piece by piece
        if stream is not None and steps is not None and answered.shape[0] and self.tlog is not None:
            answers = self._answers(records, stream, steps, answered, beats)
        piece_start = start
        for piece_end in beats if beats and beats[-1] == stop else [*beats, stop]:
            first, last = np.searchsorted(answered_rows, (piece_start, piece_end))
            if last > first:
                assert stream is not None
                self._answered(stream, int(last - first))
            if self.tlog is not None:
                self._write(
                    records, piece_start, piece_end, answered_rows[first:last], answers, first, last
                )
            last_decoded = int(np.searchsorted(decoded_rows, piece_end)) - 1
            pipeline.record_us = (
                int(records.stamp[decoded_rows[last_decoded]])
                if last_decoded >= 0
                else record_us_before
            )
            if piece_end in beats:
                pipeline.heartbeat()
            piece_start = piece_end
            if self.after_stretch is not None:
                self.after_stretch()

    def _write(
        self,
        records: framing.RecordIndex,
        start: int,
        stop: int,
        answered_rows: np.ndarray,
        answers: tuple[framing.Packets, framing.Packets | None] | None,
        first: int,
        last: int,
    ) -> None:
        """Records [start, stop) to the output tlog, each of ``answered_rows`` followed by
        its answers: rows ``first`` to ``last`` of ``answers``."""
        assert self.tlog is not None
        answer_of = np.full(stop - start, -1, dtype=np.int64)
        if answers is None or last == first:
            packets = (framing.NO_PACKETS, None)
        else:
            answer_of[answered_rows - start] = np.arange(last - first)
            packets = tuple(None if p is None else p.part(slice(first, last)) for p in answers)
        data, ends = bulk.interleave(
            self.data, records.part(slice(start, stop)), answer_of, *packets
        )
        self.tlog.write_records(data, ends)

    def _book_and_compare(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        start: int,
        stop: int,
        stream: Stream | None,
        steps: _Steps | None,
        attitudes: np.ndarray,
        last_t_before: float | None,
    ) -> np.ndarray | None:
        """The steps (those of records [start, stop)) booked, and compared with the truth
        and the autopilot's ATTITUDE (``attitudes``: their rows) among the records, in
        order (``last_t_before``: the vehicle's time before them); the indices of those
        estimated (not skipped), None if there are no steps."""
        kept = None
        index = np.empty(0, dtype=np.int64)
        truth_rows = index
        stream_last_t = None  # the stream's last estimate before the records
        if stream is not None:
            vehicle = self.pipeline.vehicles[(stream.key.system, stream.key.component)]
            vehicle.last_t = last_t_before
            stream_last_t = stream.stats.last_t
            if steps is not None and steps.rows.shape[0]:
                kept = index = self._book(stream, vehicle, steps)
            truth_rows = start + np.flatnonzero(decoded.kind[start:stop] == TRUTH)
            truth_rows = truth_rows[usable_reference(decoded.truth[truth_rows])]
        t = steps.t[index] if steps is not None else np.empty(0)
        euler = steps.euler[index] if steps is not None else np.empty((0, 3))
        rows = steps.rows[index] if steps is not None else index
        autopilot = self._autopilot(records, decoded, attitudes, stream, rows, t, stream_last_t)
        truth_t = np.empty(0)
        if stream is not None:
            scored = (
                answerable(steps.flags[index]) if steps is not None else np.empty(0, dtype=bool)
            )
            truth_t = self._compare(
                stream, decoded, t, euler, rows, scored, truth_rows, last_t_before, autopilot
            )
        for other in autopilot.streams:
            if other is not stream:  # (an ATTITUDE of a stream not estimated here)
                mine = autopilot.of(other)
                references = np.full(int(np.count_nonzero(mine)), REFERENCE)
                other.vs_autopilot.add_many(references, autopilot.t[mine], autopilot.euler[mine])
        if self.pipeline.sinks:
            self._tell_sinks(records, decoded, stream, steps, index, truth_rows, truth_t, autopilot)
        return kept

    def _autopilot(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        rows: np.ndarray,
        stream: Stream | None,
        estimate_rows: np.ndarray,
        estimate_t: np.ndarray,
        last_t: float | None,
    ) -> _Autopilot:
        """The autopilot's ATTITUDE at these rows, as Pipeline.on_message takes each: the
        stream it is compared with (if any), its time and angles. ``stream`` is estimated
        among them: its estimates' rows and times, and its last estimate's time before
        them (``last_t``), say when the autopilot restarted as the pipeline sees it."""
        target = np.full(rows.shape[0], -1, dtype=np.int64)
        streams: list[Stream] = []
        t = autopilot_time(decoded.attitude_ms[rows])
        if not rows.shape[0]:
            return _Autopilot(rows, target, streams, t, decoded.attitude[rows])
        code = (records.system[rows] << 8) | records.component[rows]
        for value in _distinct(code):  # (nearly always one vehicle)
            compared = self.pipeline.autopilot_stream(value >> 8, value & 0xFF)
            if compared is None:
                continue
            mine = np.flatnonzero(code == value)
            before = math.nan if compared.stats.last_t is None else compared.stats.last_t
            if compared is stream:  # its stats.last_t at each
                before = _time_at(estimate_rows, estimate_t, rows[mine], last_t)
            mine = mine[~autopilot_restarted(t[mine], before)]
            mine = mine[usable_reference(decoded.attitude[rows[mine]])]
            known = [k for k, other in enumerate(streams) if other is compared]
            target[mine] = known[0] if known else len(streams)
            if not known:
                streams.append(compared)
        return _Autopilot(rows, target, streams, t, decoded.attitude[rows])

    def _tell_sinks(
        self,
        records: framing.RecordIndex,
        decoded: _Decoded,
        stream: Stream | None,
        steps: _Steps | None,
        index: np.ndarray,
        truth_rows: np.ndarray,
        truth_t: np.ndarray,
        autopilot: _Autopilot,
    ) -> None:
        """The estimates (steps ``index``) and the references compared with them to the
        sinks, in pieces that end at the autopilot's ATTITUDE records: each piece's
        estimates, then its truth, then the ATTITUDE. (A recorder sends what it holds in
        batches, the batch's references beside its estimates: the pieces keep the
        batches those records make when each goes alone.)"""
        sinks = self.pipeline.sinks
        rows = steps.rows[index] if steps is not None else index
        estimate_ends = np.searchsorted(rows, autopilot.rows).tolist()
        truth_ends = np.searchsorted(truth_rows, autopilot.rows).tolist()
        first = first_truth = 0
        for k in range(autopilot.rows.shape[0] + 1):
            last = estimate_ends[k] if k < len(estimate_ends) else rows.shape[0]
            last_truth = truth_ends[k] if k < len(truth_ends) else truth_rows.shape[0]
            if stream is not None and steps is not None and last > first:
                piece = index[first:last]
                for sink in sinks:
                    sink.on_estimates(
                        stream,
                        steps.t[piece],
                        steps.euler[piece],
                        steps.gyro[piece],
                        steps.accel[piece],
                        steps.series.accel_used[piece],
                        steps.flags[piece],
                        steps.q[piece],
                        steps.series,
                        piece,
                        records.stamp[rows[first:last]],
                        steps.processing,
                    )
            if stream is not None and stream.primary:
                truth = truth_rows[first_truth:last_truth]
                truth_at = truth_t[first_truth:last_truth]
                compared = ~np.isnan(truth_at)
                for sink in sinks:
                    sink.on_references(
                        stream,
                        "truth",
                        truth_at[compared],
                        decoded.truth[truth[compared]],
                        records.stamp[truth[compared]],
                    )
            if k < autopilot.target.shape[0] and autopilot.target[k] >= 0:
                other = autopilot.streams[int(autopilot.target[k])]
                t = float(autopilot.t[k])
                euler = tuple(autopilot.euler[k].tolist())
                stamp = int(records.stamp[autopilot.rows[k]])
                for sink in sinks:
                    sink.on_reference(other, "autopilot", t, euler, stamp)
            first, first_truth = last, last_truth

    def _book(self, stream: Stream, vehicle: Vehicle, steps: _Steps) -> np.ndarray:
        """Count and report what the steps did (the pipeline's count_estimated on the
        block, book_step on its news); returns the indices of those estimated (not
        skipped)."""
        stats = stream.stats
        flags = steps.flags
        t = steps.t
        stats.received += flags.shape[0]
        skipped = (flags & StepFlags.SKIPPED) != 0
        kept = np.flatnonzero(~skipped)
        # (only before the filter starts, so before any other news of the stream)
        wrong_unit = int(np.count_nonzero(flags[kept] & StepFlags.ACCEL_WRONG_UNIT))
        if wrong_unit:
            report_accel_unit(stream, wrong_unit, steps.accel_unit_problem)
        # the rare steps that are news, in order, each booked with the stream's last
        # time as it stood before it
        notable = skipped | is_news(flags)
        if not stream.heading_source_reported and kept.shape[0]:
            first_t = stats.first_t if stats.first_t is not None else float(t[kept[0]])
            due = kept[heading_source_due(stream, stats.earlier_span + t[kept] - first_t)]
            if due.shape[0]:
                notable[due[0]] = True
        last_t = stats.last_t
        for index in np.flatnonzero(notable).tolist():
            f = int(flags[index])
            if f & StepFlags.SKIPPED:
                reject_sample(
                    stream, "skipped by the estimator: " + ", ".join(StepFlags.describe(f))
                )
                continue
            earlier = kept[kept < index]
            stats.last_t = float(t[earlier[-1]]) if earlier.shape[0] else last_t
            book_step(stream, f, float(t[index]))
        stats.last_t = last_t
        if not kept.shape[0]:
            return kept
        count_estimated(stats, flags[kept], steps.usable_mag[kept], steps.series.mag_used[kept])
        report_clipped(stream, flags[kept], t[kept])
        if stats.first_t is None:
            stats.first_t = float(t[kept[0]])
        stats.last_t = float(t[kept[-1]])
        vehicle.last_t = stats.last_t
        return kept

    def _compare(
        self,
        stream: Stream,
        decoded: _Decoded,
        t: np.ndarray,
        euler: np.ndarray,
        rows: np.ndarray,
        scored: np.ndarray,
        truth_rows: np.ndarray,
        last_t_before: float | None,
        autopilot: _Autopilot,
    ) -> np.ndarray:
        """Our estimates (at ``rows``; those not ``scored``, before the filter had an
        attitude, as NaN), and the SIMSTATE truth and the autopilot's ATTITUDE between
        them, into the comparisons in the order they came; each truth at the time of the
        last estimate before it, which is returned (NaN: none yet, so not compared)."""
        if not scored.all():
            euler = np.where(scored[:, None], euler, math.nan)
        mine = autopilot.of(stream)
        if mine.any():
            kinds, sort = _in_order(rows, autopilot.rows[mine])
            times = np.concatenate([t, autopilot.t[mine]])[sort]
            angles = np.concatenate([euler, autopilot.euler[mine]])[sort]
            stream.vs_autopilot.add_many(kinds, times, angles)
        elif t.shape[0]:
            stream.vs_autopilot.add_many(np.full(t.shape[0], ESTIMATE), t, euler)
        if not truth_rows.shape[0]:
            if t.shape[0]:
                stream.vs_truth.add_many(np.full(t.shape[0], ESTIMATE), t, euler)
            return np.empty(0)
        # each truth at the vehicle's last_t there (the last estimate's time)
        truth_t = _time_at(rows, t, truth_rows, last_t_before)
        kinds, sort = _in_order(rows, truth_rows)
        euler_all = np.concatenate([euler, decoded.truth[truth_rows]])[sort]
        times = np.concatenate([t, truth_t])[sort]
        use = ~np.isnan(times)  # truth before any estimate of the vehicle: not compared
        stream.vs_truth.add_many(kinds[use], times[use], euler_all[use])
        return truth_t

    def _answers(
        self,
        records: framing.RecordIndex,
        stream: Stream,
        steps: _Steps,
        answered: np.ndarray,
        beats: list[int],
    ) -> tuple[framing.Packets, framing.Packets | None]:
        """ATTITUDE (and ATTITUDE_QUATERNION) for the answered samples, as the pipeline
        packs them, each in the MAVLink version its sample came in, with the encoder's
        sequence numbers from its next one. ``beats``: where the pieces after which a
        HEARTBEAT of ours goes out end; each HEARTBEAT takes one number between the
        answers. The encoder hands the numbers out as they are written
        (:meth:`_answered`)."""
        rows = steps.rows[answered]
        answered = _as_slice(answered)  # (nearly always all: a view of each)
        q = steps.q[answered]
        rates = steps.gyro[answered] - steps.bias[answered]
        stamps = time_boot_ms_many(steps.t[answered])
        encoder = self.pipeline.encoder(stream.key.system)
        with_quaternion = self.pipeline.config.output.attitude_quaternion
        return bulk.attitude_packets(
            stamps,
            steps.euler[answered],
            rates,
            q if with_quaternion else None,
            encoder.system,
            encoder.component,
            encoder.sequence,
            self.data[records.start[rows] + 8] == mavlink2.PROTOCOL_MARKER_V1,
            skips=np.searchsorted(beats, rows, side="right"),
        )

    def _answered(self, stream: Stream, count: int) -> None:
        """``count`` samples' answers sent: the encoder's sequence numbers they take,
        and the counts."""
        pipeline = self.pipeline
        sent = count * bulk.packets_per_answer(pipeline.config.output.attitude_quaternion)
        pipeline.encoder(stream.key.system).take_sequence(sent)
        pipeline.sent += sent
        stream.stats.answered += count


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """Ascending distinct indices, as a slice where they are consecutive (which takes a
    view rather than a copy), else as they are."""
    n = index.shape[0]
    if n and int(index[-1]) - int(index[0]) == n - 1:
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


def _distinct(values: np.ndarray) -> list[int]:
    """The distinct values, ascending; nearly always one, found without sorting."""
    if (values == values[0]).all():
        return [int(values[0])]
    return np.unique(values).tolist()


def _part(inputs: tuple[np.ndarray, ...], start: int, size: int, count: int) -> tuple[Any, ...]:
    """The filter's inputs for the part of a batch of ``count`` samples from ``start``
    (at most ``size``), and whether it is the batch's last part."""
    stop = min(start + size, count)
    return (*(values[start:stop] for values in inputs), stop == count)


def _aiding_rows(
    records: framing.RecordIndex, decoded: _Decoded, start: int, stop: int, vehicle: Vehicle
) -> np.ndarray:
    """Rows [start, stop) of this vehicle's GPS and airspeed messages (decoded in bulk)."""
    inline = start + np.flatnonzero(decoded.kind[start:stop] == INLINE)
    mine = (
        (records.system[inline] == vehicle.system)
        & (records.component[inline] == vehicle.component)
        & (records.message_id[inline] != _ATTITUDE)  # the other INLINE messages: aiding
    )
    return inline[mine]


class _AidingHistory(NamedTuple):
    """A vehicle's aiding state before its GPS and airspeed messages (row 0) and after
    each of them (row k + 1: after the k-th), as the samples meet it."""

    accel: np.ndarray  # (m + 1, 3) m/s² NED; NaN rows: none yet
    accel_t: np.ndarray  # (m + 1,)
    fix_t: np.ndarray
    airspeed_t: np.ndarray


def _follow_many(
    vehicle: Vehicle,
    decoded: _Decoded,
    message_ids: np.ndarray,
    rows: np.ndarray,
    times: list[float | None],
) -> _AidingHistory:
    """What Pipeline.on_message does to a vehicle's aiding state with these GPS and
    airspeed messages (rows of ``decoded``, in order), each at its vehicle time (None:
    no time yet, so it is not taken); the state after each."""
    gps = vehicle.gps
    columns = {field: column[rows].tolist() for field, column in decoded.aiding.items()}
    m = rows.shape[0]
    accel = np.full((m + 1, 3), math.nan)
    accel_t = np.empty(m + 1)
    fix_t = np.empty(m + 1)
    airspeed_t = np.empty(m + 1)
    if gps.accel is not None:
        accel[0] = gps.accel
    accel_t[0], fix_t[0], airspeed_t[0] = gps.accel_t, gps.fix_t, vehicle.airspeed_t
    for k, message_id in enumerate(message_ids.tolist()):
        values = {field: columns[field][k] for field in _AIDING_TAKEN[message_id]}
        vehicle.follow(AidingFields(message_id, **values), times[k])
        if gps.accel is not None:
            accel[k + 1] = gps.accel
        accel_t[k + 1], fix_t[k + 1], airspeed_t[k + 1] = gps.accel_t, gps.fix_t, vehicle.airspeed_t
    return _AidingHistory(accel, accel_t, fix_t, airspeed_t)


class _Autopilot(NamedTuple):
    """The autopilot's ATTITUDE records of a stretch, as the comparisons take them."""

    rows: np.ndarray  # the records, in order
    target: np.ndarray  # each one's stream (an index of ``streams``); -1: not compared
    streams: list[Stream]
    t: np.ndarray  # s, on the stream's timeline
    euler: np.ndarray  # (n, 3) rad

    def of(self, stream: Stream) -> np.ndarray:
        """Which are compared with this stream."""
        k = next((k for k, other in enumerate(self.streams) if other is stream), -2)
        return self.target == k


def _vehicle_times(
    steps: _Steps | None, estimated_at: np.ndarray, rows: np.ndarray, before: float | None
) -> list[float | None]:
    """A vehicle's time at each of these rows (in order), as the pipeline has it there:
    its last estimate's (``estimated_at``: the steps estimated), else ``before``."""
    if steps is None:
        return [before] * rows.shape[0]
    return _as_times(_time_at(steps.rows[estimated_at], steps.t[estimated_at], rows, before))


def _time_at(
    estimate_rows: np.ndarray, estimate_t: np.ndarray, rows: np.ndarray, before: float | None
) -> np.ndarray:
    """The time of the last estimate before each of ``rows`` (the estimates at
    ``estimate_rows``, ascending, made at ``estimate_t``): the ``last_t`` the pipeline
    holds when it comes to that record. ``before`` where there is none (NaN for None)."""
    upto = np.searchsorted(estimate_rows, rows)
    last = estimate_t[np.maximum(upto - 1, 0)] if estimate_t.shape[0] else math.nan
    return np.where(upto > 0, last, math.nan if before is None else before)


def _as_times(times: np.ndarray) -> list[float | None]:
    """Times as the pipeline holds them: floats, None for none yet (NaN)."""
    return [None if math.isnan(value) else value for value in times.tolist()]


def _in_order(rows: np.ndarray, reference_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimates (at ``rows``) and references (at ``reference_rows``) in the order of
    their records: the kinds (ESTIMATE, REFERENCE), and the order of the estimates
    followed by the references. (A reference's record comes after its sample's:
    estimates first at equal places.)"""
    sort = np.argsort(np.concatenate([rows, reference_rows]), kind="stable")
    kinds = np.concatenate(
        [np.full(rows.shape[0], ESTIMATE), np.full(reference_rows.shape[0], REFERENCE)]
    )[sort]
    return kinds, sort
