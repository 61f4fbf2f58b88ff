"""``mavest replay LOG --smooth``: the smoothed estimate beside the online one.

The smoother must be given exactly what the online filter took, whichever replay path
took it; its figures must be scored over the same samples as the online ones; it must
appear in the summary, the estimates table and the recording, and cost nothing when
not asked for.
"""

from __future__ import annotations

import asyncio
import csv
import math
import threading
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from test_hostile_input import CASES, _tlog_bytes, clean_flights
from test_onboard_replay import _synthetic_log
from test_rerun import _scalars

import mavest
import mavest.service.estimates_table as estimates_table
import mavest.service.runners as runners
import mavest.service.smoothing as smoothing
from mavest.cli import main
from mavest.estimator import InputError, smoother
from mavest.evaluation.online import ESTIMATE, REFERENCE, EulerComparison
from mavest.mavlink.messages import MAVLink
from mavest.mavlink.tlog import TlogWriter
from mavest.service.config import ServiceConfig
from mavest.service.estimates_table import COLUMNS, SMOOTHED_COLUMNS
from mavest.service.runners import Outputs, RunReport, replay
from mavest.service.smoothing import (
    CHUNK,
    RecordedComparison,
    RecordedInputs,
    measured_interval_acceleration,
)
from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog
from mavest.viz.blueprint import stream_layout
from mavest.viz.recorder import stream_root

ONLINE = {
    "qw": "smoothed_qw",
    "qx": "smoothed_qx",
    "qy": "smoothed_qy",
    "qz": "smoothed_qz",
    "sigma_roll_deg": "smoothed_sigma_roll_deg",
    "sigma_pitch_deg": "smoothed_sigma_pitch_deg",
    "sigma_yaw_deg": "smoothed_sigma_yaw_deg",
    "bias_x_dps": "smoothed_bias_x_dps",
    "bias_y_dps": "smoothed_bias_y_dps",
    "bias_z_dps": "smoothed_bias_z_dps",
}
ANGLES = {"roll_deg": "smoothed_roll_deg", "pitch_deg": "smoothed_pitch_deg"}


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 s at 200 Hz, turning, with GPS, airspeed, magnetometer and truth."""
    path = tmp_path_factory.mktemp("flight") / "flight.tlog"
    write_flight_tlog(path, 30.0, 200.0, AUTOPILOTS["ardupilot"], seed=5)
    return path


def _replay(
    log: Path, outputs: Outputs | None = None, fast: bool = True, smooth: bool = True, **kw: Any
) -> RunReport:
    return asyncio.run(
        replay(
            log,
            ServiceConfig(),
            outputs or Outputs(),
            progress=False,
            fast=fast,
            smooth=smooth,
            **kw,
        )
    )


def _read(path: Path) -> dict[str, np.ndarray]:
    """A table's columns (numbers as float; ``message`` as text), in the file's order."""
    if path.suffix == ".parquet":
        table = pq.read_table(path)
        return {
            name: np.array(
                table.column(name).to_pylist(), dtype=None if name == "message" else float
            )
            for name in table.column_names
            if name != "accel_used"
        }
    with path.open(newline="") as stream:
        rows = list(csv.reader(stream))
    columns: dict[str, np.ndarray] = {}
    for i, name in enumerate(rows[0]):
        values = [row[i] for row in rows[1:]]
        if name not in ("message", "accel_used"):
            columns[name] = np.array([float(v) for v in values])
    return columns


def _in_one_block(run: Any) -> Any:
    """A function of smooth's arguments that returns a whole series (the filter, say), as
    ``smooth_blocks`` gives its result: here in one block."""

    def blocks(*args: Any) -> Any:
        yield 0, run(*args)

    return blocks


# ------------------------------------------------------------------ the inputs


@pytest.mark.parametrize("fast", [True, False])
def test_with_the_filter_in_the_smoothers_place_the_smoothed_columns_are_the_online_ones(
    fast: bool, flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What is kept is exactly what the filter took (the specific force after the airspeed
    correction, the magnetometer where usable, the GPS acceleration), whichever path took
    it: the filter run again over it gives the online estimate, bit for bit, and the
    comparisons made again give the online figures."""
    monkeypatch.setattr(smoothing, "smooth_blocks", _in_one_block(mavest.estimate))
    # (the GPS acceleration's move to its interval is the smoother's, not the filter's)
    monkeypatch.setattr(smoothing, "measured_interval_acceleration", lambda a: a)
    table = tmp_path / "estimates.csv"
    report = _replay(flight, Outputs(estimates=table), fast=fast)
    (stream,) = report.streams
    assert stream.stats.gps_aided and stream.stats.airspeed_aided and stream.stats.mag_used
    columns = _read(table)
    assert len(columns["qw"]) == stream.stats.estimated
    for online, smoothed in ONLINE.items():
        np.testing.assert_array_equal(columns[smoothed], columns[online], err_msg=online)
    for online, smoothed in ANGLES.items():
        np.testing.assert_allclose(columns[smoothed], columns[online], atol=1e-9)
    smoothed_stream = report.smoothed[stream.key]
    assert smoothed_stream.vs_truth == stream.vs_truth.result()
    assert smoothed_stream.vs_autopilot == stream.vs_autopilot.result()


