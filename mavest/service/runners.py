"""Running the pipeline: live on MAVLink links, or replaying a log.

A replayed log is a tlog, or an autopilot's onboard log (ArduPilot DataFlash, PX4
ULog), chosen by content: an onboard log is decoded, its samples made MAVLink
records (:mod:`mavest.onboard.convert`), and those replayed exactly as a tlog's.

Both are asyncio coroutines. Live, bytes arrive through the links' protocol
callbacks and timers send HEARTBEAT and the message-interval request; nothing
waits on a socket outside the event loop. Replay reads the file's records and
yields to the loop every few hundred records, so a signal stops it at once,
and paces itself by the records' times when asked to (``speed``).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import logging
import math
import sys
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TextIO, TypeVar

import numpy as np

from mavest.estimator import Estimator
from mavest.mavlink import wire
from mavest.mavlink.framing import RecordIndex
from mavest.mavlink.links import Link, make_link, parse_endpoint
from mavest.mavlink.messages import IMU_MESSAGES, Encoder, StreamKey
from mavest.mavlink.signing import Signing
from mavest.mavlink.tlog import TlogError, TlogReader, TlogRecord, TlogWriter, message_ids
from mavest.onboard import LogDamage, OnboardLogError, detect, load
from mavest.onboard.convert import RECORD_EPOCH_US, to_tlog_bytes
from mavest.paths import check_outputs
from mavest.service import bulk
from mavest.service.config import ServiceConfig
from mavest.service.estimates_table import EstimatesTable, table_format
from mavest.service.pipeline import (
    EstimateSink,
    Pipeline,
    Stream,
    accel_seldom_gravity,
    heartbeats_after,
    never_started,
)
from mavest.service.signals import stop_on_signals
from mavest.service.smoothing import SmoothedStream, smooth_stream
from mavest.viz.viewer import (
    DEFAULT_GRPC_PORT,
    DEFAULT_WEB_PORT,
    Viewer,
    ViewerRequest,
)

if TYPE_CHECKING:
    from mavest.viz.recorder import RerunRecorder

log = logging.getLogger("mavest")

# What replay decodes; every other record is copied to the output tlog undecoded.
REPLAY_MESSAGES = message_ids(
    [
        *IMU_MESSAGES,
        "ATTITUDE",
        "SIMSTATE",
        "HEARTBEAT",
        "VFR_HUD",
        "PARAM_VALUE",
        "GPS_RAW_INT",
        "GLOBAL_POSITION_INT",
    ]
)


@dataclass
class Outputs:
    """Files and viewers a run writes to, besides the MAVLink it sends."""

    tlog: Path | None = None
    rrd: Path | None = None
    estimates: Path | None = None  # the estimates table, .csv or .parquet
    rerun: str | None = None  # live viewer: "spawn", "connect" or "serve"
    rerun_url: str | None = None  # for "connect"
    rerun_bind: str = "127.0.0.1"  # for "spawn"/"serve": where the viewer listens
    rerun_port: int = DEFAULT_GRPC_PORT
    rerun_web_port: int = DEFAULT_WEB_PORT

    def paths(self) -> dict[str, Path | None]:
        """The files written, by the option that names each (for
        :func:`~mavest.paths.check_outputs`)."""
        return {"--out-tlog": self.tlog, "--rrd": self.rrd, "--estimates": self.estimates}

    def viewer_request(self) -> ViewerRequest:
        rrd = Path(self.rrd) if self.rrd is not None else None
        return ViewerRequest(
            rrd,
            self.rerun,
            self.rerun_url,
            self.rerun_bind,
            self.rerun_port,
            self.rerun_web_port,
        )


@dataclass
class RunReport:
    """What a run did: enough for the summary and for tests."""

    pipeline: Pipeline
    elapsed: float  # wall-clock seconds
    records: int = 0
    source: str = ""
    interrupted: bool = False
    bad_records: int = 0
    skipped_bytes: int = 0
    skipped_unknown: bool = False  # damage passed over by a reader that did not count it
    # what a bad record is: a tlog's packet, an onboard log's record
    bad_record_kind: str = "packets"
    # an onboard log's samples whose time repeated, went back or was far off the timeline
    dropped_samples: int = 0
    outputs: Outputs = field(default_factory=Outputs)
    # an output file that stopped early (disk full, write error) → why
    output_errors: dict[Path, str] = field(default_factory=dict)
    # of those, the ones of which nothing was kept (a Parquet table cannot stop early)
    unwritten: set[Path] = field(default_factory=set)
    # of ``elapsed``, the seconds spent compiling the filter (a first run): not throughput
    compile_seconds: float = 0.0
    # the replay was over and a served viewer went on serving it until the stop
    lingered: bool = False
    # replay --smooth: each stream smoothed (NaN where the smoother refused), or why
    # nothing was
    smoothed: dict[StreamKey, SmoothedStream] = field(default_factory=dict)
    smoothing_skipped: str = ""

    @property
    def streams(self) -> list[Stream]:
        return self.pipeline.every_stream

    def summary(self) -> str:
        return format_summary(self)


# How often a live run with a recording file but no viewer sends its buffered rows, s.
FILE_ONLY_FLUSH_PERIOD = 10.0


class _Opened:
    """The outputs of a run, open: the output tlog, the Rerun recording and its recorder,
    the estimates table.

    A file that cannot be written any more (a full disk) stops with one line in the
    log and stays valid up to there; the run goes on without it. A run that fails
    (:meth:`abandon`) leaves no table: it appears whole, when the run ends.
    """

    def __init__(self, outputs: Outputs, smoothing: bool = False) -> None:
        """``smoothing``: smoothed estimates may come at the end (:meth:`on_smoothed`)."""
        request = outputs.viewer_request()
        if request.wanted:
            # rerun-sdk only when asked for (a second to import), and before any file is
            # opened (an output file that exists means the run has started), the layout's
            # module too (else the first stream would wait for it)
            import mavest.viz.blueprint  # noqa: F401
            from mavest.viz.recorder import RerunRecorder
        if outputs.estimates is not None:
            table_format(outputs.estimates)  # a wrong suffix, no pyarrow: before any file
        self.outputs = outputs
        self.table: EstimatesTable | None = None
        self.tlog: TlogWriter | None = None
        self.viewer: Viewer | None = None
        self.recorder: RerunRecorder | None = None
        self._recorder_period = 0.0  # s between the recorder's batches (0: every flush)
        self._recorder_flushed = 0.0  # time.monotonic() of the last one
        # the pipeline's estimate sinks: the recorder, until nothing takes the recording;
        # the table; and a replay's caller's (replay's ``sinks``)
        self.sinks: list[EstimateSink] = []
        # Every output was tried for writing (check_outputs); should one fail all the
        # same, the others opened so far are closed and the table dropped. The output
        # tlog, which opening empties, comes last: the viewer can fail for reasons of
        # its own (no display, a port taken), the table is a hidden file until the end.
        try:
            if request.wanted:
                self.viewer = Viewer(request)
                self.recorder = RerunRecorder.for_viewer(
                    self.viewer.recording, live=request.mode is not None
                )
                # a viewer should feel live; a file only needs what is buffered on disk
                # now and then (each batch costs ~30 send_columns: 3 % of the CPU at 1 kHz
                # if sent every second)
                if request.mode is None:
                    self._recorder_period = FILE_ONLY_FLUSH_PERIOD
                    self._recorder_flushed = time.monotonic()
                self.recorder.on_new_stream.append(self.viewer.add_stream)
                self.sinks.append(self.recorder)
            if outputs.estimates is not None:
                self.table = EstimatesTable(outputs.estimates, smoothing=smoothing)
                self.sinks.append(self.table)
            if outputs.tlog is not None:
                self.tlog = TlogWriter(outputs.tlog)
        except BaseException:
            self.abandon()
            self.close()
            raise

    @property
    def _recording(self) -> bool:
        """Whether the recorder takes estimates (until nothing takes the recording)."""
        return self.recorder is not None and self.recorder in self.sinks

    def flush(self) -> None:
        if self.tlog is not None:
            self.tlog.flush()
        if (
            self.recorder is not None
            and self._recording
            and time.monotonic() - self._recorder_flushed >= self._recorder_period
        ):
            self.recorder.flush()
            self._recorder_flushed = time.monotonic()
        if self.viewer is not None:
            self.viewer.check()
            self.check_space()
            self.viewer.flush()
            self._drop_idle_recorder()

    @property
    def serving(self) -> bool:
        """Whether a web viewer mavest started is serving the recording."""
        return self.viewer is not None and self.viewer.serving

    def flush_all(self) -> None:
        """Everything buffered to its file or viewer now (the recorder's batches too); the
        table whole under its name (a replay that ends and lingers: nothing more comes)."""
        if self.table is not None:
            self.table.close()
        if self.tlog is not None:
            self.tlog.flush()
        if self.recorder is not None and self._recording:
            self.recorder.flush()
            self._recorder_flushed = time.monotonic()
        if self.viewer is not None:
            self.viewer.flush()

    def on_smoothed(self, stream: Stream, smoothed: SmoothedStream) -> None:
        """A stream's smoothed estimate, beside its online one in the table and the
        recording."""
        if self.table is not None:
            self.table.add_smoothed(
                stream, smoothed.q, smoothed.euler, smoothed.sigma, smoothed.bias
            )
        if self.recorder is not None and self._recording:
            self.recorder.on_smoothed(stream, smoothed.t, smoothed.euler, smoothed.sigma)

    def check_space(self) -> None:
        """Close the .rrd while it can still be completed if its disk is nearly full."""
        if self.viewer is not None:
            self.viewer.check_space()
            self._drop_idle_recorder()

    def _drop_idle_recorder(self) -> None:
        # nothing takes the recording any more: stop building it (memory, time)
        if self.viewer is not None and not self.viewer.active and self._recording:
            self.sinks.remove(self.recorder)

    def close(self) -> None:
        if self.tlog is not None:
            self.tlog.close()
        if self.recorder is not None and self._recording:
            self.recorder.close()
        if self.viewer is not None:
            self.viewer.close()
        if self.table is not None:
            self.table.close()

    def abandon(self) -> None:
        """The run failed: no table (:meth:`close` still closes the rest)."""
        if self.table is not None:
            self.table.discard()

    def unwritten(self) -> set[Path]:
        """Output files that stopped early and of which nothing was kept."""
        if self.table is not None and self.table.error is not None and not self.table.published:
            return {self.table.path}
        return set()

    def errors(self) -> dict[Path, str]:
        """Output files that stopped early, and why."""
        errors: dict[Path, str] = {}
        if self.tlog is not None and self.tlog.error is not None:
            errors[self.tlog.path] = self.tlog.error
        if self.viewer is not None and self.viewer.rrd_error is not None:
            assert self.outputs.rrd is not None
            errors[Path(self.outputs.rrd)] = self.viewer.rrd_error
        if self.table is not None and self.table.error is not None:
            errors[self.table.path] = self.table.error
        return errors


def _settle_heap() -> None:
    """Move everything alive now (modules, compiled code, the recording's machinery) out of
    the garbage collector's view before the per-sample work starts.

    A full collection walks every tracked object, and numba, numpy and rerun leave
    hundreds of thousands of them; the Rerun recorder's tuples (one per sample, until
    its block is packed) make collections frequent. Frozen, those objects are no
    longer walked (docs/limits.md says what the recorder still costs).

    Only the young generations are collected first: that is where the start's garbage
    is (some hundred objects). A full collection walked every object of numba, the
    kernels and Rerun to find at most a few dozen more (some kB, from Rerun's classes
    being built): 50 ms of every command's start, 0.3 s with Rerun loaded. Those stay,
    frozen: once, and small.
    """
    gc.collect(1)
    gc.freeze()


class ProgressBar:
    """A one-line bar on a terminal, redrawn at most five times a second (nothing when
    the output is not a terminal); what follows the bar is the caller's."""

    WIDTH = 30

    def __init__(self, stream: TextIO = sys.stderr, enabled: bool | None = None):
        self.stream = stream
        self.enabled = stream.isatty() if enabled is None else enabled
        self._last = -math.inf
        self.start = time.perf_counter()

    def due(self, now: float, final: bool = False) -> bool:
        """Whether to draw now (always the final state), counting it as drawn."""
        if not self.enabled or (now - self._last < 0.2 and not final):
            return False
        self._last = now
        return True

    def draw(self, fraction: float, text: str) -> None:
        filled = round(self.WIDTH * min(fraction, 1.0))
        self.stream.write(f"\r  [{'#' * filled}{'.' * (self.WIDTH - filled)}] {text}")
        self.stream.flush()

    def finish(self) -> None:
        if self.enabled:
            self.stream.write("\r" + " " * 78 + "\r")
            self.stream.flush()


class _ReplayProgress(ProgressBar):
    """The replay's bar: the share of the file read, samples estimated and their rate."""

    def __init__(self, total: int, enabled: bool | None = None):
        super().__init__(enabled=enabled)
        self.total = max(total, 1)

    def update(self, done: int, samples: int) -> None:
        now = time.perf_counter()
        if not self.due(now):
            return
        fraction = min(done / self.total, 1.0)
        rate = samples / max(now - self.start, 1e-9)
        self.draw(fraction, f"{100 * fraction:5.1f}%  {samples} samples, {rate / 1000:.1f} k/s ")


async def replay(
    path: str | Path,
    config: ServiceConfig,
    outputs: Outputs | None = None,
    speed: float | None = None,
    progress: bool | None = None,
    stop: asyncio.Event | None = None,
    fast: bool = True,
    linger: Callable[[RunReport], Awaitable[None]] | None = None,
    smooth: bool = False,
    sinks: Sequence[EstimateSink] = (),
) -> RunReport:
    """Replay a log through the pipeline: a tlog, or an onboard log (DataFlash, ULog) by
    content (:class:`~mavest.mavlink.tlog.TlogError`,
    :class:`~mavest.onboard.OnboardLogError` if unusable;
    :class:`~mavest.paths.OutputPathError` for an output that is the log or another output).

    ``fast``: clean stretches of the file go through :class:`~mavest.service.bulk.BulkFeed`
    (the same outcome, compiled) unless the replay is paced; False takes every record
    one at a time, as the live service does. ``linger``: when the whole log was replayed
    into a viewer mavest serves (``--rerun serve``), awaited with the finished report
    before the viewer is stopped (it holds the recording: the served page shows nothing
    once it goes). ``smooth``: when the whole log is replayed, each stream is smoothed
    too (:mod:`mavest.service.smoothing`): :attr:`RunReport.smoothed`, and beside the
    online estimate in the table and the recording. ``sinks``: estimate sinks of the
    caller's beside the outputs' (with ``on_estimates`` too, or the replay goes one
    record at a time).
    """
    outputs = outputs or Outputs()
    check_outputs({"the log being replayed": path}, outputs.paths())
    source = _open_log(path, config)
    reader = source.reader
    opened = _Opened(outputs, smoothing=smooth)
    tlog = opened.tlog
    opened.sinks.extend(sinks)
    pipeline = Pipeline(config, out_tlog=tlog, sinks=opened.sinks)
    pipeline.smoothing = smooth
    bar = _ReplayProgress(reader.size, enabled=progress)
    _settle_heap()
    report = RunReport(pipeline, 0.0, source=source.label, outputs=outputs)
    heartbeat_period = 1.0 / config.output.heartbeat_rate if config.output.heartbeat_rate else 0.0
    heartbeat_us = int(heartbeat_period * 1e6)
    next_heartbeat_us = 0
    first_us: int | None = None
    last_us = 0  # the time of the last record handled
    feed = None
    if fast and not speed and bulk.usable(pipeline):
        feed = bulk.BulkFeed(pipeline, reader.array, REPLAY_MESSAGES, tlog, opened.check_space)
    start = time.perf_counter()
    records = iter(reader)
    try:
        while True:
            clean = reader.scan(_SCAN_RECORDS) if feed is not None else None
            if clean is not None and len(clean):
                next_heartbeat_us = _feed(feed, clean, heartbeat_us, next_heartbeat_us)
                last_us = int(clean.stamp[-1])
                records = iter(reader)  # the careful reader goes on from here
            else:  # one record the careful way (or damage: the reader resynchronises)
                record = next(records, None)
                if record is None:
                    break
                last_us = record.timestamp_us
                next_heartbeat_us = _one_record(
                    pipeline, tlog, record, heartbeat_us, next_heartbeat_us
                )
                if reader.stats.records % 256:
                    continue
            bar.update(reader.position, _estimated(pipeline))
            _check_rates(pipeline, source.rate_advice)
            opened.check_space()
            if speed:
                if first_us is None:
                    first_us = last_us
                ahead = (last_us - first_us) * 1e-6 / speed - (time.perf_counter() - start)
                await _pause(ahead, stop)
            else:
                await asyncio.sleep(0)
            if stop is not None and stop.is_set():
                report.interrupted = True
                break
        _check_rates(pipeline, source.rate_advice)
        if smooth:
            bar.finish()
            await _smooth(report, opened, stop)
        if linger is not None and opened.serving and not report.interrupted:
            if feed is not None:
                feed.close()
                feed = None
            bar.finish()
            opened.flush_all()
            _fill_replay_report(report, source, opened, start)
            report.lingered = True
            await linger(report)
    except Exception:
        opened.abandon()  # (a stop, Ctrl-C, is no failure: the table keeps its rows)
        raise
    finally:
        if feed is not None:
            feed.close()
        bar.finish()
        opened.close()
    if not report.lingered:
        _fill_replay_report(report, source, opened, start)
    _run_ended(report, opened, pipeline)
    return report


def _record_outputs(report: RunReport, opened: _Opened) -> None:
    """The outputs that stopped early, and those of which nothing was kept."""
    report.output_errors, report.unwritten = opened.errors(), opened.unwritten()


def _run_ended(report: RunReport, opened: _Opened, pipeline: Pipeline) -> None:
    """What every run (live or replay) reports when it ends: the outputs that stopped
    early (and those of which nothing was kept), and a warning for each stream that
    never had an attitude, or whose accelerometer was mostly kept out of its gravity
    updates (its tilt is then the gyro's alone, its σ says how unsure; the summary
    says how often)."""
    _record_outputs(report, opened)
    for stream in pipeline.every_stream:
        if never_started(stream.stats):
            tolerance = pipeline.config.estimator.accel_norm_tolerance
            gravity = pipeline.config.estimator.gravity
            log.warning(
                "%s: no attitude from any of its %d samples: the accelerometer never read "
                "g = %g m/s² within %g m/s² (not in m/s², or never at rest long enough to start)",
                stream.key,
                stream.stats.estimated,
                gravity,
                tolerance,
            )
            continue
        share = accel_seldom_gravity(stream.stats)
        if share is not None:
            log.warning(
                "%s: the accelerometer was too far from g to be taken as gravity at %.0f %% "
                "of the updates: tilt seldom observed (a vehicle always accelerating, or "
                "an attitude lost to a gyro offset beyond the filter's prior, "
                "estimator.initial_bias_sigma)",
                stream.key,
                100.0 * share,
            )


async def _pause(seconds: float, stop: asyncio.Event | None) -> None:
    """A paced replay ahead of its log's clock waits ``seconds``, or until ``stop`` is
    set (a pause in the log can be an hour long)."""
    if stop is None or seconds <= 0.0:
        await asyncio.sleep(max(seconds, 0.0))
        return
    with contextlib.suppress(asyncio.TimeoutError):  # (TimeoutError itself from 3.11)
        await asyncio.wait_for(stop.wait(), seconds)


async def _smooth(report: RunReport, opened: _Opened, stop: asyncio.Event | None) -> None:
    """Smooth each stream the replay estimated, into the report, the table and the
    recording; an interrupted replay is not smoothed (the user asked to stop), said in
    one line.

    Smoothing a long log takes seconds: each stream is smoothed in a worker thread
    (the smoother's kernels release the GIL) while the event loop waits for it or for
    ``stop``. A stop comes as an interrupted replay's: nothing smoothed goes to the
    outputs (they are added only once every stream is done), and the thread, whose
    kernel cannot be cut short, is left to end on its own.
    """
    if report.interrupted:
        report.smoothing_skipped = "smoothing skipped: the replay was interrupted"
        log.warning("%s", report.smoothing_skipped)
        return
    done: list[tuple[Stream, SmoothedStream]] = []
    for stream in report.pipeline.every_stream:
        result = await _unless_stopped(functools.partial(smooth_stream, stream), stop)
        if stop is not None and stop.is_set():
            report.interrupted = True
            report.smoothing_skipped = "smoothing stopped: the replay was interrupted"
            log.warning("%s", report.smoothing_skipped)
            return
        if result is not None:
            done.append((stream, result))
    for stream, result in done:
        report.smoothed[stream.key] = result
        opened.on_smoothed(stream, result)


_T = TypeVar("_T")


async def _unless_stopped(work: Callable[[], _T], stop: asyncio.Event | None) -> _T | None:
    """``work()``, run in a daemon thread until it returns (its exception raised here),
    or None as soon as ``stop`` is set (the thread then ends on its own; a daemon
    thread does not hold up the process's exit). Without ``stop``, run here."""
    if stop is None:
        return work()
    loop = asyncio.get_running_loop()
    done: asyncio.Future[_T] = loop.create_future()

    def settle(result: _T | None, error: BaseException | None) -> None:
        if done.done():  # (given up on)
            return
        if error is not None:
            done.set_exception(error)
        else:
            done.set_result(result)  # type: ignore[arg-type]

    def run() -> None:
        result, error = None, None
        try:
            result = work()
        except BaseException as raised:  # (handed to the waiting loop)
            error = raised
        with contextlib.suppress(RuntimeError):  # the loop is gone: nobody waits
            loop.call_soon_threadsafe(settle, result, error)

    threading.Thread(target=run, name="mavest-smoothing", daemon=True).start()
    stopped = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({done, stopped}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopped.cancel()
    if not done.done():
        done.cancel()
        return None
    return done.result()


@dataclass(frozen=True)
class _Source:
    """A log opened for replay: its records as a tlog's, and what loading it found."""

    reader: TlogReader
    label: str  # the summary's name for it
    damage: LogDamage  # an onboard log's, found while decoding it (a tlog's: the reader's)
    bad_record_kind: str
    loading: float  # seconds spent decoding and converting it (part of the replay's time)
    rate_advice: str  # what to do about an IMU too slow to estimate from


_ONBOARD_FORMATS = {"dataflash": "DataFlash log", "ulog": "ULog"}
_ONBOARD_SUFFIXES = (".bin", ".ulg")


def _open_log(path: str | Path, config: ServiceConfig) -> _Source:
    """The log at ``path`` as tlog records: a tlog as it is (mapped, never read whole), an
    onboard log decoded and converted in memory. The format is the content's, whatever
    the name (a tlog saved as .bin is read as a tlog); a file of neither is refused in
    the terms of the name it has (.bin/.ulg, else tlog)."""
    path = Path(path)
    kind = None
    if path.is_file():
        with contextlib.suppress(OnboardLogError):  # unreadable: TlogReader.open says why
            kind = detect(path)
    began = time.perf_counter()
    if kind is None:
        try:
            reader = TlogReader.open(path, REPLAY_MESSAGES)
        except TlogError:
            if not (path.suffix.lower() in _ONBOARD_SUFFIXES and path.is_file()):
                raise
            # an onboard log after bytes of another kind, or else refused in its own words
            onboard = load(path)
        else:
            if path.suffix.lower() in _ONBOARD_SUFFIXES:
                log.info("%s: named as an onboard log, holds a tlog: read as one", path.name)
            return _Source(reader, str(path), LogDamage(), "packets", 0.0, _RAISE_STREAM_RATE)
    else:
        onboard = load(path)
    data = to_tlog_bytes(onboard)
    if onboard.notes:  # one line: lines of one template are rate-limited (log_repeats)
        log.info("%s: %s", path.name, "; ".join(onboard.notes))
    if config.input.imu not in ("auto", "all", "HIGHRES_IMU"):
        log.warning(
            "%s: an onboard log's IMUs are replayed as HIGHRES_IMU (id: the IMU's instance); "
            "--imu %s selects none of them",
            path.name,
            config.input.imu,
        )
    logged = sorted(imu.instance for imu in onboard.imus)
    if config.input.imu_instance >= 0 and config.input.imu_instance not in logged:
        log.warning(
            "%s: --instance %d selects no IMU: the log's are instance %s",
            path.name,
            config.input.imu_instance,
            ", ".join(map(str, logged)),
        )
    return _Source(
        TlogReader(data, REPLAY_MESSAGES, name=path.name, boot_epoch_us=RECORD_EPOCH_US),
        f"{path} ({onboard.autopilot} {_ONBOARD_FORMATS.get(onboard.format, onboard.format)})",
        onboard.damage,
        "records",
        time.perf_counter() - began,
        _RAISE_LOG_RATE,
    )


def _fill_replay_report(report: RunReport, source: _Source, opened: _Opened, start: float) -> None:
    reader, damage = source.reader, source.damage
    _record_outputs(report, opened)  # (a served replay's summary comes before the close)
    report.elapsed = time.perf_counter() - start + source.loading
    report.records = reader.stats.records
    report.bad_records = reader.stats.bad_crc + damage.bad_records
    report.skipped_bytes = (
        reader.stats.skipped_bytes
        + reader.stats.truncated_bytes
        + damage.skipped_bytes
        + damage.truncated_bytes
    )
    report.skipped_unknown = damage.extent_unknown
    report.bad_record_kind = source.bad_record_kind
    report.dropped_samples = damage.dropped_samples


# Clean records indexed per scan: about 8 s of a 1 kHz log with its truth, so that a
# signal stops a fast replay within a fraction of a second and the index stays small;
# each scan is at least one stretch of the fast path, which has a cost of its own.
_SCAN_RECORDS = 16384


def _one_record(
    pipeline: Pipeline, tlog: TlogWriter | None, record: TlogRecord, period_us: int, next_us: int
) -> int:
    """One record as it comes: written, handled, a HEARTBEAT after it when one is due.

    Returns when the next HEARTBEAT is due (µs of record time)."""
    stamp = record.timestamp_us
    if tlog is not None:
        tlog.write(stamp, record.packet)
    if record.message is not None:
        pipeline.on_message(record.message, stamp)
    if period_us and pipeline.vehicles:
        beats, next_us = heartbeats_after(stamp, next_us, period_us)
        if beats:
            pipeline.heartbeat()
    return next_us


def _feed(feed: bulk.BulkFeed, records: RecordIndex, period_us: int, next_us: int) -> int:
    """Clean records through the fast path, which sends a HEARTBEAT after one of them
    when one is due (as :func:`_one_record` would). Returns when the next one is due."""
    pipeline = feed.pipeline
    start = 0
    n = len(records)
    while start < n:
        end = n
        if period_us and not pipeline.vehicles:
            # none to speak for yet: only a decoded record can bring one
            decoded = np.flatnonzero(feed.kinds[records.message_id[start:]] != 0)
            end = start + int(decoded[0]) + 1 if decoded.shape[0] else n
        next_us = feed.feed(records.part(slice(start, end)), period_us, next_us)
        start = end
    return next_us


def _estimated(pipeline: Pipeline) -> int:
    return sum(s.stats.estimated for s in pipeline.every_stream)


async def run_live(
    connection: str,
    config: ServiceConfig,
    out_connections: tuple[str, ...] = (),
    outputs: Outputs | None = None,
    baud: int = 115200,
    stop: asyncio.Event | None = None,
    status_period: float = 10.0,
    ready: asyncio.Event | None = None,
    signing: Signing | None = None,
) -> RunReport:
    """Serve until ``stop`` is set (or SIGINT/SIGTERM when ``stop`` is not given).

    ``signing``: sign what is sent and verify what is heard (MAVLink 2 signing).
    """
    outputs = outputs or Outputs()
    check_outputs({}, outputs.paths())
    endpoints = [parse_endpoint(connection, baud)] + [
        parse_endpoint(c, baud) for c in out_connections
    ]
    # Signals are ours from here on: one that arrives while the filter loads or the files
    # open stops the run as soon as it listens, with its files closed properly.
    with stop_on_signals(stop) as stopping:
        # (the run's time includes the filter's loading, as a replay's does: the summary
        # takes the compiling out of it, which would else be counted twice)
        start = time.perf_counter()
        # Compile (or load) the filter before listening: the first IMU packet must not
        # wait for it.
        _warm_up(config)
        opened = _Opened(outputs)
        links: list[Link] = [make_link(e) for e in endpoints]
        pipeline = Pipeline(
            config,
            links=links,
            out_tlog=opened.tlog,
            sinks=opened.sinks,
            now_us=lambda: time.time_ns() // 1000,
            signing=signing,
        )
        if signing is not None:
            log.info("%s", signing.describe())
        report = RunReport(pipeline, 0.0, source=connection, outputs=outputs)
        tasks: list[asyncio.Task[None]] = []
        try:
            await _serve(pipeline, links, config, opened, status_period, ready, stopping, tasks)
        except Exception:
            opened.abandon()
            raise
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            for link in links:
                link.close()
            opened.close()
    _run_ended(report, opened, pipeline)
    report.elapsed = time.perf_counter() - start
    report.records = pipeline.messages_in
    report.bad_records = pipeline.bad_packets
    report.skipped_bytes = pipeline.skipped_bytes
    return report


def _warm_up(config: ServiceConfig) -> None:
    """Load the compiled kernels the first IMU sample needs, so that it does not wait.

    Building an estimator loads the filter's (or compiles them, the first time);
    the Euler angles of an estimate, which every ATTITUDE carries, come from a kernel
    loaded at its first call: ~25 ms that the first sample, and the ones queued
    behind it, would otherwise wait. So do the packet scanner and packer
    (:mod:`mavest.mavlink.framing`) that decode the first datagram and pack the first
    ATTITUDE.
    """
    estimator = Estimator(config.estimator)
    estimate = estimator.update(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, -9.80665))
    _ = estimate.euler
    encoder = Encoder(config.output.system_id or 1, config.output.component_id)
    packet = encoder.attitude(0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    wire.decode_datagram(packet)


async def _serve(
    pipeline: Pipeline,
    links: list[Link],
    config: ServiceConfig,
    opened: _Opened,
    status_period: float,
    ready: asyncio.Event | None,
    stop: asyncio.Event,
    tasks: list[asyncio.Task[None]],
) -> None:
    """Open the links, start the timers, wait for the stop (cleanup is the caller's)."""
    # Before the first packet can arrive: the full collection takes ~0.1 s, which the
    # first samples would wait for (and "listening on" is what a vehicle may wait for).
    _settle_heap()
    for link in links:
        await link.start(pipeline.on_bytes)
    log.info(
        "listening on %s%s",
        links[0],
        "".join(f", sending to {link}" for link in links[1:]),
    )
    if ready is not None:
        ready.set()
    if config.output.heartbeat_rate > 0:
        tasks.append(
            asyncio.create_task(_every(1.0 / config.output.heartbeat_rate, pipeline.heartbeat))
        )
    tasks.append(asyncio.create_task(_every(2.0, pipeline.request_intervals)))
    tasks.append(
        asyncio.create_task(
            _every(NO_IMU_REPEAT, lambda: _no_imu_yet(pipeline, links[0]), first=NO_IMU_FIRST)
        )
    )
    if status_period > 0:
        tasks.append(asyncio.create_task(_every(status_period, lambda: _status(pipeline))))
    tasks.append(asyncio.create_task(_every(1.0, opened.flush)))
    await stop.wait()


async def _every(period: float, action: Callable[[], object], first: float | None = None) -> None:
    await asyncio.sleep(period if first is None else first)
    while True:
        action()
        await asyncio.sleep(period)


# A live run that has no IMU stream says what it hears this long after it starts
# listening, and again every NO_IMU_REPEAT seconds until a stream comes.
NO_IMU_FIRST = 5.0
NO_IMU_REPEAT = 20.0

_STREAM_SETUP = (
    "ask for one with --request-rate 50 (MAV_CMD_SET_MESSAGE_INTERVAL), or set it up on the "
    "vehicle: ArduPilot SRn_RAW_SENS (the port's stream rate, e.g. SR0_RAW_SENS=50), "
    "PX4 `mavlink stream -d DEVICE -s HIGHRES_IMU -r 50`"
)


def _no_imu_yet(pipeline: Pipeline, link: Link) -> None:
    """Say what is heard when no IMU stream is, and what to do about it."""
    if pipeline.streams:
        return
    heard = pipeline.heard_without_imu
    if pipeline.ignored_imu:
        systems = ", ".join(str(s) for s in sorted(pipeline.ignored_imu))
        log.warning(
            "IMU messages come only from system %s, which is not followed "
            "(--system ID picks a vehicle; [input] ignore_systems lists those never followed)",
            systems,
        )
    elif heard:
        described = "; ".join(
            f"{', '.join(sorted(names))} from {system}/{component}"
            for (system, component), names in sorted(heard.items())
        )
        asked = pipeline.config.input.request_rate
        advice = (
            f"asked for it at {asked:g} Hz; the vehicle has not answered with one yet"
            if asked > 0
            else _STREAM_SETUP
        )
        log.warning("no IMU message yet; heard %s. %s", described, advice)
    elif pipeline.bad_packets:
        log.warning(
            "only damaged MAVLink on %s (%d bad packets): a wrong --baud, or not MAVLink?",
            link,
            pipeline.bad_packets,
        )
    else:
        log.warning(
            "nothing heard on %s yet: is the vehicle (or its router, e.g. MAVProxy --out) "
            "sending to this address and port?",
            link,
        )


# Below this IMU rate an estimate cannot follow a moving vehicle: the filter takes the
# time between samples as a gap and re-aligns tilt to the accelerometer alone.
LOW_IMU_RATE = 20.0


# What to do about an IMU too slow to estimate from: a link's stream can be asked to go
# faster; an onboard log holds what the autopilot logged.
_RAISE_STREAM_RATE = (
    "Raise the IMU stream rate (live: --request-rate 50, or ArduPilot's SRn_RAW_SENS); "
    "the vehicle's onboard log holds the IMU at its full rate"
)
_RAISE_LOG_RATE = (
    "This onboard log holds the IMU at that rate: raise the autopilot's IMU logging rate "
    "for the next flight (ArduPilot: LOG_BITMASK's fast IMU logging; PX4: an SDLOG_PROFILE "
    "with high-rate sensors)"
)


def _check_rates(pipeline: Pipeline, advice: str = _RAISE_STREAM_RATE) -> None:
    """Warn, once per stream, of an IMU stream too slow to estimate from."""
    for stream in pipeline.streams.values():
        stats = stream.stats
        if stream.rate_warned or stats.estimated < 10:
            continue
        realigning = stats.realigned > stats.estimated // 2
        if 0.0 < stream.rate < LOW_IMU_RATE or realigning:
            stream.rate_warned = True
            log.warning(
                "%s: IMU at %.1f Hz is too slow for this estimate%s: attitude follows the "
                "accelerometer alone and can be tens of degrees off while the vehicle moves. %s",
                stream.key,
                stream.rate,
                f" ({stats.realigned} of {stats.estimated} samples came after a gap)"
                if realigning
                else "",
                advice,
            )


def _status(pipeline: Pipeline) -> None:
    _check_rates(pipeline)
    for stream in pipeline.streams.values():
        asked = ""
        vehicle = pipeline.vehicles.get((stream.key.system, stream.key.component))
        if vehicle is not None and vehicle.interval_asked == stream.key.message:
            asked = f" (asked {pipeline.config.input.request_rate:g} Hz)"
        stats = stream.stats
        log.info(
            "%s: %.1f Hz%s, %d estimated, %d answered, %d rejected",
            stream.key,
            stream.rate,
            asked,
            stats.estimated,
            stats.answered,
            stats.rejected + stats.duplicates + stats.out_of_order + stats.off_timeline,
        )
    if pipeline.verifier is not None and pipeline.verifier.dropped:
        log.info("signing: %s", pipeline.verifier.describe())


def _counted(counts: tuple[tuple[str, int], ...]) -> list[str]:
    """ "N name" for each count that is not zero; a name "one/many" takes its number's."""
    out = []
    for name, value in counts:
        if value:
            one, _, many = name.partition("/")
            out.append(f"{value} {one if value == 1 or not many else many}")
    return out


def format_summary(report: RunReport) -> str:
    """The one-screen summary printed at the end of a run."""
    pipeline = report.pipeline
    lines = []
    samples = _estimated(pipeline)
    # (the command counts the compiling from just before the run, whose own clock
    # starts a little later: never more than the whole)
    compiled = min(report.compile_seconds, report.elapsed)
    working = report.elapsed - compiled
    status = " (interrupted)" if report.interrupted else ""
    compiling = (
        f" ({compiled:.0f} s of it compiling the filter, a first run)" if compiled >= 0.5 else ""
    )
    throughput = f" ({samples / working / 1000:.1f} k samples/s)" if working > 0.0 else ""
    lines.append(
        f"{report.source}{status}: {report.records} messages in {report.elapsed:.2f} s"
        f"{compiling}, {samples} IMU samples estimated{throughput}"
    )
    if report.bad_records or report.skipped_bytes or report.dropped_samples:
        dropped = (
            f", {report.dropped_samples} samples dropped"
            " (their time repeated, went back or was far off)"
            if report.dropped_samples
            else ""
        )
        skipped = (
            "bytes skipped not counted by the decoder (what follows the damage may be lost)"
            if report.skipped_unknown
            else f"{report.skipped_bytes} bytes skipped"
        )
        lines.append(
            f"  damaged input: {report.bad_records} bad {report.bad_record_kind}, "
            f"{skipped}{dropped}"
        )
    if not pipeline.streams:
        lines.append(
            "  no IMU stream found (RAW_IMU, SCALED_IMU/2/3 or HIGHRES_IMU from a vehicle)"
        )
    for stream in pipeline.every_stream:
        stats = stream.stats
        role = " → ATTITUDE" if stream.primary else ""
        if stream.followed_by is not None:
            until = f" until {stats.last_t:.1f} s" if stats.last_t is not None else ""
            role = f" → ATTITUDE{until}, then {stream.followed_by}"
        # (fewer than estimated at --attitude-rate, or while the filter has no attitude)
        answered = f", {stats.answered} answered" if stream.primary or stream.followed_by else ""
        lines.append(
            f"  {stream.key}{role}: {stats.estimated} of {stats.received} samples over "
            f"{stats.span:.1f} s at {stream.rate:.1f} Hz{answered}"
        )
        problems = _counted(
            (
                ("rejected", stats.rejected),
                ("duplicate/duplicates", stats.duplicates),
                ("out of order", stats.out_of_order),
                ("off the timeline", stats.off_timeline),
                ("gap/gaps", stats.gaps),
                ("re-aligned", stats.realigned),
                ("reboot/reboots", stats.reboots),
                ("wrap/wraps", stats.wraps),
            )
        )
        lines.append("    " + (", ".join(problems) if problems else "no gaps, nothing rejected"))
        if stats.rejected_reasons:
            lines.append(
                "    rejected: "
                + "; ".join(f"{n} {why}" for why, n in stats.rejected_reasons.items())
            )
        health = _counted(
            (
                ("tilt reopened (accelerometer disturbed too long)", stats.tilt_reopened),
                ("re-initialised after a divergence", stats.diverged),
                ("re-initialised after a failed health check", stats.unhealthy),
                ("sample with the gyro clipped/samples with the gyro clipped", stats.gyro_clipped),
                ("tilt re-aligned after the gyro clipped", stats.clip_realigned),
            )
        )
        lines.append("    filter health: " + (", ".join(health) if health else "no resets"))
        if (share := accel_seldom_gravity(stats)) is not None:
            lines.append(
                f"    accelerometer too far from g at {100 * share:.0f} % "
                f"of the {stats.updates} gravity updates: tilt seldom observed"
            )
        if stats.accel_wrong_unit:
            problem = stream.estimator.accel_unit_problem or "accelerometer not in m/s²"
            lines.append(
                f"    {stats.accel_wrong_unit} samples with no attitude (the filter did not "
                f"start): {problem}"
            )
        if stats.mag_taken:
            used = 100.0 * stats.mag_used / stats.mag_taken
            lines.append(
                f"    heading from the magnetometer (9-D): {used:.1f} % used of the "
                f"{stats.mag_taken} readings taken (of {stats.mag_usable} usable)"
            )
        elif stats.mag_usable:
            lines.append(
                f"    heading free (6-D): none of the {stats.mag_usable} usable magnetometer "
                "readings taken"
            )
        else:
            lines.append("    no magnetometer: heading free (6-D), yaw drifts")
        aided = [
            f"{100.0 * count / stats.estimated:.1f} % from {source}"
            for source, count in (
                ("GPS velocity", stats.gps_aided),
                ("airspeed (centripetal only)", stats.airspeed_aided),
            )
            if count and stats.estimated
        ]
        lines.append(
            "    vehicle acceleration removed: " + (", ".join(aided) if aided else "never")
        )
        settle = pipeline.config.input.settle_time
        smoothed = report.smoothed.get(stream.key)
        for name, comparison, smoothed_result in (
            (
                "truth (SIMSTATE)",
                stream.vs_truth,
                smoothed.vs_truth if smoothed is not None else None,
            ),
            (
                "autopilot ATTITUDE",
                stream.vs_autopilot,
                smoothed.vs_autopilot if smoothed is not None else None,
            ),
        ):
            result = comparison.result()
            for who, scored in (("", result), ("smoothed ", smoothed_result)):
                if scored is not None and scored.count:
                    described = scored.describe(stream.estimator.heading_referenced)
                    lines.append(f"    {who}vs {name} after {settle:g} s: {described}")
            if not result.count and comparison.references:  # (a short log: say why none)
                lines.append(
                    f"    vs {name}: not scored: none of its {comparison.references} attitudes "
                    f"came {settle:g} s or more into the stream and beside its estimates"
                )
        if smoothed is not None and smoothed.refused == len(smoothed):
            lines.append(
                f"    smoothed: none of its {len(smoothed)} samples: the smoother refused them"
                " (its warning says why)"
            )
        elif smoothed is not None:
            count = (
                f"{len(smoothed) - smoothed.refused} of {len(smoothed)}"
                if smoothed.refused
                else f"{len(smoothed)}"
            )
            lines.append(f"    smoothed: {count} samples, given the whole log")
    if report.smoothing_skipped:
        lines.append(f"  {report.smoothing_skipped}")
    if pipeline.ignored_imu:
        ignored = ", ".join(f"{n} from system {s}" for s, n in sorted(pipeline.ignored_imu.items()))
        lines.append(f"  IMU messages ignored (systems not followed): {ignored}")
    if pipeline.verifier is not None:
        lines.append(f"  signing: {pipeline.verifier.describe()}")
    if pipeline.sent:
        signed = (
            " (signed)" if pipeline.signing is not None and pipeline.signing.sign_outgoing else ""
        )
        lines.append(f"  sent {pipeline.sent} messages{signed}")
    for label, path in (
        ("tlog", report.outputs.tlog),
        ("Rerun recording", report.outputs.rrd),
        ("estimates table", report.outputs.estimates),
    ):
        if path is None:
            continue
        error = report.output_errors.get(Path(path))
        if Path(path) in report.unwritten:
            lines.append(f"  no {label} written: {error}")
        else:
            stopped = f", stopped early: {error}" if error else ""
            lines.append(f"  wrote {path} ({label}{stopped})")
    return "\n".join(lines)
