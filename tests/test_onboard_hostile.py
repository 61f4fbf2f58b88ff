"""Damaged and odd onboard logs: what each costs is the part it damages, said in one line.

Each log is written here, small: a DataFlash log of a few FMT-described records, or a
ULog of a few topics, with one thing wrong (a column renamed or given as text, an
instance or vehicle type no MAVLink field can carry, a timestamp far off the timeline,
a clock that went back and stayed, two sensors claiming one instance).
"""

from __future__ import annotations

import asyncio
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from dataflash_writer import DataflashWriter

from mavest.cli import EXIT_USAGE, main
from mavest.mavlink.messages import MAVLink
from mavest.onboard import OnboardLog, OnboardLogError, load
from mavest.onboard.convert import RECORD_EPOCH_US, to_tlog_bytes
from mavest.paths import OutputPathError, check_outputs
from mavest.service.config import ServiceConfig
from mavest.service.runners import Outputs, replay

# --------------------------------------------------------------------------
# Writing DataFlash logs
# --------------------------------------------------------------------------

IMU_FORMAT, IMU_COLUMNS = "QffffffI", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG"
START_US, STEP_US = 10_000_000, 2500  # 400 Hz


def imu_log(times: list[int] | None = None, samples: int = 1000) -> DataflashWriter:
    """IMU samples at rest at ``times`` (µs), by default ``samples`` of them at 400 Hz."""
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    for t in times if times is not None else [START_US + STEP_US * k for k in range(samples)]:
        log.record("IMU", t, 0.001, -0.002, 0.0005, 0.1, -0.05, -9.80665, 0)
    return log


def with_others(
    log: DataflashWriter, defined: dict[str, tuple[str, str]], samples: int = 100
) -> None:
    """MAG, ATT, GPS and PARM records beside the IMU's, in the formats ``defined`` gives
    (by name: format, columns), else the usual ones."""
    formats = {
        "MAG": ("Qhhh", "TimeUS,MagX,MagY,MagZ"),
        "ATT": ("Qccc", "TimeUS,Roll,Pitch,Yaw"),
        "GPS": ("QBfff", "TimeUS,Status,Spd,GCrs,VZ"),
        "PARM": ("QNf", "TimeUS,Name,Value"),
    } | defined
    for kind, (name, (fmt, columns)) in enumerate(formats.items(), start=201):
        log.define(kind, name, fmt, columns)
    rows = {"MAG": (200, -50, 400), "ATT": (150, -250, 900), "GPS": (3, 10.0, 90.0, -1.5)}
    values = {}
    for name, row in rows.items():
        # a column given as text holds text; one left out, nothing
        kinds = formats[name][0][1:]
        values[name] = tuple("ab" if c in "nNZ" else v for c, v in zip(kinds, row, strict=False))
    log.record("PARM", 0, "COMPASS_DEC", "ab" if formats["PARM"][0][-1] in "nNZ" else 0.2)
    for k in range(samples):
        t = START_US + 40_000 * k
        for name, row in values.items():
            log.record(name, t, *row)


def notes_of(log: OnboardLog) -> str:
    return "; ".join(log.notes)


# --------------------------------------------------------------------------
# A column missing or not a number: that message type left out
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("defined", "left_out", "said"),
    [
        ({"MAG": ("Qhhh", "TimeUS,MagX,LagY,MagZ")}, "mag", "MAG has no column MagY: left out"),
        ({"ATT": ("Qnhh", "TimeUS,Roll,Pitch,Yaw")}, "attitude", "ATT.Roll is not a number"),
        ({"GPS": ("Qfff", "TimeUS,Spd,GCrs,VZ")}, "gps_fix", "GPS has no column Status"),
        ({"GPS": ("QBfn", "TimeUS,Status,Spd,GCrs")}, "gps_velocity", "GPS speed left out"),
        ({"PARM": ("QNn", "TimeUS,Name,Value")}, "declination", "PARM.Value is not a number"),
    ],
    ids=["renamed-mag", "text-att", "gps-without-status", "gps-without-vz", "text-parm"],
)
def test_a_column_missing_or_not_a_number_leaves_its_message_type_out(
    tmp_path: Path, defined: dict[str, tuple[str, str]], left_out: str, said: str
) -> None:
    log = imu_log()
    with_others(log, defined)
    loaded = load(log.save(tmp_path / "odd.bin"))
    intact = imu_log()
    with_others(intact, {})
    whole = load(intact.save(tmp_path / "intact.bin"))
    assert len(loaded.imus[0].t_us) == len(whole.imus[0].t_us) == 1000
    assert said in notes_of(loaded)
    assert getattr(loaded, left_out) in (None, {})
    for kept in sorted({"mag", "attitude", "gps_fix", "declination"} - {left_out}):
        assert getattr(loaded, kept) not in (None, {}), kept
    assert len(to_tlog_bytes(loaded)) > 0