def _roll_tlog(
    path: Path, roll: Callable[[float], float], accel_g: Callable[[float], float]
) -> None:
    """An ArduPilot vehicle's RAW_IMU at 200 Hz for 15 s, rolled by ``roll(t)`` (rad) about
    its x axis, its accelerometer ``accel_g(t)`` g along the vertical, its magnetometer
    consistent: the gyro field saturates (32767 mrad/s) where it rolls faster."""
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    rng = np.random.default_rng(0)
    with TlogWriter(path) as tlog:
        heartbeat = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, 3, 0, 0, 0)
        tlog.write(0, heartbeat.pack(mav))
        for k in range(1, 3001):
            t = k / 200.0
            phi, rate = roll(t), (roll(t + 1e-4) - roll(t - 1e-4)) / 2e-4
            s, c = math.sin(phi), math.cos(phi)
            a = 1000.0 * accel_g(t)
            noise = rng.normal(0.0, 2.0, 6)
            raw = mav.raw_imu_encode(
                round(t * 1e6),
                round(noise[0]),
                round(-a * s + noise[1]),
                round(-a * c + noise[2]),
                min(32767, round(rate * 1000.0 + noise[3])),
                round(noise[4]),
                round(noise[5]),
                200,
                round(400 * s),
                round(400 * c),
                0,
                3500,
            )
            tlog.write(round(t * 1e6), raw.pack(mav))


def test_a_clipped_gyro_starts_a_smoothing_timeline(tmp_path: Path) -> None:
    """Level, then rolled 90° in 0.04 s at 39 rad/s (the gyro field saturates: those
    samples are rejected and the filter re-aligns tilt when calm): the smoother carries no
    attitude across the rotation it cannot know, so each side is smoothed on its own.
    Across it, both passes took the other side's attitude: 42° off everywhere."""
    log = tmp_path / "clip.tlog"
    _roll_tlog(log, lambda t: min(max(t - 5.0, 0.0) / 0.04, 1.0) * math.pi / 2, lambda t: 1.0)
    table = tmp_path / "estimates.csv"
    report = _replay(log, Outputs(estimates=table))
    (stream,) = report.streams
    assert stream.stats.rejected > 0
    columns = _read(table)
    t = columns["time_s"]
    truth = np.where(t > 5.04, 90.0, 0.0)
    away = (t < 5.0) | (t > 5.6)  # (the filter waits for calm before it re-aligns)
    error = np.abs(columns["smoothed_roll_deg"] - truth)[away]
    assert np.all(np.isfinite(error)) and np.max(error) < 1.0, np.max(error)


