"""Long runs: an hour of simulated 1 kHz flight through the pipeline, in accelerated time.

    .venv/bin/python tools/long_run.py [--minutes 60] [--rate 1000] [--seed 1]
        [--config FILE] [--only pipeline|replay] [--markdown] [--results [FILE]]

Pipeline: the JSBSim Cessna of ``mavest sim`` (ArduPilot RAW_IMU with the
magnetometer, SIMSTATE truth per sample, GPS and VFR_HUD at 10 Hz), made by
``flight_records`` 10 s at a time, goes record by record through mavest's
own tlog reader and the replay's ``Pipeline`` as fast as it goes, never as a
whole flight in memory. Every estimate is checked: NaN, the 6×6 covariance
(symmetric, Cholesky, σ within bounds, smallest eigenvalue), roll, pitch,
tilt and yaw against the truth per block (10 min), and the process's RSS
every simulated minute.

Replay: the same flight written to a tlog in a temporary folder, then the
whole command ``mavest replay FILE --out-tlog OUT`` (peak RSS and wall time of
the child process, taken by a small launcher process), beside pymavlink's plain parse of the
same file (``mavutil.mavlink_connection`` and a ``recv_match`` loop, a
process of its own), in the same run; and ``mavest replay`` of a 10 s flight
for its fixed cost. The exit status is 1 when a health check fails: a NaN,
a covariance not positive definite or out of bounds, RSS growing by more than
``--max-growth`` MiB after the warm-up, the last block's tilt more than
``--max-drift`` × the first's (and 0.25° worse), a sample with an attitude not
answered, or a replay that failed. ``--results`` writes the table (as Markdown, failed checks
included) as the Long runs section of docs/results.md (or FILE).
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import re
import resource
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mavest.evaluation import report
from mavest.evaluation.online import EulerComparison
from mavest.mavlink.tlog import TlogReader, TlogWriter
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Pipeline, Stream, answerable
from mavest.service.process import MAVEST
from mavest.service.runners import REPLAY_MESSAGES
from mavest.sim.vehicle import AUTOPILOTS, flight_records, write_flight_tlog

ARDUPILOT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "ardupilot.toml"
PARTS = ("pipeline", "replay")
MIB = 2**20
PAGE_SIZE = os.sysconf("SC_PAGE_SIZE")
WARM_UP = 600.0  # s: RSS growth counts from here (caches, the first blocks' objects)
RSS_PERIOD = 60.0  # s of flight between RSS samples
BASELINE_SECONDS = 10.0  # the short flight whose replay shows mavest's fixed memory
# Covariance bounds. A 9-D vehicle always has gravity and the field: an attitude σ
# beyond 30° means the filter has lost the attitude; below 0.001° it would claim more
# than a 1 kHz MEMS IMU can give. The gyro bias σ must stay under twice its prior (the
# bias random walk over an hour adds far less) and above 1e-5 °/s.
ATTITUDE_SIGMA_DEG = (1e-3, 30.0)
BIAS_SIGMA_PRIOR_FACTOR = 2.0
BIAS_SIGMA_MIN_DEG_S = 1e-5
ASYMMETRY_MAX = 1e-9  # max |P − Pᵀ| / max |P|
DRIFT_FLOOR_DEG = 0.25  # the last block must also be this much worse to count as drift
TLOG_STAMP = struct.Struct(">Q")  # a tlog record: 8-byte big-endian µs, then the packet
CHUNK_RECORDS = 4096  # records handed to the reader at once (about 2 s of flight)

# Runs argv[2:], then writes its peak RSS (KiB) and wall time (s) to argv[1].
LAUNCHER = """
import resource, subprocess, sys, time
start = time.perf_counter()
returncode = subprocess.call(sys.argv[2:])
wall = time.perf_counter() - start
with open(sys.argv[1], "w") as usage:
    usage.write(f"{resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss} {wall}")
