"""One log → its rows of the fleet table: ``mavest replay`` of the log, summed up.

:func:`log_rows` is what a Dask worker runs for each log (and what a plain loop
would run): the same :func:`~mavest.service.runners.replay` as ``mavest replay``,
with the same configuration, so a row's figures are that command's summary's. A
log that cannot be replayed (empty, damaged beyond reading, not a log, unreadable)
is one row with ``status`` ``error`` and the line ``mavest replay`` would print;
it never raises. The rows depend on the log and the configuration only: no
times, no host names, so the same logs give the same table.

A remote log (an fsspec URL: ``s3://``, ``gs://``, ``memory://`` …) is copied to a
temporary file on the worker first; the replay needs a file it can map.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mavest.mavlink.messages import StreamKey, mavlink2
from mavest.mavlink.tlog import TlogError
from mavest.onboard import OnboardLogError
from mavest.paths import OutputPathError, partial_path, publish
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Stream
from mavest.service.runners import Outputs, RunReport, replay
from mavest.so3 import euler_sigmas
from mavest.viz.viewer import ViewerError

log = logging.getLogger("mavest")

# The table's columns and their types (Arrow's names), in order. One row per log and
# IMU stream; a log with no stream, or that failed, is one row with the stream's
# columns empty. Counts are StreamStats'; angles in degrees; RMS figures are NaN
# where there was nothing to compare with (no ATTITUDE, no SIMSTATE in the log).
COLUMNS: tuple[tuple[str, str], ...] = (
    ("path", "string"),  # the log as given (a path or a URL)
    ("status", "string"),  # "ok" or "error"
    ("error", "string"),  # why not ok: the line `mavest replay` prints
    ("system", "int64"),  # the vehicle's MAVLink system and component id
    ("component", "int64"),
    ("autopilot", "string"),  # its HEARTBEAT's MAV_AUTOPILOT (ARDUPILOTMEGA, PX4, …)
    ("fixed_wing", "bool"),  # its HEARTBEAT's MAV_TYPE is a fixed-wing one
    ("message", "string"),  # the IMU stream: message and instance
    ("instance", "int64"),
    ("primary", "bool"),  # the vehicle's stream answered with ATTITUDE
    ("samples", "int64"),  # estimated
    ("received", "int64"),
    ("duration_s", "float64"),  # first to last sample, vehicle time
    ("rate_hz", "float64"),
    ("gaps", "int64"),
    ("rejected", "int64"),  # values not finite, saturated, beyond any sensor's range
    ("dropped", "int64"),  # duplicates, out of order, off the stream's timeline
    ("realigned", "int64"),  # tilt re-aligned after a gap
    ("reboots", "int64"),
    ("gyro_clipped", "int64"),  # samples with a gyro axis beyond gyro_clip
    # filter health: tilt reopened (the accelerometer disturbed too long),
    # re-initialised after a divergence or a failed health check, tilt re-aligned
    # after the gyro clipped; health_events is their sum
    ("tilt_reopened", "int64"),
    ("diverged", "int64"),
    ("unhealthy", "int64"),
    ("clip_realigned", "int64"),
    ("health_events", "int64"),
    ("heading_referenced", "bool"),  # 9-D (a magnetometer); else heading is free (drift)
    ("tilt_rms_vs_autopilot_deg", "float64"),  # against the log's ATTITUDE, after settling
    ("heading_rms_vs_autopilot_deg", "float64"),
    ("compared_vs_autopilot", "int64"),  # how many of its ATTITUDE were compared
    ("tilt_rms_vs_truth_deg", "float64"),  # against a simulator's SIMSTATE
    ("heading_rms_vs_truth_deg", "float64"),
    ("compared_vs_truth", "int64"),
    # the filter's own 1σ, averaged over the stream's estimates after the settling time
    # (as the RMS figures; the estimates table's sigma columns): tilt is
    # √(σ_roll² + σ_pitch²); values at ±90° pitch (∞) left out
    ("mean_sigma_tilt_deg", "float64"),
    ("mean_sigma_heading_deg", "float64"),
    ("records", "int64"),  # the log's records (an onboard log's, as MAVLink)
    ("bad_records", "int64"),
    ("skipped_bytes", "int64"),
    ("warnings", "string"),  # what `mavest replay` warned of, "; " between (the first 10)
)
COLUMN_NAMES = tuple(name for name, _ in COLUMNS)

# What a replay raises for a log it cannot use, or an output it cannot write: the row's
# message. Anything else is a fault of mavest's, still one row (with its type).
LOG_ERRORS = (TlogError, OnboardLogError, OutputPathError, ViewerError, OSError)


@dataclass(frozen=True)
class LogTask:
    """One log to replay, and where its own outputs go (None: not written)."""

    source: str  # a local path or an fsspec URL, as the table names it
    config: ServiceConfig
    rrd: str | None = None  # the Rerun recording
    estimates: str | None = None  # the estimates table (.csv or .parquet)
    # where a worker finds it: a local path made absolute (a worker of a cluster has
    # a working folder of its own); None: ``source``
    location: str | None = None

    @classmethod
    def of(cls, source: str, config: ServiceConfig) -> LogTask:
        """The task of the log ``source`` (a path, relative or not, or a URL)."""
        return cls(source, config, location=None if is_url(source) else os.path.abspath(source))


def is_url(text: str) -> bool:
    """Whether ``text`` names a file through fsspec (``scheme://…``) rather than a path
    (a scheme of two letters or more: ``C://`` is a drive)."""
    scheme, separator, _ = text.partition("://")
    return (
        bool(separator)
        and len(scheme) > 1
        and scheme[0].isalpha()
        and all(c.isalnum() or c in "+.-" for c in scheme)
    )


def empty_row(source: str, status: str = "ok", error: str = "") -> dict[str, Any]:
    """A row of the log alone (no stream): every other column empty."""
    row: dict[str, Any] = dict.fromkeys(COLUMN_NAMES)
    row.update(path=source, status=status, error=error or None)
    return row


def error_row(source: str, message: str) -> dict[str, Any]:
    return empty_row(source, "error", message)


def warm_up() -> None:
    """Load (or compile, the first time on a machine) everything a log's replay runs in
    this process — the filter's kernels, the replay's decoder and bulk path, the
    σ of its estimates — by replaying a small log made here (2 s of
    RAW_IMU at rest), so the first log of a worker does not pay it in its own time.

    In a thread of its own: Dask's ``Client.run`` calls this in the worker's event
    loop, inside which the replay's ``asyncio.run`` cannot start."""
    rows: list[dict[str, Any]] = []

    def replay_one() -> None:
        with tempfile.TemporaryDirectory(prefix="mavest-fleet-") as scratch:
            log_path = Path(scratch) / "warm-up.tlog"
            write_resting_tlog(log_path)
            rows.extend(log_rows(LogTask(str(log_path), ServiceConfig())))

    # (the vehicle's messages are built where the simulated vehicle's are, in mavest.sim:
    # the service itself builds none but its answers)
    from mavest.sim.vehicle import write_resting_tlog

    thread = threading.Thread(target=replay_one, name="mavest-warm-up")
    thread.start()
    thread.join()
    if not rows or rows[0]["status"] != "ok":
        log.warning("warming up the replay failed: %s", rows[0]["error"] if rows else "no row")


def log_rows(task: LogTask) -> list[dict[str, Any]]:
    """The rows of one log (never raises for a bad log: an error row says why)."""
    with (
        _warnings_kept() as warnings,
        tempfile.TemporaryDirectory(prefix="mavest-fleet-") as scratch,
    ):
        where = task.location or task.source
        local = Path(where)
        try:
            local = _local_copy(where, Path(scratch))
            report, sigmas = _replay(local, task)
        except LOG_ERRORS as error:
            # in the terms of the log as given (not its copy, or its absolute path)
            message = str(error).replace(str(local), task.source)
            return [error_row(task.source, message)]
        except Exception as error:  # a fault of mavest's: this log's row, not the run's end
            return [error_row(task.source, f"{type(error).__name__}: {error}")]
        rows = _rows(task.source, report, sigmas)
        if task.rrd:  # (the recording was written under a partial name, its own now)
            partial, final = str(partial_path(task.rrd)), str(task.rrd)
            warnings = [warning.replace(partial, final) for warning in warnings]
        for row in rows:
            row["warnings"] = _joined(warnings)
        return rows


# Warnings kept per log: a log with a gap a second would otherwise fill its cell.
_MAX_WARNINGS = 10


def _joined(warnings: list[str]) -> str | None:
    if len(warnings) > _MAX_WARNINGS:
        more = len(warnings) - _MAX_WARNINGS
        warnings = [*warnings[:_MAX_WARNINGS], f"{more} more warning{'s' if more > 1 else ''}"]
    return "; ".join(warnings) or None


def _name(source: str) -> str:
    """The log's file name (a URL's last part)."""
    return source.rstrip("/").rsplit("/", 1)[-1] or "log"


def local_file(source: str) -> Path | None:
    """The file here that a log names: a path as it is, a ``file://`` URL's path (or any
    URL whose file system is the local one); None for a remote one."""
    if not is_url(source):
        return Path(source)
    import fsspec  # (only for URLs: part of mavest[fleet])

    try:
        fs, path = fsspec.core.url_to_fs(source)
    except (ImportError, ValueError):  # (a backend not installed, no such protocol)
        return None
    return Path(path) if "file" in fs.protocol else None  # (the names it goes by)


def _local_copy(source: str, scratch: Path) -> Path:
    """A path the replay can map: a local file as it is, a remote one copied."""
    here = local_file(source)
    if here is not None:
        return here
    import fsspec

    fs, path = fsspec.core.url_to_fs(source)
    local = scratch / _name(source)
    try:
        with fs.open(path, "rb") as remote, local.open("wb") as copy:
            shutil.copyfileobj(remote, copy, 1 << 20)
    except FileNotFoundError:
        raise OSError(f"{source}: no such file") from None
    except OSError as error:  # (the backends' messages seldom name the file)
        raise OSError(f"cannot read {source}: {error.strerror or error}") from None
    return local


def _replay(log_path: Path, task: LogTask) -> tuple[RunReport, SigmaMeans]:
    """The replay, as `mavest replay LOG --rrd … --estimates …`, and each stream's mean σ."""
    estimates = Path(task.estimates) if task.estimates else None
    rrd = Path(task.rrd) if task.rrd else None
    # the recording appears whole or not at all (the estimates table does by itself)
    rrd_partial = partial_path(rrd) if rrd is not None else None
    outputs = Outputs(rrd=rrd_partial, estimates=estimates)
    sigmas = SigmaMeans(task.config.input.settle_time)
    try:
        report = asyncio.run(
            replay(log_path, task.config, outputs, progress=False, sinks=(sigmas,))
        )
        if rrd is not None and rrd_partial is not None:
            publish(rrd_partial, rrd)  # (where a link points; into a FIFO, never over it)
    finally:
        if rrd_partial is not None:
            with contextlib.suppress(OSError):  # (a read-only folder refuses even this)
                rrd_partial.unlink(missing_ok=True)
    for path, error in report.output_errors.items():
        log.warning("%s stopped early: %s", rrd if path == rrd_partial else path, error)
    return report, sigmas


class SigmaMeans:
    """Each stream's mean tilt and heading σ (degrees) over its estimates from ``settle``
    s after its first, as its accuracy is scored; taken as the replay makes them (an
    estimate sink: one at a time, or many on the fast path), so that no estimates table
    need be written and read back for them. Tilt σ is the root sum square of the roll
    and pitch σ, heading σ the yaw's, as the estimates table has them
    (:func:`mavest.so3.euler_sigmas`); one that is not finite (at ±90° pitch) is left out.
    """

    def __init__(self, settle: float) -> None:
        self.settle = settle
        self._first_t: dict[StreamKey, float] = {}
        # per stream: the tilt σ sum, its count, the heading σ sum, its count
        self._sums: dict[StreamKey, list[float]] = {}
        # per stream: its error side and the settled estimates' q and attitude covariance
        # not yet summed (the fast path hands them over a few at a time, and σ costs
        # most per call: summed a block at a time)
        self._held: dict[StreamKey, tuple[str, list[np.ndarray], list[np.ndarray]]] = {}
        self._held_rows = 0

    def means(self, key: StreamKey) -> tuple[float, float]:
        """The stream's mean tilt and heading σ, degrees (NaN: none)."""
        self._sum_held()
        tilt, tilt_count, heading, heading_count = self._sums.get(key, (0.0, 0, 0.0, 0))
        return (
            tilt / tilt_count if tilt_count else math.nan,
            heading / heading_count if heading_count else math.nan,
        )

    def on_estimate(
        self,
        stream: Stream,
        sample: Any,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None:
        self._add(stream, np.array([estimate.t]), estimate.q[None], estimate.cov[None, :3, :3])

    def on_estimates(
        self,
        stream: Stream,
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
        """Many estimates of one stream, in order: the i-th is ``series[index[i]]``."""
        self._add(stream, t, q, series.cov[index, :3, :3])

    def on_reference(
        self, stream: Stream, source: str, t: float, euler: tuple, receive_us: int = 0
    ) -> None:
        """References are not estimates: nothing."""

    def on_references(
        self, stream: Stream, source: str, t: np.ndarray, euler: np.ndarray, receive_us: Any
    ) -> None:
        """As :meth:`on_reference`: nothing."""

    def _add(self, stream: Stream, t: np.ndarray, q: np.ndarray, cov: np.ndarray) -> None:
        if not t.shape[0]:
            return
        first = self._first_t.setdefault(stream.key, float(t[0]))
        picked = t >= first + self.settle
        if not picked.any():
            return
        _, qs, covs = self._held.setdefault(stream.key, (stream.estimator.config.error, [], []))
        qs.append(q[picked])
        covs.append(cov[picked])
        self._held_rows += qs[-1].shape[0]
        if self._held_rows >= _SIGMA_BLOCK:
            self._sum_held()

    def _sum_held(self) -> None:
        for key, (side, qs, covs) in self._held.items():
            if not qs:
                continue
            sigma = np.degrees(euler_sigmas(np.concatenate(qs), np.concatenate(covs), side))
            sums = self._sums.setdefault(key, [0.0, 0, 0.0, 0])
            for k, values in ((0, np.hypot(sigma[:, 0], sigma[:, 1])), (2, sigma[:, 2])):
                finite = values[np.isfinite(values)]
                sums[k] += float(finite.sum())
                sums[k + 1] += int(finite.shape[0])
            qs.clear()
            covs.clear()
        self._held_rows = 0


# Estimates whose σ are summed at a time (about 1 MB held).
_SIGMA_BLOCK = 8192


def _autopilot_name(value: int) -> str:
    entry = mavlink2.enums["MAV_AUTOPILOT"].get(value)
    return entry.name.removeprefix("MAV_AUTOPILOT_") if entry is not None else str(value)


def _rows(source: str, report: RunReport, sigmas: SigmaMeans) -> list[dict[str, Any]]:
    pipeline = report.pipeline
    log_columns = {
        "records": report.records,
        "bad_records": report.bad_records,
        "skipped_bytes": report.skipped_bytes,
    }
    if not pipeline.streams:
        row = error_row(
            source, "no IMU stream found (RAW_IMU, SCALED_IMU/2/3 or HIGHRES_IMU from a vehicle)"
        )
        row.update(log_columns)
        return [row]
    rows = []
    for stream in pipeline.every_stream:  # (one given up for a better one too)
        stats, key = stream.stats, stream.key
        vehicle = pipeline.vehicles.get((key.system, key.component))
        autopilot = stream.vs_autopilot.result()
        truth = stream.vs_truth.result()
        health = (stats.tilt_reopened, stats.diverged, stats.unhealthy, stats.clip_realigned)
        tilt_sigma, heading_sigma = sigmas.means(key)
        row = empty_row(source)
        row.update(
            system=key.system,
            component=key.component,
            autopilot=_autopilot_name(vehicle.autopilot) if vehicle is not None else None,
            fixed_wing=vehicle.fixed_wing if vehicle is not None else None,
            message=key.message,
            instance=key.instance,
            primary=stream.primary,
            samples=stats.estimated,
            received=stats.received,
            duration_s=stats.span,
            rate_hz=stream.rate,
            gaps=stats.gaps,
            rejected=stats.rejected,
            dropped=stats.duplicates + stats.out_of_order + stats.off_timeline,
            realigned=stats.realigned,
            reboots=stats.reboots,
            gyro_clipped=stats.gyro_clipped,
            tilt_reopened=stats.tilt_reopened,
            diverged=stats.diverged,
            unhealthy=stats.unhealthy,
            clip_realigned=stats.clip_realigned,
            health_events=sum(health),
            heading_referenced=stream.estimator.heading_referenced,
            tilt_rms_vs_autopilot_deg=autopilot.inclination_rms if autopilot.count else math.nan,
            heading_rms_vs_autopilot_deg=autopilot.yaw_rms if autopilot.count else math.nan,
            compared_vs_autopilot=autopilot.count,
            tilt_rms_vs_truth_deg=truth.inclination_rms if truth.count else math.nan,
            heading_rms_vs_truth_deg=truth.yaw_rms if truth.count else math.nan,
            compared_vs_truth=truth.count,
            mean_sigma_tilt_deg=tilt_sigma,
            mean_sigma_heading_deg=heading_sigma,
            **log_columns,
        )
        rows.append(row)
    return rows


class _Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@contextlib.contextmanager
def _warnings_kept() -> Iterator[list[str]]:
    """mavest's warnings while a log replays, kept for its row instead of printed (a
    worker's output is nobody's terminal)."""
    logger = logging.getLogger("mavest")
    handler = _Kept()
    handlers, propagate = logger.handlers[:], logger.propagate
    logger.handlers[:] = [handler]
    logger.propagate = False
    try:
        yield handler.lines
    finally:
        logger.handlers[:] = handlers
        logger.propagate = propagate