def test_an_imu_redefined_without_its_columns_is_one_line_naming_the_file(
    tmp_path: Path,
) -> None:
    log = imu_log(samples=100)
    log.define(200, "IMU", "Qfff", "TimeUS,X,Y,Z")
    for k in range(10):
        log.record("IMU", 20_000_000 + STEP_US * k, 1.0, 2.0, 3.0)
    with pytest.raises(OnboardLogError) as raised:
        load(log.save(tmp_path / "redefined.bin"))
    message = str(raised.value)
    assert "\n" not in message
    assert message.startswith("redefined.bin: no IMU samples") and "no column GyrX" in message


def test_an_imu_redefined_longer_part_way_reads_the_records_of_its_last_definition(
    tmp_path: Path,
) -> None:
    # Records are read by the FMT in force where they are: the earlier ones, shorter,
    # were read with the last (longer) layout, past the file's end (an IndexError) or
    # as each other's bytes; they are left out now, counted as damage and said.
    log = imu_log(samples=100)
    log.define(200, "IMU", IMU_FORMAT + "f", IMU_COLUMNS + ",T")
    for k in range(500):
        log.record("IMU", 20_000_000 + STEP_US * k, 0.001, -0.002, 0.0005, 0.1, -0.05,
                   -9.80665, 0, 25.0)  # fmt: skip
    loaded = load(log.save(tmp_path / "redefined.bin"))
    assert len(loaded.imus[0].t_us) == 500
    assert loaded.imus[0].t_us[0] == 20_000_000
    np.testing.assert_allclose(loaded.imus[0].accel[:, 2], -9.80665, rtol=1e-6)
    assert loaded.damage.bad_records == 100
    assert "IMU is defined more than once: 100 of its records" in notes_of(loaded)
    # cut right after the new definition: no record of it, none read with it
    cut = imu_log(samples=100)
    cut.define(200, "IMU", IMU_FORMAT + "f", IMU_COLUMNS + ",T")
    with pytest.raises(OnboardLogError, match=r"^cut\.bin: no IMU samples"):
        load(cut.save(tmp_path / "cut.bin"))


def test_a_format_naming_one_column_twice_leaves_its_type_out(tmp_path: Path) -> None:
    # (one flipped bit in a column's name does it: NumPy refused the layout, a traceback)
    log = imu_log()
    with_others(log, {"MAG": ("Qhhh", "TimeUS,MagX,MagX,MagZ")})
    loaded = load(log.save(tmp_path / "twice.bin"))
    assert len(loaded.imus[0].t_us) == 1000
    assert loaded.mag in (None, {})


def test_an_imu_type_without_a_time_column_is_left_out_and_the_others_read(
    tmp_path: Path,
) -> None:
    log = DataflashWriter()
    log.define(200, "IMU", "ffffffI", "GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG")
    log.define(201, "IMU2", IMU_FORMAT, IMU_COLUMNS)
    for k in range(1000):
        log.record("IMU", 0.0, 0.0, 0.0, 0.0, 0.0, -9.8, 0)
        log.record("IMU2", START_US + STEP_US * k, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8, 0)
    loaded = load(log.save(tmp_path / "untimed.bin"))
    assert [(imu.instance, len(imu.t_us)) for imu in loaded.imus] == [(1, 1000)]
    assert "IMU has neither TimeUS nor TimeMS: left out" in notes_of(loaded)


# --------------------------------------------------------------------------
# Instances and vehicle types no MAVLink field can carry; two sensors on one instance
# --------------------------------------------------------------------------