def test_where_the_smoother_has_no_estimate_none_is_shown(tmp_path: Path) -> None:
    """The first second's accelerometer reads 2 g: neither pass has an attitude there, and
    the smoothed columns are NaN, not the filter's placeholders (identity, its initial σ)."""
    log = tmp_path / "late.tlog"
    _roll_tlog(log, lambda t: 0.3, lambda t: 2.0 if t < 1.0 else 1.0)
    table = tmp_path / "estimates.csv"
    _replay(log, Outputs(estimates=table))
    columns = _read(table)
    first = columns["time_s"] < 0.9
    not_started = (columns["flags"].astype(np.int64) & mavest.StepFlags.NOT_INITIALISED) != 0
    assert first.any() and np.all(not_started[first])
    for name in ("smoothed_qw", "smoothed_roll_deg", "smoothed_sigma_roll_deg"):
        assert np.all(np.isnan(columns[name][first])), name
    later = columns["time_s"] > 3.0
    assert np.all(np.abs(columns["smoothed_roll_deg"][later] - math.degrees(0.3)) < 1.0)


def test_a_stream_the_smoother_refuses_whole_keeps_its_smoothed_columns(tmp_path: Path) -> None:
    """An accelerometer at 2 g throughout: nothing starts either filter. The table keeps
    its smoothed columns, NaN (a reader of it finds the columns it asked for), and the
    summary says none was smoothed."""
    log = tmp_path / "two_g.tlog"
    _roll_tlog(log, lambda t: 0.0, lambda t: 2.0)
    table = tmp_path / "estimates.parquet"
    report = _replay(log, Outputs(estimates=table))
    columns = pq.read_table(table).to_pydict()
    for name in SMOOTHED_COLUMNS:
        assert np.all(np.isnan(np.asarray(columns[name], dtype=float))), name
    assert "smoothed: none of its 3000 samples: the smoother refused them" in report.summary()


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return clean_flights(tmp_path_factory)