sys.exit(returncode)
"""

# pymavlink's plain parse, run as a program of its own so that its RSS is pymavlink's alone.
PYMAVLINK_PARSE = """
import sys
from pymavlink import mavutil
connection = mavutil.mavlink_connection(sys.argv[1], robust_parsing=True)
messages = 0
while connection.recv_match() is not None:
    messages += 1
print(messages)
"""


def current_rss() -> int:
    """Resident set size of this process now, bytes (Linux: /proc/self/statm)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * PAGE_SIZE


def peak_rss() -> int:
    """Peak resident set size of this process so far, bytes (ru_maxrss is in KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


@dataclass
class CovarianceHealth:
    """Every estimate's 6×6 covariance of [δθ (world), δb], checked in batches.

    Positive definiteness and symmetry hold from the first sample; the σ bounds
    from the settle time on (before the magnetometer sets heading its σ is 1 rad).
    """

    attitude_sigma_bounds: tuple[float, float]  # deg
    bias_sigma_bounds: tuple[float, float]  # deg/s
    checked: int = 0
    not_positive_definite: int = 0
    out_of_bounds: int = 0
    max_asymmetry: float = 0.0
    min_eigenvalue: float = math.inf
    # (min, max) σ seen after the settle time: tilt (world x, y), heading (z), bias
    tilt_sigma: list[float] = field(default_factory=lambda: [math.inf, 0.0])  # deg
    heading_sigma: list[float] = field(default_factory=lambda: [math.inf, 0.0])  # deg
    bias_sigma: list[float] = field(default_factory=lambda: [math.inf, 0.0])  # deg/s

    def check(self, covariances: np.ndarray, settled: np.ndarray) -> None:
        """Check finite (n, 6, 6) covariances; σ bounds where ``settled`` (n,) is True."""
        if not len(covariances):
            return
        self.checked += len(covariances)
        scale = np.abs(covariances).max(axis=(1, 2))
        asymmetry = np.abs(covariances - covariances.transpose(0, 2, 1)).max(axis=(1, 2))
        self.max_asymmetry = max(self.max_asymmetry, float((asymmetry / scale).max()))
        try:
            np.linalg.cholesky(covariances)
        except np.linalg.LinAlgError:  # one of the stack failed: count which
            for matrix in covariances:
                try:
                    np.linalg.cholesky(matrix)
                except np.linalg.LinAlgError:
                    self.not_positive_definite += 1
        self.min_eigenvalue = min(
            self.min_eigenvalue, float(np.linalg.eigvalsh(covariances)[:, 0].min())
        )
        if not settled.any():
            return
        variances = np.diagonal(covariances[settled], axis1=1, axis2=2)
        sigma = np.degrees(np.sqrt(np.maximum(variances, 0.0)))
        outside = np.zeros(len(sigma), dtype=bool)
        for seen, bounds, part in (
            (self.tilt_sigma, self.attitude_sigma_bounds, sigma[:, :2]),
            (self.heading_sigma, self.attitude_sigma_bounds, sigma[:, 2:3]),
            (self.bias_sigma, self.bias_sigma_bounds, sigma[:, 3:]),
        ):
            seen[0] = min(seen[0], float(part.min()))
            seen[1] = max(seen[1], float(part.max()))
            outside |= ((part < bounds[0]) | (part > bounds[1])).any(axis=1)
        self.out_of_bounds += int(outside.sum())

    @property
    def healthy(self) -> bool:
        return (
            self.checked > 0
            and self.not_positive_definite == 0
            and self.out_of_bounds == 0
            and self.max_asymmetry <= ASYMMETRY_MAX
        )


class HealthSink:
    """An estimate sink (like the Rerun recorder): checks and scores every estimate.

    Keeps a fixed amount of memory whatever the length of the run: the last
    batch of estimates, one running comparison per block, an RSS sample a minute.
    """

    def __init__(
        self,
        duration: float,
        block: float,
        settle_time: float,
        health: CovarianceHealth,
        rss_period: float,
    ) -> None:
        self.block = block
        self.settle_time = settle_time
        self.rss_period = rss_period
        # each block scores from the run's settle time on, as the replay's summary does
        self.blocks = [
            EulerComparison(max(0.0, settle_time - i * block))
            for i in range(max(1, math.ceil(duration / block - 1e-9)))
        ]
        self.health = health
        self.estimates = 0
        self.answerable = 0  # of those, the ones with an attitude (the service answers them)
        self.nan_samples = 0
        self.rss: list[tuple[float, int]] = []  # (flight s, bytes)
        self.first_t: float | None = None
        self.elapsed = 0.0  # s of flight estimated so far
        self._started = time.perf_counter()
        self._block_index = 0
        self._next_rss = 0.0
        self._covariances = np.empty((CHUNK_RECORDS, 6, 6))
        self._values = np.empty((CHUNK_RECORDS, 10))  # q, bias, euler
        self._elapsed = np.empty(CHUNK_RECORDS)
        self._pending = 0

    def on_estimate(
        self,
        stream: Stream,
        sample: Any,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None:
        t = estimate.t
        if self.first_t is None:
            self.first_t = t
        elapsed = self.elapsed = t - self.first_t
        if elapsed >= self._next_rss:
            self.rss.append((elapsed, current_rss()))
            self._next_rss += self.rss_period
        self.estimates += 1
        self.answerable += bool(answerable(estimate.flags))
        k = self._pending
        self._covariances[k] = estimate.cov
        values = self._values[k]
        values[:4] = estimate.q
        values[4:7] = estimate.bias
        values[7:] = euler
        self._elapsed[k] = elapsed
        self._pending = k + 1
        if self._pending == CHUNK_RECORDS:
            self.check_pending()
        block_index = min(int(elapsed / self.block), len(self.blocks) - 1)
        if block_index != self._block_index:
            self._report_progress()
            self._block_index = block_index
        self.blocks[self._block_index].add_estimate(t, euler)

    def on_reference(
        self,
        stream: Stream,
        source: str,
        t: float,
        euler: tuple[float, float, float],
        receive_us: int,
    ) -> None:
        if source == "truth":  # SIMSTATE, right after the IMU sample it belongs to
            self.blocks[self._block_index].add_reference(t, euler)

    def check_pending(self) -> None:
        n = self._pending
        covariances, values = self._covariances[:n], self._values[:n]
        finite = np.isfinite(covariances).all(axis=(1, 2)) & np.isfinite(values).all(axis=1)
        self.nan_samples += int(n - finite.sum())
        settled = self._elapsed[:n][finite] >= self.settle_time
        self.health.check(covariances[finite], settled)
        self._pending = 0

    def _report_progress(self) -> None:
        result = self.blocks[self._block_index].result()
        print(
            f"  flight minute {self.elapsed / 60:g}: tilt {result.inclination_rms:.3f}° RMS in "
            f"the block, RSS {current_rss() / MIB:.1f} MiB, "
            f"wall {time.perf_counter() - self._started:.0f} s",
            file=sys.stderr,
            flush=True,
        )

    def finish(self) -> None:
        self.check_pending()
        if self.first_t is not None:
            self.rss.append((self.elapsed, current_rss()))


class PipelineFeed:
    """Takes a simulated flight's records (``flight_records``) and replays them.

    Records are gathered a few thousand at a time and read back with mavest's own
    tlog reader, then handed to the pipeline exactly as ``runners.replay`` does
    (the messages it decodes, HEARTBEAT at the configured rate); with ``tee``
    they also go to that file, for the replay part.
    """

    def __init__(self, pipeline: Pipeline, config: ServiceConfig, tee: Path | None) -> None:
        self.pipeline = pipeline
        rate = config.output.heartbeat_rate
        self.heartbeat_us = int(1e6 / rate) if rate else 0
        self.next_heartbeat_us = 0
        self.tee = TlogWriter(tee) if tee is not None else None
        self.records = 0
        self.pipeline_seconds = 0.0  # wall time spent reading and in the pipeline
        self._chunk = bytearray()
        self._chunk_records = 0

    def write(self, timestamp_us: int, packet: bytes) -> None:
        if self.tee is not None:
            self.tee.write(timestamp_us, packet)
        self._chunk += TLOG_STAMP.pack(timestamp_us)
        self._chunk += packet
        self._chunk_records += 1
        if self._chunk_records == CHUNK_RECORDS:
            self._replay_chunk()

    def _replay_chunk(self) -> None:
        start = time.perf_counter()
        pipeline = self.pipeline
        reader = TlogReader(bytes(self._chunk), REPLAY_MESSAGES)
        for record in reader:  # the body of runners.replay's loop, without its output tlog
            stamp = record.timestamp_us
            if record.message is not None:
                pipeline.on_message(record.message, stamp)
            if self.heartbeat_us and stamp >= self.next_heartbeat_us and pipeline.vehicles:
                pipeline.heartbeat()
                self.next_heartbeat_us = stamp + self.heartbeat_us
        self.records += reader.stats.records
        self._chunk.clear()
        self._chunk_records = 0
        self.pipeline_seconds += time.perf_counter() - start

    def close(self) -> None:
        self._replay_chunk()
        if self.tee is not None:
            self.tee.close()

    def __enter__(self) -> PipelineFeed:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class PipelineRun:
    seconds: float  # of flight
    expected_samples: int
    stream: Stream | None
    sink: HealthSink
    records: int
    wall: float
    pipeline_seconds: float
    peak_rss: int


def fly_through_pipeline(
    config: ServiceConfig, seconds: float, rate: float, seed: int, block: float, tee: Path | None
) -> PipelineRun:
    estimator = config.estimator
    bias_prior = math.degrees(estimator.initial_bias_sigma)
    health = CovarianceHealth(
        ATTITUDE_SIGMA_DEG, (BIAS_SIGMA_MIN_DEG_S, BIAS_SIGMA_PRIOR_FACTOR * bias_prior)
    )
    # a minute between RSS samples, or a thirtieth of a short run
    rss_period = min(RSS_PERIOD, seconds / 30.0)
    sink = HealthSink(seconds, block, config.input.settle_time, health, rss_period)
    pipeline = Pipeline(config, sinks=[sink])
    feed = PipelineFeed(pipeline, config, tee)
    # as runners.replay does before its loop: what is alive now is never walked again
    gc.collect()
    gc.freeze()
    start = time.perf_counter()
    # the records write_flight_tlog would write, in the same order, made chunk by
    # chunk: the flight is never whole in memory
    with feed:
        for stamp, packet in flight_records(seconds, rate, AUTOPILOTS["ardupilot"], seed=seed):
            feed.write(stamp, packet)
    sink.finish()
    wall = time.perf_counter() - start
    streams = list(pipeline.streams.values())
    return PipelineRun(
        seconds,
        round(seconds * rate) + 1,  # write_flight_tlog's samples: both ends included
        streams[0] if streams else None,
        sink,
        feed.records,
        wall,
        feed.pipeline_seconds,
        peak_rss(),
    )


@dataclass
class Measured:
    """A child process: wall time, peak RSS, exit status, what it printed."""

    wall: float
    peak_rss: int
    returncode: int
    stdout: str


def run_measured(command: list[str]) -> Measured:
    """Run a command through a small launcher process and take its peak RSS from there.

    Measured from this process (``os.wait4`` or RUSAGE_CHILDREN), a child's ru_maxrss
    starts at this process's own RSS at the fork, a few hundred MiB after the pipeline
    part; the launcher is ~10 MiB, so that is the floor of what it reports.
    """
    with tempfile.TemporaryDirectory() as folder:
        usage = Path(folder) / "usage"
        finished = subprocess.run(
            [sys.executable, "-c", LAUNCHER, str(usage), *command],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        peak_kib, wall = usage.read_text().split()
    return Measured(float(wall), int(peak_kib) * 1024, finished.returncode, finished.stdout)


@dataclass
class ReplayRun:
    tlog_bytes: int
    mavest: Measured
    mavest_samples: int | None  # from its summary
    pymavlink: Measured
    pymavlink_messages: int | None
    baseline: Measured  # mavest replay of a short flight


def replay_part(tlog: Path, config_path: Path, rate: float, seed: int, workdir: Path) -> ReplayRun:
    command = [*MAVEST, "replay", "--config", str(config_path), "-q"]
    mavest = run_measured([*command, str(tlog), "--out-tlog", str(workdir / "out.tlog")])
    match = re.search(r"(\d+) IMU samples estimated", mavest.stdout)
    pymavlink = run_measured([sys.executable, "-c", PYMAVLINK_PARSE, str(tlog)])
    counted = pymavlink.stdout.strip().splitlines()
    short = workdir / "short.tlog"
    write_flight_tlog(short, BASELINE_SECONDS, rate, AUTOPILOTS["ardupilot"], seed=seed)
    baseline = run_measured([*command, str(short), "--out-tlog", str(workdir / "short_out.tlog")])
    return ReplayRun(
        tlog.stat().st_size,
        mavest,
        int(match.group(1)) if match else None,
        pymavlink,
        int(counted[-1]) if counted and counted[-1].isdigit() else None,
        baseline,
    )


# ------------------------------------------------------------------ the table


@dataclass
class Table:
    rows: list[tuple[str, str]] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def add(self, label: str, value: str) -> None:
        self.rows.append((label, value))

    def check(self, label: str, passed: bool, value: str) -> None:
        self.rows.append((f"check: {label}", f"{'✓' if passed else '✗ FAIL'} {value}"))
        if not passed:
            self.failures.append(label)

    def render(self, markdown: bool) -> str:
        if markdown:
            lines = ["| long run | |", "|---|---|"]
            lines += [f"| {label} | {value} |" for label, value in self.rows]
            return "\n".join(lines)
        width = max(len(label) for label, _ in self.rows)
        return "\n".join(f"{label:<{width}}  {value}" for label, value in self.rows)


def _mib(value: float) -> str:
    return f"{value / MIB:.1f} MiB"


def _wall(seconds: float) -> str:
    """Whole seconds, or hundredths below ten (a short run's replay takes under one)."""
    return f"{seconds:.0f} s" if seconds >= 10.0 else f"{seconds:.2f} s"


def _rss_at(samples: list[tuple[float, int]], t: float) -> tuple[float, int]:
    """The RSS sample nearest to flight time t."""
    return min(samples, key=lambda sample: abs(sample[0] - t))


def pipeline_rows(
    table: Table, run: PipelineRun, rate: float, max_growth: float, max_drift: float
) -> None:
    sink, health, stream = run.sink, run.sink.health, run.stream
    minutes = run.seconds / 60.0
    table.add("flight", f"{minutes:g} min at {rate:g} Hz, {run.records:,} MAVLink records")
    received = stream.stats.received if stream else 0
    answered = stream.stats.answered if stream else 0
    table.add(
        "IMU samples in / estimated / answered",
        f"{received:,} / {sink.estimates:,} / {answered:,} (expected {run.expected_samples:,})",
    )
    table.add(
        "wall time (simulation + pipeline)",
        f"{run.wall:.0f} s, {run.seconds / run.wall:.1f}× real time "
        f"(pipeline alone {run.pipeline_seconds:.0f} s, "
        f"{run.seconds / max(run.pipeline_seconds, 1e-9):.1f}×)",
    )
    rss = sink.rss
    warm_up = min(WARM_UP, run.seconds / 2.0)
    at_warm_up, end = _rss_at(rss, warm_up), rss[-1]
    first = rss[1] if len(rss) > 2 else rss[0]  # a minute in (or a thirtieth of the run)
    growth = end[1] - at_warm_up[1]
    span_hours = max(run.seconds - at_warm_up[0], 1e-9) / 3600.0
    table.add(
        "RSS at flight minute",
        f"{first[0] / 60:.3g}: {_mib(first[1])}, {at_warm_up[0] / 60:.3g}: {_mib(at_warm_up[1])}, "
        f"end ({minutes:g}): {_mib(end[1])}",
    )
    table.add(
        f"RSS growth, minute {at_warm_up[0] / 60:g} → end",
        f"{growth / MIB:+.2f} MiB ({growth / MIB / span_hours:+.2f} MiB/h)",
    )
    table.add("peak RSS (this process)", _mib(run.peak_rss))
    table.add(
        f"covariance σ after {sink.settle_time:g} s (min–max)",
        f"tilt {health.tilt_sigma[0]:.3g}–{health.tilt_sigma[1]:.3g}°, "
        f"heading {health.heading_sigma[0]:.3g}–{health.heading_sigma[1]:.3g}°, "
        f"gyro bias {health.bias_sigma[0]:.3g}–{health.bias_sigma[1]:.3g} °/s",
    )
    table.add(
        "covariance: min eigenvalue, max asymmetry (relative)",
        f"{health.min_eigenvalue:.3g}, {health.max_asymmetry:.2g}",
    )
    accuracy = [block.result() for block in sink.blocks]
    for i, result in enumerate(accuracy):
        start, stop = i * sink.block / 60.0, min((i + 1) * sink.block, run.seconds) / 60.0
        table.add(
            f"block {start:g}–{stop:g} min: roll / pitch / tilt / yaw RMS",
            f"{result.roll_rms:.3f} / {result.pitch_rms:.3f} / {result.inclination_rms:.3f} / "
            f"{result.yaw_rms:.3f}° (n={result.count:,})",
        )
    if stream is not None:
        whole = stream.vs_truth.result()
        table.add(
            "whole run (the replay summary's figure)",
            f"{whole.roll_rms:.3f} / {whole.pitch_rms:.3f} / {whole.inclination_rms:.3f} / "
            f"{whole.yaw_rms:.3f}° (n={whole.count:,})",
        )
    scored = [result for result in accuracy if result.count] or accuracy
    first_block, last_block = scored[0], scored[-1]  # blocks within the settle time have none
    ratios = [
        last / first if first > 0 else math.nan
        for first, last in (
            (first_block.roll_rms, last_block.roll_rms),
            (first_block.pitch_rms, last_block.pitch_rms),
            (first_block.inclination_rms, last_block.inclination_rms),
            (first_block.yaw_rms, last_block.yaw_rms),
        )
    ]
    table.add("last / first scored block RMS", " / ".join(f"{r:.2f}" for r in ratios))

    table.check(
        "every sample estimated, and answered once the filter has an attitude",
        received == sink.estimates == run.expected_samples and answered == sink.answerable,
        f"{answered:,} answered of {sink.answerable:,} with an attitude, "
        f"{sink.estimates:,} of {run.expected_samples:,} estimated",
    )
    table.check("no NaN", sink.nan_samples == 0, f"{sink.nan_samples} estimates with a NaN")
    bias_low, bias_high = health.bias_sigma_bounds
    table.check(
        "covariance healthy",
        health.healthy,
        f"{health.checked:,} checked: {health.not_positive_definite} not positive definite "
        f"(Cholesky), {health.out_of_bounds} settled with σ outside attitude "
        f"{ATTITUDE_SIGMA_DEG[0]:g}–{ATTITUDE_SIGMA_DEG[1]:g}°, bias "
        f"{bias_low:g}–{bias_high:.3g} °/s; asymmetry ≤ {ASYMMETRY_MAX:g}",
    )
    table.check(
        "memory flat",
        growth <= max_growth * MIB,
        f"{growth / MIB:+.2f} MiB after minute {at_warm_up[0] / 60:g} (bound {max_growth:g} MiB)",
    )
    first_tilt, last_tilt = first_block.inclination_rms, last_block.inclination_rms
    drifted = last_tilt > max_drift * first_tilt and last_tilt - first_tilt > DRIFT_FLOOR_DEG
    table.check(
        "accuracy steady",
        first_block.count > 0 and last_block.count > 0 and not drifted,
        f"tilt {first_tilt:.3f}° → {last_tilt:.3f}° (bound {max_drift:g}× and "
        f"+{DRIFT_FLOOR_DEG:g}°)",
    )


def replay_rows(table: Table, run: ReplayRun, expected_samples: int) -> None:
    mavest, pymavlink, baseline = run.mavest, run.pymavlink, run.baseline
    table.add("replayed tlog", f"{run.tlog_bytes / 1e6:.0f} MB, {run.pymavlink_messages} messages")
    table.add(
        "`mavest replay FILE --out-tlog OUT`: peak RSS, wall",
        f"{_mib(mavest.peak_rss)}, {_wall(mavest.wall)} ({run.mavest_samples} samples estimated)",
    )
    table.add(
        "pymavlink parse (mavlink_connection + recv_match): peak RSS, wall",
        f"{_mib(pymavlink.peak_rss)}, {_wall(pymavlink.wall)}",
    )
    table.add(
        f"`mavest replay` of a {BASELINE_SECONDS:g} s flight: peak RSS, wall",
        f"{_mib(baseline.peak_rss)}, {baseline.wall:.1f} s",
    )
    table.check(
        "replay ran",
        mavest.returncode == 0 and pymavlink.returncode == 0 and baseline.returncode == 0,
        f"exit {mavest.returncode} (mavest), {pymavlink.returncode} (pymavlink), "
        f"{baseline.returncode} (short)",
    )
    table.check(
        "replay estimated every sample",
        run.mavest_samples == expected_samples,
        f"{run.mavest_samples} of {expected_samples:,}",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 2)[2],
    )
    parser.add_argument("--minutes", type=float, default=60.0, help="flight length (default 60)")
    parser.add_argument("--rate", type=float, default=1000.0, help="IMU rate, Hz (default 1000)")
    parser.add_argument("--seed", type=int, default=1, help="the flight (default 1)")
    parser.add_argument(
        "--config", type=Path, default=ARDUPILOT_CONFIG, help="mavest configuration (TOML)"
    )
    parser.add_argument(
        "--block-minutes", type=float, default=10.0, help="accuracy block length (default 10)"
    )
    parser.add_argument(
        "--max-growth",
        type=float,
        default=16.0,
        help="RSS growth allowed after minute 10 (or mid-run), MiB (default 16)",
    )
    parser.add_argument(
        "--max-drift",
        type=float,
        default=2.0,
        help="last block's tilt RMS allowed, × the first's (default 2)",
    )
    parser.add_argument(
        "--only", choices=PARTS, action="append", help="run only this part (default: both)"
    )
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    if not (args.minutes > 0 and args.rate > 0 and args.block_minutes > 0):
        parser.error("--minutes, --rate and --block-minutes must be positive")
    parts = args.only or list(PARTS)
    config = ServiceConfig.from_toml(args.config)
    seconds = args.minutes * 60.0
    expected = round(seconds * args.rate) + 1
    table = Table()
    with tempfile.TemporaryDirectory(prefix="long_run_") as folder:
        workdir = Path(folder)
        tlog = workdir / "flight.tlog"
        if "pipeline" in parts:
            tee = tlog if "replay" in parts else None  # one simulation serves both parts
            run = fly_through_pipeline(
                config, seconds, args.rate, args.seed, args.block_minutes * 60.0, tee
            )
            pipeline_rows(table, run, args.rate, args.max_growth, args.max_drift)
            print(f"pipeline part done in {run.wall:.0f} s", file=sys.stderr, flush=True)
        else:
            write_flight_tlog(tlog, seconds, args.rate, AUTOPILOTS["ardupilot"], seed=args.seed)
        if "replay" in parts:
            replayed = replay_part(tlog, args.config, args.rate, args.seed, workdir)
            replay_rows(table, replayed, expected)
    with report.results_section(args.results, "Long runs", __file__, argv, __doc__):
        print(table.render(args.markdown or args.results is not None))
    if table.failures:
        print(f"failed: {', '.join(table.failures)}", file=sys.stderr)
    return 1 if table.failures else 0


if __name__ == "__main__":
    sys.exit(main())