INSTANCED = ("QiffffffI", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG")


@pytest.mark.parametrize("wrong", [1000, -1])
def test_an_impossible_imu_instance_is_left_out_with_one_line(tmp_path: Path, wrong: int) -> None:
    log = DataflashWriter()
    log.define(200, "IMU", *INSTANCED)
    for k in range(400):
        for instance in (0, wrong):
            log.record("IMU", START_US + STEP_US * k, instance, 0, 0, 0, 0, 0, -9.8, 0)
    loaded = load(log.save(tmp_path / "instances.bin"))
    assert [(imu.instance, len(imu.t_us)) for imu in loaded.imus] == [(0, 400)]
    assert "IMU: 400 records with an instance I outside 0…255 left out" in notes_of(loaded)
    to_tlog_bytes(loaded)

    only = DataflashWriter()
    only.define(200, "IMU", *INSTANCED)
    for k in range(10):
        only.record("IMU", START_US + STEP_US * k, wrong, 0, 0, 0, 0, 0, -9.8, 0)
    with pytest.raises(OnboardLogError, match=r"^only\.bin: no IMU samples .*outside 0…255"):
        load(only.save(tmp_path / "only.bin"))


def test_two_sensors_on_one_instance_are_not_merged(tmp_path: Path) -> None:
    log = DataflashWriter()
    log.define(200, "IMU", "QBffffffI", INSTANCED[1])
    log.define(201, "IMU2", IMU_FORMAT, IMU_COLUMNS)
    for k in range(500):
        t = START_US + STEP_US * k
        log.record("IMU", t, 0, 0, 0, 0, 0, 0, -9.8, 0)
        log.record("IMU", t + 10, 1, 0, 0, 0, 0, 0, -9.8, 0)
        log.record("IMU2", t + 20, 0.5, 0, 0, 0, 0, -9.8, 0)  # spinning: another sensor
    loaded = load(log.save(tmp_path / "clash.bin"))
    assert [imu.instance for imu in loaded.imus] == [0, 1]
    second = loaded.imus[1]
    np.testing.assert_array_equal(second.t_us, START_US + STEP_US * np.arange(500) + 10)
    assert np.all(second.gyro == 0.0)
    assert "IMU2 left out as instance 1" in notes_of(loaded)


# --------------------------------------------------------------------------
# Timestamps far off the timeline, and a clock that goes back and stays
# --------------------------------------------------------------------------


def _times(samples: int = 3000) -> list[int]:
    return [START_US + STEP_US * k for k in range(samples)]


@pytest.mark.parametrize(
    "where", ["first", "last", "middle-far", "middle-30s", "first-top-bit"], ids=str
)
def test_a_lone_wild_time_costs_its_sample_and_no_more(tmp_path: Path, where: str) -> None:
    times = _times()
    wild = {
        "first": (0, times[0] + 2**40),
        "last": (-1, times[-1] + 2**40),
        "middle-far": (1500, times[1500] + 2**40),
        "middle-30s": (1500, times[1500] + 30_000_000),  # within a gap a stream may have
        "first-top-bit": (0, times[0] | 2**63),  # a uint64 that would wrap negative
    }[where]
    times[wild[0]] = wild[1]
    path = imu_log(times).save(tmp_path / "wild.bin")
    loaded = load(path)
    imu = loaded.imus[0]
    expected = np.delete(np.array(_times()), wild[0])
    np.testing.assert_array_equal(imu.t_us, expected)
    assert loaded.damage.dropped_samples == 1
    assert "1 samples whose time was far off the timeline" in notes_of(loaded)
    # the tlog: one HEARTBEAT a second of the samples' span, not of the wild time's
    tlog = to_tlog_bytes(loaded)
    intact = to_tlog_bytes(load(imu_log(_times()).save(tmp_path / "intact.bin")))
    assert len(tlog) <= len(intact)


def test_a_log_of_every_record_twice_keeps_each_once(tmp_path: Path) -> None:
    # (a repeated time is a sample to drop, not a run of far-off times to confirm)
    times = [t for t in _times(1000) for _ in range(2)]
    loaded = load(imu_log(times).save(tmp_path / "twice.bin"))
    np.testing.assert_array_equal(loaded.imus[0].t_us, _times(1000))
    assert "dropped 1000 samples whose time did not increase" in notes_of(loaded)


def test_float_times_that_are_not_numbers_are_skipped(tmp_path: Path) -> None:
    log = DataflashWriter()
    log.define(200, "IMU", "fffffff", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    for k in range(1000):
        t = math.nan if k % 100 == 0 else float(START_US + STEP_US * k)  # the first too
        log.record("IMU", t, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)
    loaded = load(log.save(tmp_path / "float.bin"))
    assert len(loaded.imus[0].t_us) == 990
    assert len(to_tlog_bytes(loaded)) < 200_000


def test_heartbeats_stop_across_a_confirmed_jump_longer_than_any_gap(tmp_path: Path) -> None:
    # a jump of 2**40 µs (12.7 days) that the samples after it confirm
    times = _times(1000) + [START_US + 2**40 + STEP_US * k for k in range(1000)]
    loaded = load(imu_log(times).save(tmp_path / "jump.bin"))
    assert len(loaded.imus[0].t_us) == 2000
    heartbeats = [m for m in _messages(to_tlog_bytes(loaded)) if m[1].get_type() == "HEARTBEAT"]
    # a second's worth for each second of each stretch (not 12.7 days of them)
    assert len(heartbeats) <= 2 * (math.ceil(1000 * STEP_US / 1e6) + 1)


def test_a_jump_of_an_onboard_logs_clock_is_said_in_the_logs_terms(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # (it named "tlog", a byte of the conversion in memory and dates of its year 2000)
    times = _times(1000) + [START_US + 2**40 + STEP_US * k for k in range(1000)]
    path = imu_log(times).save(tmp_path / "jump.bin")
    with caplog.at_level("WARNING", logger="mavest"):
        asyncio.run(replay(path, ServiceConfig()))
    said = [r.getMessage() for r in caplog.records if "clock jumped" in r.getMessage()]
    last = (START_US + 999 * STEP_US) * 1e-6
    assert len(said) == 1 and said[0].startswith(  # (a count of held lines may follow)
        f"jump.bin: the log's clock jumped forward by 12.7 days at {last:.3f} s of its time; "
        "read on at the new time"
    )


def test_an_accelerometer_that_never_reads_g_is_said_and_nothing_is_scored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # (a log's accelerometer a millionth of m/s²: no line, exit 0, and the level attitude
    # the filter starts from scored against the autopilot's, 21° "RMS")
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    for t in _times(4000):
        log.record("IMU", t, 0.001, -0.002, 0.0005, 0.1e-6, -0.05e-6, -9.8e-6, 0)
    with_others(log, {}, samples=250)
    path = log.save(tmp_path / "tiny.bin")
    for fast in (True, False):  # in bulk, and one record at a time
        caplog.clear()
        with caplog.at_level("WARNING", logger="mavest"):
            report = asyncio.run(replay(path, ServiceConfig(), fast=fast))
        said = [r.getMessage() for r in caplog.records if "no attitude" in r.getMessage()]
        assert len(said) == 1 and "of its 4000 samples: the accelerometer never read g" in said[0]
        (stream,) = report.streams
        assert stream.vs_autopilot.count == 0 and stream.vs_autopilot.references > 0
        assert "not scored" in report.summary()


def test_a_smoothed_replay_scores_alike_an_accelerometer_that_starts_late(
    tmp_path: Path,
) -> None:
    # estimates before the filter's first attitude, NaN in the comparisons, are the
    # same count as the smoothed ones compared again (a count that differed: a crash)
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    for k, t in enumerate(_times(8000)):  # 20 s: 15 s scored after the settling
        scale = 1e-6 if k < 1000 else 1.0
        log.record("IMU", t, 0.001, -0.002, 0.0005, 0.1 * scale, -0.05 * scale,
                   -9.80665 * scale, 0)  # fmt: skip
    with_others(log, {}, samples=500)
    path = log.save(tmp_path / "late.bin")
    for fast in (True, False):
        report = asyncio.run(replay(path, ServiceConfig(), fast=fast, smooth=True))
        (stream,) = report.streams
        assert stream.stats.not_started == 1000
        online = stream.vs_autopilot.result()
        smoothed = report.smoothed[stream.key].vs_autopilot
        assert online.count > 0 and smoothed is not None and smoothed.count > 0


def test_a_stream_given_up_for_a_lower_instance_stays_in_the_summary(tmp_path: Path) -> None:
    # IMU2 (instance 1) from the start, IMU (instance 0) from the middle on: the replay
    # follows instance 0 once it comes; what it estimated from instance 1 before is in
    # the outputs, and was missing from the summary, the counts and the smoothing
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    log.define(199, "IMU2", IMU_FORMAT, IMU_COLUMNS)
    for k, t in enumerate(_times(4000)):
        log.record("IMU2", t, 0.001, -0.002, 0.0005, 0.1, -0.05, -9.80665, 0)
        if k >= 2000:
            log.record("IMU", t + 1, 0.001, -0.002, 0.0005, 0.1, -0.05, -9.80665, 0)
    table = tmp_path / "estimates.csv"
    report = asyncio.run(
        replay(log.save(tmp_path / "two.bin"), ServiceConfig(), Outputs(estimates=table),
               smooth=True)
    )  # fmt: skip
    first, then = report.streams
    assert (first.key.instance, then.key.instance) == (1, 0)
    # (instance 1 up to its sample at the first of instance 0's)
    assert (first.stats.estimated, then.stats.estimated) == (2001, 2000)
    assert len(table.read_text().splitlines()) == 1 + 4001
    assert set(report.smoothed) == {first.key, then.key}
    summary = report.summary()
    assert "4001 IMU samples estimated" in summary
    assert f"{first.key} → ATTITUDE until " in summary and f", then {then.key}:" in summary


def _messages(tlog: bytes) -> list[tuple[int, object]]:
    """(stamp µs, message) of each record of a tlog written by to_tlog_bytes."""
    parser = MAVLink(None)
    found, p = [], 0
    while p < len(tlog):
        stamp = int.from_bytes(tlog[p : p + 8], "big")
        length = 12 + tlog[p + 9] + (13 if tlog[p + 10] & 1 else 0)
        message = parser.decode(bytearray(tlog[p + 8 : p + 8 + length]))
        found.append((stamp, message))
        p += 8 + length
    return found


def test_a_clock_that_goes_back_and_stays_keeps_every_sample(tmp_path: Path) -> None:
    later = [7_200_000_000 + STEP_US * k for k in range(2500)]
    earlier = [START_US + STEP_US * k for k in range(1500)]
    loaded = load(imu_log(later + earlier).save(tmp_path / "back.bin"))
    imu = loaded.imus[0]
    np.testing.assert_array_equal(imu.t_us, later + earlier)
    np.testing.assert_array_equal(imu.restarts, [2500])
    assert loaded.damage.dropped_samples == 0
    assert "the clock went back and stayed" in notes_of(loaded)

    tlog = to_tlog_bytes(loaded)
    assert tlog == to_tlog_bytes(load(tmp_path / "back.bin"))  # the same bytes every time
    records = _messages(tlog)
    stamps = [stamp for stamp, _ in records]
    assert stamps == sorted(stamps)  # recorded on, as a ground station records a restart
    sent = [m.time_usec for _, m in records if m.get_type() == "HIGHRES_IMU"]
    assert sent == later + earlier  # each sample's own time, as logged
    restart = next(s for s, m in records if getattr(m, "time_usec", None) == earlier[0])
    assert restart - RECORD_EPOCH_US == later[-1] + 1_000_000

    report = asyncio.run(replay(tmp_path / "back.bin", ServiceConfig()))
    (stream,) = report.streams
    assert stream.stats.estimated == 4000 and stream.stats.reboots == 1
    # how long it was estimated: both timelines, not the last time less the first
    assert stream.stats.span == pytest.approx((2499 + 1499) * STEP_US * 1e-6)


# --------------------------------------------------------------------------
# ULog
# --------------------------------------------------------------------------

SENSOR_COMBINED = (
    "uint64_t timestamp;float[3] gyro_rad;int32_t accelerometer_timestamp_relative;"
    "float[3] accelerometer_m_s2"
)
GPS = "uint64_t timestamp;uint8_t fix_type;float vel_n_m_s;float vel_e_m_s;float vel_d_m_s"
ATTITUDE = "uint64_t timestamp;float[4] q"


def _ulog_message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def write_ulog(
    path: Path,
    times: list[int] | None = None,
    formats: dict[str, str] | None = None,
    mav_type: bytes = b"\x10int32_t MAV_TYPE" + struct.pack("<i", 1),
) -> Path:
    """A ULog of sensor_combined at ``times`` (400 Hz from START_US by default) and a
    GPS and attitude at 10 Hz, in the ``formats`` given (by topic) or the usual ones."""
    formats = {
        "sensor_combined": SENSOR_COMBINED,
        "vehicle_gps_position": GPS,
        "vehicle_attitude": ATTITUDE,
    } | (formats or {})
    times = times if times is not None else _times(1000)
    out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0))
    out += _ulog_message("B", bytes(40))
    for name, fields in formats.items():
        out += _ulog_message("F", f"{name}:{fields}".encode())
    out += _ulog_message("P", mav_type)
    for number, name in enumerate(formats):
        out += _ulog_message("A", struct.pack("<BH", 0, number) + name.encode())
    for k, t in enumerate(times):
        sample = struct.pack("<Q3fi3f", t, 0.001, -0.002, 0.0005, 0, 0.1, -0.05, -9.8)
        out += _ulog_message("D", struct.pack("<H", 0) + sample)
        if k % 40 == 0:
            fix = struct.pack("<QB3f", t, 3, 1.0, 2.0, -0.5)
            out += _ulog_message("D", struct.pack("<H", 1) + fix)
            out += _ulog_message("D", struct.pack("<H", 2) + struct.pack("<Q4f", t, 1, 0, 0, 0))
    path.write_bytes(bytes(out))
    return path


@pytest.mark.parametrize(
    ("topic", "fields", "left_out", "said"),
    [
        ("vehicle_gps_position", GPS.replace("vel_n_m_s", "vel_x_m_s"), "gps_velocity",
         "vehicle_gps_position has no field vel_n_m_s: GPS velocity left out"),
        ("vehicle_gps_position", GPS.replace("fix_type", "fix_kind"), "gps_fix",
         "vehicle_gps_position has no field fix_type: left out"),
        ("vehicle_attitude", ATTITUDE.replace(" q", " r"), "attitude",
         "vehicle_attitude has no field q[0]: left out"),
    ],
    ids=["gps-velocity", "gps-fix", "attitude"],
)  # fmt: skip
def test_a_ulog_topic_without_a_field_is_left_out(
    tmp_path: Path, topic: str, fields: str, left_out: str, said: str
) -> None:
    whole = load(write_ulog(tmp_path / "whole.ulg"))
    assert whole.gps_velocity is not None and whole.attitude is not None
    loaded = load(write_ulog(tmp_path / "odd.ulg", formats={topic: fields}))
    assert len(loaded.imus[0].t_us) == 1000
    assert getattr(loaded, left_out) is None
    assert said in notes_of(loaded)
    assert len(to_tlog_bytes(loaded)) > 0


def test_a_ulog_imu_without_its_fields_is_one_line_naming_the_file(tmp_path: Path) -> None:
    fields = SENSOR_COMBINED.replace("accelerometer_m_s2", "accel_m_s2")
    with pytest.raises(OnboardLogError) as raised:
        load(write_ulog(tmp_path / "noaccel.ulg", formats={"sensor_combined": fields}))
    message = str(raised.value)
    assert "\n" not in message and message.startswith("noaccel.ulg: no IMU samples")
    assert "accelerometer_m_s2[0]" in message


def test_a_ulog_of_no_usable_imu_sample_is_one_line_as_a_dataflash_log_is(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # times three centuries on: every sample off any timeline (it was an empty stream,
    # exit 1 and "no IMU stream found (RAW_IMU, …)" on standard output, nothing said)
    years = 300 * 365 * 86400 * 10**6
    path = write_ulog(tmp_path / "far.ulg", [years + t for t in _times(1000)])
    with pytest.raises(OnboardLogError, match=r"^far\.ulg: no IMU samples in this ULog"):
        load(path)
    table = tmp_path / "estimates.csv"
    assert main(["replay", str(path), "--estimates", str(table), "-q"]) == EXIT_USAGE
    assert capsys.readouterr().err.strip().endswith("no usable sample)")
    assert not table.exists()


@pytest.mark.parametrize(
    "parameter",
    [
        b"\x10int32_t MAV_TYPE" + struct.pack("<i", 1000),
        b"\x0efloat MAV_TYPE" + struct.pack("<f", math.nan),
    ],
    ids=["1000", "nan"],
)
def test_a_mav_type_no_heartbeat_can_carry_is_taken_as_generic(
    tmp_path: Path, parameter: bytes
) -> None:
    loaded = load(write_ulog(tmp_path / "type.ulg", mav_type=parameter))
    assert loaded.vehicle_type == 0
    assert "is no vehicle type: taken as generic" in notes_of(loaded)
    beats = [m for _, m in _messages(to_tlog_bytes(loaded)) if m.get_type() == "HEARTBEAT"]
    assert beats and all(m.type == 0 for m in beats)


def test_a_ulog_clock_that_goes_back_and_stays_keeps_every_sample(tmp_path: Path) -> None:
    times = [7_200_000_000 + STEP_US * k for k in range(600)] + _times(400)
    loaded = load(write_ulog(tmp_path / "back.ulg", times))
    np.testing.assert_array_equal(loaded.imus[0].t_us, times)
    np.testing.assert_array_equal(loaded.imus[0].restarts, [600])
    assert loaded.damage.dropped_samples == 0


def test_a_wild_last_ulog_time_costs_its_sample(tmp_path: Path) -> None:
    times = _times(1000)
    times[-1] += 2**40
    loaded = load(write_ulog(tmp_path / "wild.ulg", times))
    np.testing.assert_array_equal(loaded.imus[0].t_us, times[:-1])


# --------------------------------------------------------------------------
# What a replay says
# --------------------------------------------------------------------------


def test_an_instance_the_log_lacks_is_said_with_the_ones_it_has(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = imu_log().save(tmp_path / "one.bin")
    config = ServiceConfig().replace(input={"imu_instance": 7})
    with caplog.at_level("WARNING", logger="mavest"):
        report = asyncio.run(replay(path, config))
    assert not report.streams
    said = [r.getMessage() for r in caplog.records if "--instance" in r.getMessage()]
    assert said == ["one.bin: --instance 7 selects no IMU: the log's are instance 0"]


def test_a_dangling_link_as_output_names_the_folder_it_leads_into(tmp_path: Path) -> None:
    link = tmp_path / "est.csv"
    link.symlink_to(tmp_path / "nowhere" / "x.csv")
    with pytest.raises(OutputPathError) as raised:
        check_outputs({}, {"--estimates": link})
    assert str(raised.value).endswith(f"no folder {tmp_path / 'nowhere'}")


def test_an_accelerometer_seldom_taken_as_gravity_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A board at rest whose gyro reads 24 °/s on two axes (uncalibrated, beyond the
    filter's prior): the attitude spins, the low-passed specific force with it, and the
    accelerometer is kept out of nearly every update. The σ says so (it grows to
    hundreds of degrees), but the summary said "filter health: no resets" and nothing
    else; it now says how often, and a warning (a fleet's row keeps it) says why."""
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    for k in range(50 * 120):  # 120 s at 50 Hz
        log.record("IMU", START_US + 20_000 * k, -0.42, -0.42, 0.0, 0.1, -0.05, -9.80665, 0)
    path = log.save(tmp_path / "offset.bin")
    report = asyncio.run(replay(path, ServiceConfig(), progress=False))
    (stream,) = report.streams
    assert stream.stats.accel_far_from_g > 0.5 * stream.stats.updates > 0
    assert "of the updates: tilt seldom observed" in caplog.text
    assert re.search(r"accelerometer too far from g at \d+ % of the \d+ gravity updates",
                     report.summary())  # fmt: skip
    # a board at rest with its gyro's offset within the prior: nothing to say
    caplog.clear()
    quiet = asyncio.run(replay(imu_log().save(tmp_path / "rest.bin"), ServiceConfig()))
    assert quiet.streams[0].stats.accel_far_from_g == 0
    assert "too far from g" not in caplog.text + quiet.summary()


def test_a_log_stamped_with_unix_time_is_scored_against_its_autopilot(tmp_path: Path) -> None:
    """A PX4 simulator stamps its log with Unix time (1.7e15 µs): ATTITUDE's 32-bit
    time_boot_ms wrapped, so the autopilot's attitude never met an IMU sample and the
    replay said nothing of it. Every message's time now counts from the log's first."""
    epoch_us = 1_710_773_350_354_000
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    log.define(201, "ATT", "Qccc", "TimeUS,Roll,Pitch,Yaw")
    for k in range(400 * 20):  # 20 s at rest at 400 Hz, the autopilot's attitude at 10 Hz
        t = epoch_us + STEP_US * k
        log.record("IMU", t, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665, 0)
        if k % 40 == 0:
            log.record("ATT", t, 0, 0, 9000)
    path = log.save(tmp_path / "unix_time.bin")
    config = ServiceConfig().replace(input={"settle_time": 1.0})
    report = asyncio.run(replay(path, config, progress=False))
    (stream,) = report.streams
    scored = stream.vs_autopilot.result()
    assert scored.count > 150 and scored.inclination_rms < 0.5, scored


def test_a_dataflash_log_after_a_loggers_own_header_is_read(tmp_path: Path) -> None:
    """A board's logger may write 64 bytes of its own before the DataFlash log (seen on
    an ArduCopter 4.6.3 log): refused before as "neither an ArduPilot DataFlash log nor
    a PX4 ULog"; read now, those bytes counted as damage."""
    path = tmp_path / "00000001.BIN"
    path.write_bytes(bytes(range(64)) + bytes(imu_log().out))
    report = asyncio.run(replay(path, ServiceConfig(), progress=False))
    assert report.streams[0].stats.estimated == 1000
    assert report.skipped_bytes == 64
    # noise alone is still refused, in its own words
    (tmp_path / "noise.bin").write_bytes(bytes(range(256)) * 64)
    with pytest.raises(OnboardLogError, match="neither an ArduPilot DataFlash log"):
        asyncio.run(replay(tmp_path / "noise.bin", ServiceConfig(), progress=False))


def test_a_log_too_short_to_score_says_so(tmp_path: Path) -> None:
    """A log shorter than the settle time (10 s) scored nothing and said nothing of the
    autopilot's attitudes it holds: the summary now says none was scored, and why."""
    log = DataflashWriter()
    log.define(200, "IMU", IMU_FORMAT, IMU_COLUMNS)
    log.define(201, "ATT", "Qccc", "TimeUS,Roll,Pitch,Yaw")
    for k in range(400 * 5):  # 5 s
        log.record("IMU", START_US + STEP_US * k, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665, 0)
        if k % 40 == 0:
            log.record("ATT", START_US + STEP_US * k, 0, 0, 9000)
    path = log.save(tmp_path / "short.bin")
    summary = asyncio.run(replay(path, ServiceConfig(), progress=False)).summary()
    assert "vs autopilot ATTITUDE: not scored: none of its 50 attitudes came 10 s" in summary
    scored = ServiceConfig().replace(input={"settle_time": 1.0})
    summary = asyncio.run(replay(path, scored, progress=False)).summary()
    assert "vs autopilot ATTITUDE after 1 s:" in summary and "not scored" not in summary


def test_an_instance_of_one_corrupt_record_is_no_stream(tmp_path: Path) -> None:
    """One damaged record can name an IMU instance the log never had (44, at a wild time):
    it made a stream of no sample, listed as "IMU instance 44 (IMU): 0 samples"."""
    log = DataflashWriter()
    log.define(200, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    for k in range(1000):
        log.record("IMU", START_US + STEP_US * k, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
        if k == 500:
            log.record("IMU", 2**62, 44, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
    loaded = load(log.save(tmp_path / "one_bad.bin"))
    assert [imu.instance for imu in loaded.imus] == [0]
    assert "IMU instance 44 (IMU): no usable sample, left out" in loaded.notes