@pytest.mark.parametrize("case", ["reboot", "one_timestamp_hours_off", "highres_nan_inf"])
def test_a_reboot_starts_a_segment_and_rejected_samples_are_not_inputs(
    case: str, flights: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    flavour, make = CASES[case]
    path = tmp_path / "damaged.tlog"
    path.write_bytes(_tlog_bytes(make(flights[flavour]).chunks))
    calls: list[int] = []

    def filter_again(t: np.ndarray, *args: Any) -> Any:
        calls.append(t.shape[0])
        assert np.all(np.diff(t) > 0.0)  # one timeline each
        return mavest.estimate(t, *args)

    monkeypatch.setattr(smoothing, "smooth_blocks", _in_one_block(filter_again))
    monkeypatch.setattr(smoothing, "measured_interval_acceleration", lambda a: a)
    table = tmp_path / "estimates.parquet"
    report = _replay(path, Outputs(estimates=table))
    (stream,) = report.streams
    assert sum(calls) == stream.stats.estimated
    assert len(calls) == 1 + stream.stats.reboots
    columns = _read(table)
    for online, smoothed in ONLINE.items():
        np.testing.assert_array_equal(columns[smoothed], columns[online], err_msg=online)
    assert report.smoothed[stream.key].vs_truth == stream.vs_truth.result()


def test_a_timeline_the_smoother_refuses_is_left_out_not_the_stream(
    flights: dict[str, Any],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A reboot whose timeline nothing can start the filter on (say, the vehicle carried
    off) costs the smoothing of that timeline only: NaN there, the one before smoothed
    and scored, one line to say so."""
    flavour, make = CASES["reboot"]
    path = tmp_path / "damaged.tlog"
    path.write_bytes(_tlog_bytes(make(flights[flavour]).chunks))
    segments: list[int] = []

    def refuse_the_second(t: np.ndarray, *args: Any) -> Any:
        segments.append(t.shape[0])
        if len(segments) == 2:
            raise InputError("nothing estimated")
        return mavest.estimate(t, *args)

    monkeypatch.setattr(smoothing, "smooth_blocks", _in_one_block(refuse_the_second))
    monkeypatch.setattr(smoothing, "measured_interval_acceleration", lambda a: a)
    table, rrd = tmp_path / "estimates.csv", tmp_path / "run.rrd"
    config = ServiceConfig().replace(input={"settle_time": 1.0})  # (scored from 1 s on)
    report = asyncio.run(
        replay(path, config, Outputs(estimates=table, rrd=rrd), progress=False, smooth=True)
    )
    (stream,) = report.streams
    first, second = segments
    assert first + second == stream.stats.estimated
    columns = _read(table)
    for online, smoothed in ONLINE.items():
        np.testing.assert_array_equal(columns[smoothed][:first], columns[online][:first])
        assert np.all(np.isnan(columns[smoothed][first:])), smoothed
    smoothed_stream = report.smoothed[stream.key]
    assert smoothed_stream.refused == second
    score = smoothed_stream.vs_truth
    assert score is not None and 0 < score.count < stream.vs_truth.result().count
    assert all(math.isfinite(v) for v in (score.roll_rms, score.pitch_rms, score.yaw_rms))
    assert f"smoothed: {first} of {first + second} samples" in runners.format_summary(report)
    refused = [r.getMessage() for r in caplog.records if "not smoothed" in r.getMessage()]
    assert len(refused) == 1 and f"samples {first + 1}–{first + second}" in refused[0]
    assert rrd.stat().st_size > 0


def test_both_paths_give_the_same_smoothed_table(flight: Path, tmp_path: Path) -> None:
    tables = []
    for fast in (True, False):
        table = tmp_path / f"{fast}.parquet"
        _replay(flight, Outputs(estimates=table), fast=fast)
        tables.append(table.read_bytes())
    assert pq.read_table(table).column_names == [*COLUMNS, *SMOOTHED_COLUMNS]
    assert tables[0] == tables[1]


# ------------------------------------------------------------------ the outputs


@pytest.fixture(scope="module")
def smoothed_run(flight: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("smoothed")
    table, rrd = folder / "estimates.csv", folder / "replay.rrd"
    report = _replay(flight, Outputs(estimates=table, rrd=rrd))
    return {"report": report, "table": table, "rrd": rrd}


def test_the_smoothed_estimate_is_the_smoother_on_the_inputs_and_beats_the_filter(
    smoothed_run: dict[str, Any],
) -> None:
    report = smoothed_run["report"]
    (stream,) = report.streams
    smoothed = report.smoothed[stream.key]
    assert len(smoothed) == stream.stats.estimated
    columns = _read(smoothed_run["table"])
    np.testing.assert_array_equal(columns["time_s"], smoothed.t)
    np.testing.assert_array_equal(columns["smoothed_qw"], smoothed.q[:, 0])
    np.testing.assert_array_equal(columns["smoothed_roll_deg"], np.degrees(smoothed.euler[:, 0]))
    # the whole flight at each sample: closer to the truth, and surer
    online, better = stream.vs_truth.result(), smoothed.vs_truth
    assert better.count == online.count > 0
    assert better.inclination_rms < online.inclination_rms
    assert better.yaw_rms < online.yaw_rms
    # surer. Near the log's end the backward pass knows little yet and the smoothed
    # estimate is nearly the smoother's own forward pass, which takes the GPS acceleration
    # over its interval instead of lagging as online: there (measured: the last 5.5 s of
    # 30) its σ may exceed the online one by a few percent, never elsewhere
    end = columns["time_s"] > columns["time_s"][-1] - 10.0
    for axis in ("roll", "pitch", "yaw"):
        smoothed_sigma, online_sigma = (columns[f"{k}sigma_{axis}_deg"] for k in ("smoothed_", ""))
        assert np.all(smoothed_sigma[~end] <= online_sigma[~end] + 1e-9), axis
        assert np.all(smoothed_sigma[end] <= 1.05 * online_sigma[end]), axis
    assert smoothed.vs_autopilot is not None and smoothed.vs_autopilot.count == 0  # none logged


def test_the_summary_scores_the_smoothed_estimate_as_the_online_one(
    smoothed_run: dict[str, Any],
) -> None:
    report = smoothed_run["report"]
    (stream,) = report.streams
    summary = report.summary()
    smoothed = report.smoothed[stream.key].vs_truth
    line = f"    smoothed vs truth (SIMSTATE) after 10 s: {smoothed.describe(True)}"
    assert line in summary.splitlines()
    assert summary.index("    vs truth (SIMSTATE)") < summary.index(line)
    assert f"smoothed: {stream.stats.estimated} samples" in summary


def test_the_recording_has_the_smoothed_estimate_and_its_band_beside_the_online_one(
    smoothed_run: dict[str, Any],
) -> None:
    report = smoothed_run["report"]
    (stream,) = report.streams
    smoothed = report.smoothed[stream.key]
    series = _scalars(smoothed_run["rrd"])
    root = "/" + stream_root(stream.key)
    online_t = series[f"{root}/attitude/roll/mavest"][0]
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        t, values, has_receive_time = series[f"{root}/attitude/{axis}/smoothed"]
        assert not has_receive_time  # vehicle time only: no sample was received then
        np.testing.assert_allclose(t, online_t, atol=1e-9)  # the same timeline
        np.testing.assert_allclose(values[:, 0], np.degrees(smoothed.euler[:, i]), atol=1e-9)
        band_t, band, _ = series[f"{root}/attitude/{axis}/smoothed_3sigma"]
        assert band.shape[1] == 2 and 0.45 * len(t) < len(band_t) <= 0.5 * len(t) + 1  # 100 Hz
        at = np.searchsorted(t, band_t - 1e-9)
        width = (band[:, 0] - band[:, 1]) / 6.0
        np.testing.assert_allclose(width, np.degrees(smoothed.sigma[at, i]), rtol=1e-9)
    # the layout's attitude plots show everything under their origin: the smoothed too
    attitude = stream_layout(stream_root(stream.key)).contents[1].contents[0]
    roll = attitude.contents[0]
    assert f"/{roll.origin}/smoothed".startswith(f"{root}/attitude/roll")
    assert "smoothed ±3σ" in roll.name


def test_without_smooth_nothing_is_kept_and_the_table_is_the_online_part(
    flight: Path, smoothed_run: dict[str, Any], tmp_path: Path
) -> None:
    table = tmp_path / "plain.csv"
    report = _replay(flight, Outputs(estimates=table), smooth=False)
    (stream,) = report.streams
    assert stream.inputs is None and type(stream.vs_truth) is EulerComparison
    assert not report.smoothed and "smoothed" not in report.summary()
    # the same bytes as the --smooth table's first columns, which ends each row
    with_smooth = smoothed_run["table"].read_text().splitlines()
    plain = table.read_text().splitlines()
    assert plain[0] == ",".join(COLUMNS)
    width = len(",".join(SMOOTHED_COLUMNS)) + 1
    assert with_smooth[0][:-width] == plain[0]
    cut = [",".join(row.split(",")[: len(COLUMNS)]) for row in with_smooth]
    assert cut == plain


def test_a_table_that_cannot_take_the_smoothed_columns_keeps_the_online_ones(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def full(source: Path, target: Path, *args: Any) -> None:
        target.write_bytes(b"part")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(estimates_table, "_add_csv_columns", full)
    table = tmp_path / "e.csv"
    report = _replay(flight, Outputs(estimates=table))
    assert table.read_text().splitlines()[0] == ",".join(COLUMNS)
    assert len(table.read_text().splitlines()) - 1 == report.streams[0].stats.estimated
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.csv"]  # no partial file left
    assert f"cannot add the smoothed columns to {table}: No space left on device" in caplog.text


async def _smoothed_replay(flight: Path, estimates: Path, stop: asyncio.Event) -> RunReport:
    """``replay --smooth --estimates ESTIMATES`` of the flight, stopped by ``stop``."""
    return await replay(
        flight,
        ServiceConfig(),
        Outputs(estimates=estimates),
        progress=False,
        stop=stop,
        smooth=True,
    )


def test_an_interrupted_replay_is_not_smoothed_and_says_so(
    flight: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async def stopped() -> RunReport:
        stop = asyncio.Event()
        stop.set()  # Ctrl-C at once: the replay ends after its first stretch
        return await _smoothed_replay(flight, tmp_path / "e.csv", stop)

    report = asyncio.run(stopped())
    assert report.interrupted and not report.smoothed
    assert "  smoothing skipped: the replay was interrupted" in report.summary().splitlines()
    assert [r.message for r in caplog.records if "smoothing" in r.message] == [
        "smoothing skipped: the replay was interrupted"
    ]
    rows = list(csv.reader((tmp_path / "e.csv").open()))  # whole, its rows as estimated
    assert rows[0] == list(COLUMNS)
    assert len(rows) - 1 == report.streams[0].stats.estimated > 0


def test_a_stop_while_smoothing_ends_the_replay_as_an_interrupted_one(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    release = threading.Event()

    async def stopped_while_smoothing() -> tuple[RunReport, float]:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        asked: list[float] = []

        def slow_smoothing(stream: Any) -> Any:
            smoothed = smoothing.smooth_stream(stream)
            asked.append(time.perf_counter())
            loop.call_soon_threadsafe(stop.set)  # Ctrl-C while a long log is smoothed
            release.wait(20)  # (its kernel goes on: one cannot cut it short)
            return smoothed

        monkeypatch.setattr(runners, "smooth_stream", slow_smoothing)
        report = await _smoothed_replay(flight, tmp_path / "e.csv", stop)
        return report, time.perf_counter() - asked[0]

    try:
        report, waited = asyncio.run(stopped_while_smoothing())
    finally:
        release.set()
    assert waited < 5.0  # at once, not once the smoother is done
    assert report.interrupted and not report.smoothed
    assert "  smoothing stopped: the replay was interrupted" in report.summary().splitlines()
    # the table whole, with the rows estimated online and no smoothed column
    rows = list(csv.reader((tmp_path / "e.csv").open()))
    assert rows[0] == list(COLUMNS)
    assert len(rows) - 1 == report.streams[0].stats.estimated > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.csv"]


def test_an_onboard_log_is_smoothed_from_the_samples_it_holds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its IMU as the filter took it (float32 HIGHRES_IMU, no aiding asked for): the
    smoother on those arrays, whatever path, gives the table's smoothed columns."""
    log = _synthetic_log(seconds=6.0)
    log.mag.clear()  # type: ignore[union-attr]
    path = tmp_path / "flight.bin"
    path.write_bytes(bytes([0xA3, 0x95, 0x80]) + bytes(100))
    monkeypatch.setattr(runners, "load", lambda _: log)
    config = ServiceConfig().replace(input={"acceleration_aiding": "off"})
    imu = log.imus[0]
    tables = []
    for fast in (True, False):
        table = tmp_path / f"{fast}.csv"
        report = asyncio.run(
            replay(path, config, Outputs(estimates=table), progress=False, fast=fast, smooth=True)
        )
        assert "(ArduPilot DataFlash log)" in report.summary()
        assert "smoothed vs truth (SIMSTATE) after 10 s" not in report.summary()  # 6 s only
        columns = _read(table)
        t = columns["time_s"]  # the filter's clock: the log's, from its first sample
        np.testing.assert_allclose(t - t[0], (imu.t_us - imu.t_us[0]) * 1e-6, atol=1e-9)
        expected = mavest.smooth(
            t,
            imu.gyro.astype(np.float32),
            imu.accel.astype(np.float32),
            config=config.estimator.replace(timeline_confirm=1),
        )
        np.testing.assert_array_equal(columns["smoothed_qx"], expected.q[:, 1])
        np.testing.assert_array_equal(
            columns["smoothed_bias_z_dps"], np.degrees(expected.bias[:, 2])
        )
        tables.append(table.read_bytes())
    assert tables[0] == tables[1]


def test_smooth_is_not_offered_live(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "udpin:127.0.0.1:0", "--smooth"]) == 2
    assert "unrecognized arguments: --smooth" in capsys.readouterr().err


# ------------------------------------------------------------------ the parts


def test_inputs_are_kept_compactly_a_chunk_at_a_time() -> None:
    """104 bytes a sample (a 1-hour 1 kHz stream: 0.37 GB), one sample at a time too."""
    inputs = RecordedInputs()
    n = 3 * CHUNK + 5
    rest = np.arange(n // 2, n) * 1e-3
    ones = np.ones((rest.shape[0], 3))
    tracemalloc.start()
    try:
        for k in range(n // 2):
            inputs.add(k * 1e-3, (0.1, 0.2, 0.3), (0.0, 0.0, -9.8), None, (1.0, 2.0, 3.0))
        inputs.add_many(rest, ones, ones, ones, ones, np.zeros(rest.shape[0], dtype=np.int64))
        held, _ = tracemalloc.get_traced_memory()
        t, gyro, accel, mag, linear_accel = inputs.take()
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held <= 13 * 8 * (n + CHUNK) + 100_000
    assert after <= 13 * 8 * n + 100_000  # the whole arrays only: the chunks went
    assert len(inputs) == 0 and t.shape == (n,)
    np.testing.assert_array_equal(t, np.arange(n) * 1e-3)
    assert np.isnan(mag[: n // 2]).all() and (mag[n // 2 :] == 1.0).all()
    assert (linear_accel[: n // 2] == (1.0, 2.0, 3.0)).all()
    assert (gyro[: n // 2] == (0.1, 0.2, 0.3)).all() and (accel[n // 2 :] == 1.0).all()


def test_smoothing_a_stream_holds_its_inputs_and_what_it_keeps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stream is smoothed a block at a time: it holds its inputs (104 bytes a sample,
    and 24 for the GPS acceleration moved to its interval), what it keeps of the result
    (q, the angles and their σ, the bias and its σ: 128) and the smoother's own (33),
    never the smoothed covariances (288 of the result's 401); and what it keeps is
    ``mavest.smooth``'s on those inputs, bit for bit."""
    log = tmp_path / "flight.tlog"
    write_flight_tlog(log, 40.0, 1000.0, AUTOPILOTS["ardupilot"], seed=2)
    peaks: dict[str, float] = {}
    given: list[tuple[Any, ...]] = []
    smooth_blocks, smooth_stream = smoothing.smooth_blocks, runners.smooth_stream

    def noted_blocks(*args: Any) -> Any:
        given.append(args)
        return smooth_blocks(*args)

    def measured_stream(stream: Any) -> Any:
        n = len(stream.inputs)
        tracemalloc.start()
        try:
            entry = tracemalloc.get_traced_memory()[0]
            out = smooth_stream(stream)
            peaks["stream"] = (tracemalloc.get_traced_memory()[1] - entry) / n
        finally:
            tracemalloc.stop()
        return out

    monkeypatch.setattr(smoothing, "smooth_blocks", noted_blocks)
    monkeypatch.setattr(runners, "smooth_stream", measured_stream)
    # (blocks and the comparisons' pieces small beside the flight: what each holds is
    # fixed, whatever the length)
    monkeypatch.setattr(smoother, "BLOCK", 512)
    monkeypatch.setattr(smoothing, "_SCORE_PIECE", 512)
    report = _replay(log)
    assert peaks["stream"] <= 104 + 24 + 128 + 33 + 40, peaks
    (stream,) = report.streams
    (args,) = given
    whole = mavest.smooth(*args)
    smoothed = report.smoothed[stream.key]
    np.testing.assert_array_equal(smoothed.q, whole.q)
    np.testing.assert_array_equal(smoothed.bias, whole.bias)


def test_samples_the_filter_skipped_are_not_inputs() -> None:
    inputs = RecordedInputs()
    t = np.arange(5.0)
    values = np.arange(15.0).reshape(5, 3)
    flags = np.array([0, mavest.StepFlags.SKIPPED, 0, 0, mavest.StepFlags.SKIPPED])
    inputs.add_many(t, values, values, values, values, flags)
    np.testing.assert_array_equal(inputs.take()[0], [0.0, 2.0, 3.0])


def _feed(comparison: EulerComparison, t: np.ndarray, euler: np.ndarray) -> None:
    """Estimates one at a time and in bulk, references among them both ways (the same
    every call), a restart (a reboot) half-way."""
    rng = np.random.default_rng(1)
    n = t.shape[0]
    k = 0
    while k < n:
        if k == n // 2:
            comparison.restart()
        if rng.random() < 0.5:
            end = min(k + int(rng.integers(1, 20)), n if k >= n // 2 else n // 2)
            kinds, times, angles = [], [], []
            for i in range(k, end):
                kinds.append(ESTIMATE)
                times.append(t[i])
                angles.append(euler[i])
                if rng.random() < 0.3:
                    kinds.append(REFERENCE)
                    times.append(t[i] + 0.03)
                    angles.append(rng.normal(0.0, 0.3, 3))
            comparison.add_many(np.array(kinds), np.array(times), np.array(angles))
            k = end
        else:
            comparison.add_estimate(t[k], tuple(euler[k]))
            if rng.random() < 0.5:
                comparison.add_reference(t[k] - 0.02, tuple(rng.normal(0.0, 0.3, 3)))
            k += 1


def test_a_comparison_made_again_is_the_same_over_pieces_and_restarts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Made again with the same estimates, the same result; with others, what a comparison
    fed those in their place gives: in any pieces, across a restart."""
    monkeypatch.setattr(smoothing, "_SCORE_PIECE", 7)
    rng = np.random.default_rng(2)
    t = np.concatenate([np.arange(200) * 0.1, 3.0 + np.arange(200) * 0.1])  # a reboot
    ours, others = rng.normal(0.0, 0.3, (2, 400, 3))
    recorded, plain, plain_others = (
        RecordedComparison(2.0),
        EulerComparison(2.0),
        EulerComparison(2.0),
    )
    _feed(recorded, t, ours)
    _feed(plain, t, ours)
    _feed(plain_others, t, others)
    assert recorded.result() == plain.result() and recorded.count > 100
    assert recorded.again(t, ours) == plain.result()
    assert recorded.again(t, others) == plain_others.result() != plain.result()
    assert recorded.again(t, ours) == plain.result()


def test_the_summary_says_when_smoothing_was_skipped() -> None:
    report = RunReport(runners.Pipeline(ServiceConfig()), 1.0)
    assert "smooth" not in report.summary()
    report.smoothing_skipped = "smoothing skipped: the replay was interrupted"
    assert "  smoothing skipped: the replay was interrupted" in report.summary().splitlines()


def test_the_smoother_takes_each_gps_acceleration_over_the_interval_it_measured() -> None:
    nan = math.nan
    held = np.array(
        [[nan] * 3, [1.0] * 3, [1.0] * 3, [2.0] * 3, [2.0] * 3, [3.0] * 3, [nan] * 3, [4.0] * 3]
    )
    moved = measured_interval_acceleration(held)
    # 1 → 2 and 2 → 3 move one interval earlier; 3 is followed by a gap, 4 by nothing
    expected = np.array(
        [[nan] * 3, [2.0] * 3, [2.0] * 3, [3.0] * 3, [3.0] * 3, [3.0] * 3, [nan] * 3, [4.0] * 3]
    )
    np.testing.assert_array_equal(moved, expected)
    assert measured_interval_acceleration(held[:1]).shape == (1, 3)
