"""The bulk onboard-log readers (mavest.onboard): DataFlash against pymavlink's DFReader,
ULog against pyulog, and damaged files.

Logs written here (a few FMT-described records) cover the DataFlash decoder without any
data; the comparisons on real logs use the shared files and skip, naming MAVEST_DATA,
when they are absent.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from dataflash_writer import HEADER, DataflashWriter
from scipy.spatial.transform import Rotation

from mavest.datasets import DATA_ENV_VAR, data_root
from mavest.onboard import OnboardLog, OnboardLogError, detect, load
from mavest.onboard.dataflash import read_records

# --------------------------------------------------------------------------
# Writing DataFlash logs
# --------------------------------------------------------------------------


def imu_log(samples: int = 50, with_units: bool = False) -> DataflashWriter:
    """A newer-firmware log: IMU with an instance column, MAG, GPS, ATT, PARM, MSG."""
    log = DataflashWriter()
    log.define(129, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    log.define(130, "MAG", "Qhhh", "TimeUS,MagX,MagY,MagZ")
    log.define(131, "GPS", "QBBIHfff", "TimeUS,I,Status,GMS,GWk,Spd,GCrs,VZ")
    log.define(132, "ATT", "QccC", "TimeUS,Roll,Pitch,Yaw")  # older centidegree layout
    log.define(133, "PARM", "QNf", "TimeUS,Name,Value")
    log.define(134, "MSG", "QZ", "TimeUS,Message")
    log.define(135, "ARSP", "Qf", "TimeUS,Airspeed")
    if with_units:
        log.define(136, "UNIT", "QbZ", "TimeUS,Id,Label")
        log.define(137, "MULT", "Qbd", "TimeUS,Id,Mult")
        log.define(138, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds")
        for unit, label in (("s", "s"), ("E", "rad/s"), ("o", "m/s/s"), ("G", "Gauss"),
                            ("n", "m/s"), ("d", "deg"), ("h", "degheading")):  # fmt: skip
            log.record("UNIT", 0, ord(unit), label)
        for mult, value in (("F", 1e-6), ("0", 1.0), ("C", 1e-3), ("B", 1e-2)):
            log.record("MULT", 0, ord(mult), value)
        log.record("FMTU", 0, 129, "s#EEEooo", "F-000000")
        log.record("FMTU", 0, 130, "sGGG", "FCCC")
        log.record("FMTU", 0, 131, "s#---nhn", "F----000")
        log.record("FMTU", 0, 132, "sddh", "FBBB")
    log.record("MSG", 0, "ArduPlane V4.5.1 (abcdef12)")
    log.record("PARM", 0, "AHRS_TRIM_X", 0.02)
    log.record("PARM", 0, "AHRS_TRIM_Y", -0.01)
    log.record("PARM", 0, "COMPASS_DEC", 0.2)
    for k in range(samples):
        t_us = 1_000_000 + 2500 * k
        for instance in (0, 1):
            log.record("IMU", t_us + instance, instance, 0.01 * k, -0.02, 0.5 + instance,
                       0.1, -0.2, -9.8)  # fmt: skip
        if k % 5 == 0:
            log.record("MAG", t_us, 200, -50, 400)
            log.record("GPS", t_us, 0, 3 if k >= 10 else 1, 300_000 + k, 2300, 10.0, 90.0, -1.5)
            log.record("ATT", t_us, 150, -250, 35900)
            log.record("ARSP", t_us, 12.5)
    return log


def test_synthetic_log_decodes_to_si_units(tmp_path: Path) -> None:
    path = imu_log().save(tmp_path / "plane.bin")
    assert detect(path) == "dataflash"
    log = load(path)
    assert (log.format, log.autopilot, log.vehicle_type) == ("dataflash", "ArduPilot", 1)
    assert [imu.instance for imu in log.imus] == [0, 1]
    imu = log.imus[1]
    np.testing.assert_array_equal(imu.t_us, 1_000_001 + 2500 * np.arange(50))
    np.testing.assert_array_equal(imu.gyro[:, 0], np.float32(0.01 * np.arange(50)))
    np.testing.assert_array_equal(imu.gyro[0, 1:], [np.float32(-0.02), 1.5])
    np.testing.assert_array_equal(imu.accel[0], np.float32([0.1, -0.2, -9.8]))
    assert log.mag[0].values[0] == pytest.approx([20.0, -5.0, 40.0])  # milligauss → µT
    # GPS: the 3-D fixes only, ground speed 10 m/s on course 90° (east), climbing 1.5 m/s
    assert len(log.gps_velocity.t_us) == 8
    assert log.gps_velocity.values[0] == pytest.approx([0.0, 10.0, -1.5], abs=1e-6)
    np.testing.assert_array_equal(log.gps_fix.values[:, 0], [1, 1, 3, 3, 3, 3, 3, 3, 3, 3])
    # ATT 1.5°, -2.5°, 359° with the trim (rad) added back to roll and pitch; yaw wrapped
    trim = [float(np.float32(0.02)), float(np.float32(-0.01))]  # stored as float32
    expected = [math.radians(1.5) + trim[0], math.radians(-2.5) + trim[1]]
    assert log.attitude.values[0, :2] == pytest.approx(expected, abs=1e-12)
    assert log.attitude.values[0, 2] == pytest.approx(math.radians(-1.0))
    assert log.airspeed.values[:, 0] == pytest.approx(12.5)
    assert log.declination == pytest.approx(0.2)
    assert log.damage.bad_records == log.damage.skipped_bytes == log.damage.truncated_bytes == 0
    assert any("no FMTU" in note for note in log.notes)


def test_units_from_fmtu_convert_and_unknown_units_leave_the_quantity_out(
    tmp_path: Path,
) -> None:
    with_units = load(imu_log(with_units=True).save(tmp_path / "units.bin"))
    plain = load(imu_log().save(tmp_path / "plain.bin"))
    # Gauss with multiplier 1e-3 is the milligauss the older logs are assumed to hold
    np.testing.assert_allclose(with_units.mag[0].values, plain.mag[0].values, rtol=1e-15)
    np.testing.assert_array_equal(with_units.imus[0].gyro, plain.imus[0].gyro)
    np.testing.assert_array_equal(with_units.attitude.values, plain.attitude.values)
    assert not any("no FMTU" in note for note in with_units.notes)

    # a log stating its gyro in deg/s is converted; one in an unknown unit is left out
    log = imu_log(with_units=True)
    log.out = log.out.replace(b"rad/s", b"deg/s").replace(b"Gauss", b"Tesla")
    converted = load(log.save(tmp_path / "degrees.bin"))
    np.testing.assert_allclose(converted.imus[0].gyro, np.radians(plain.imus[0].gyro), rtol=1e-15)
    assert converted.mag == {}
    assert any("MAG.MagX is in 'Tesla'" in note for note in converted.notes)


def test_copter_frame_and_sub_firmware_give_the_vehicle_type(tmp_path: Path) -> None:
    for text, frame, expected in (
        ("ArduCopter V4.4.0", "Frame: HEXA/X", 13),
        ("ArduCopter V4.4.0", "Frame: QUAD/X", 2),
        ("ArduSub V4.1.0", "", 12),
        ("ArduRover V4.2.0", "", 10),
        ("something else", "", 0),
    ):
        log = imu_log(samples=3)
        log.record("MSG", 0, text)
        if frame:
            log.record("MSG", 0, frame)
        log.out = log.out.replace(b"ArduPlane V4.5.1", b"nothing here    ")
        assert load(log.save(tmp_path / "v.bin")).vehicle_type == expected, text


def test_damage_is_skipped_and_counted(tmp_path: Path) -> None:
    log = imu_log()
    intact = load(log.save(tmp_path / "intact.bin"))
    data = bytes(log.out)
    middle = len(data) // 2
    # five bytes of rubbish between two records: one bad record, five bytes skipped
    cut = middle + data[middle:].index(HEADER + bytes([129]))
    garbled = data[:cut] + b"\x01\xa3\x95\xff\x00" + data[cut:]
    log171 = load(_write(tmp_path / "garbled.bin", garbled))
    assert (log171.damage.bad_records, log171.damage.skipped_bytes) == (1, 5)
    assert len(log171.imus[0].t_us) == len(intact.imus[0].t_us)

    # a record whose type byte now names another type of a different length is dropped
    retyped = bytearray(data)
    retyped[cut + 2] = 130  # IMU → MAG
    damaged = load(_write(tmp_path / "retyped.bin", bytes(retyped)))
    assert damaged.damage.bad_records == 1
    assert sum(len(i.t_us) for i in damaged.imus) == sum(len(i.t_us) for i in intact.imus) - 1

    # cut inside the last record: counted as truncated, everything before it read
    last = log.record("IMU", 9_000_000, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)
    full = bytes(log.out)
    for kept in (1, 2, 3, 10, len(last) - 1):
        cut_log = load(_write(tmp_path / "cut.bin", full[: len(full) - len(last) + kept]))
        assert cut_log.damage.truncated_bytes == kept
        assert cut_log.damage.bad_records == 0
        assert len(cut_log.imus[0].t_us) == len(intact.imus[0].t_us)


def test_a_log_of_many_short_records_is_indexed_whole(tmp_path: Path) -> None:
    log = imu_log(samples=10)
    log.define(140, "TINY", "B", "V")
    for k in range(30_000):  # 4-byte records: more than one pass of the index
        log.record("TINY", k % 256)
    log.record("IMU", 9_000_000, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)
    path = log.save(tmp_path / "tiny.bin")
    records = read_records(path)
    assert records.count("TINY") == 30_000
    np.testing.assert_array_equal(records.table("TINY")["V"], np.arange(30_000) % 256)
    assert load(path).imus[0].t_us[-1] == 9_000_000


def test_time_going_back_is_dropped_and_counted(tmp_path: Path) -> None:
    log = imu_log(samples=3)
    log.record("IMU", 1_000_000, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)  # a repeat of sample 0
    loaded = load(log.save(tmp_path / "repeat.bin"))
    assert loaded.damage.dropped_samples == 1
    assert np.all(np.diff(loaded.imus[0].t_us) > 0)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


@pytest.mark.parametrize(
    "content",
    [b"", b"\0" * 4096, b"\xa3\x95", b"\xa3\x95\x80\x80", b"ULog\x01\x12\x35", "random"],
    ids=["empty", "zeros", "header-only", "cut-fmt", "ulog-magic-only", "random"],
)
def test_unusable_files_raise_one_line_errors(tmp_path: Path, content: bytes | str) -> None:
    if content == "random":
        content = np.random.default_rng(7).integers(0, 256, 10_000, dtype=np.uint8).tobytes()
    path = _write(tmp_path / "bad.bin", content)
    with pytest.raises(OnboardLogError) as raised:
        load(path)
    message = str(raised.value)
    assert "\n" not in message and path.name in message


def test_a_log_of_formats_only_or_zeros_after_them_has_no_imu(tmp_path: Path) -> None:
    log = imu_log(samples=0)
    with pytest.raises(OnboardLogError, match="no IMU samples"):
        load(log.save(tmp_path / "formats.bin"))
    padded = _write(tmp_path / "padded.bin", bytes(log.out) + b"\0" * 1000)
    with pytest.raises(OnboardLogError, match="no IMU samples"):
        load(padded)
    assert read_records(padded).damage.skipped_bytes == 1000


def test_missing_file_raises_onboard_log_error(tmp_path: Path) -> None:
    with pytest.raises(OnboardLogError, match="cannot read"):
        load(tmp_path / "absent.bin")


# --------------------------------------------------------------------------
# The shared logs
# --------------------------------------------------------------------------


def shared(folder: str, pattern: str) -> list[Path]:
    root = data_root()
    files = sorted((root / folder).glob(pattern)) if root is not None else []
    if not files:
        pytest.skip(
            f"no {folder} logs: set {DATA_ENV_VAR} to a folder containing {folder}/ "
            "(default: ../shared/data beside the project)"
        )
    return files


def dataflash_files() -> list[Path]:
    return [p for p in shared("dataflash", "*") if p.suffix.lower() == ".bin"]


@pytest.fixture(scope="module", params=["log171", "copter_112", "plane_329"])
def dataflash_pair(request: pytest.FixtureRequest) -> tuple[Path, dict[str, list]]:
    """A shared .bin file and every message DFReader reads from it, by type."""
    path = next((p for p in dataflash_files() if request.param in p.name), None)
    if path is None:
        pytest.skip(f"no shared DataFlash log named *{request.param}*")
    return path, dfreader_messages(path)


def dfreader_messages(path: Path) -> dict[str, list]:
    """Every message pymavlink's DFReader reads from ``path``, by type."""
    from pymavlink.DFReader import DFReader_binary

    reader = DFReader_binary(str(path))
    messages: dict[str, list] = {}
    while (message := reader.recv_msg()) is not None:
        messages.setdefault(message.get_type(), []).append(message)
    return messages


def assert_records_equal_dfreader(path: Path, messages: dict[str, list]) -> None:
    records = read_records(path)
    for name, expected in messages.items():
        if name == "FMT":
            continue
        assert records.count(name) == len(expected), name
        for column in records.columns(name):
            kind = records.format_char(name, column)
            values = [getattr(m, column) for m in expected]
            if kind in "nNZ":
                assert records.strings(name, column) == values, (name, column)
            elif kind == "a":
                np.testing.assert_array_equal(records.table(name)[column], values)
            else:
                np.testing.assert_array_equal(
                    records.column(name, column), np.array(values, dtype=np.float64), (name, column)
                )


def test_every_record_of_every_type_equals_dfreader(dataflash_pair) -> None:
    path, messages = dataflash_pair
    assert_records_equal_dfreader(path, messages)


def test_a_written_log_with_units_equals_dfreader(tmp_path: Path) -> None:
    path = imu_log(with_units=True).save(tmp_path / "units.bin")
    messages = dfreader_messages(path)
    assert {"IMU", "MAG", "GPS", "ATT", "FMTU", "UNIT", "MULT"} <= set(messages)
    assert_records_equal_dfreader(path, messages)


def test_imu_att_gps_mag_equal_dfreader_in_si_units(dataflash_pair) -> None:
    path, messages = dataflash_pair
    log = load(path)
    for imu in log.imus:
        name = ("IMU", "IMU2", "IMU3")[imu.instance]
        expected = messages[name]
        np.testing.assert_array_equal(imu.t_us, [m.TimeMS * 1000 for m in expected])
        np.testing.assert_array_equal(imu.gyro, [[m.GyrX, m.GyrY, m.GyrZ] for m in expected])
        np.testing.assert_array_equal(imu.accel, [[m.AccX, m.AccY, m.AccZ] for m in expected])
    assert {i.instance for i in log.imus} == {
        n for n, name in enumerate(("IMU", "IMU2", "IMU3")) if messages.get(name)
    }

    parameters = {m.Name: m.Value for m in messages["PARM"]}
    trim = np.degrees([parameters.get("AHRS_TRIM_X", 0.0), parameters.get("AHRS_TRIM_Y", 0.0)])
    att = messages["ATT"]
    np.testing.assert_array_equal(log.attitude.t_us, [m.TimeMS * 1000 for m in att])
    euler = np.radians([[m.Roll + trim[0], m.Pitch + trim[1], m.Yaw] for m in att])
    np.testing.assert_allclose(log.attitude.values[:, :2], euler[:, :2], rtol=0, atol=1e-12)
    yaw_error = np.angle(np.exp(1j * (log.attitude.values[:, 2] - euler[:, 2])))
    assert np.max(np.abs(yaw_error)) < 1e-12

    fixed = [m for m in messages["GPS"] if m.Status >= 3]
    np.testing.assert_array_equal(log.gps_velocity.t_us, [m.T * 1000 for m in fixed])
    course = np.radians([m.GCrs for m in fixed])
    speed = np.array([m.Spd for m in fixed])
    np.testing.assert_allclose(
        log.gps_velocity.values,
        np.column_stack((speed * np.cos(course), speed * np.sin(course), [m.VZ for m in fixed])),
        rtol=0,
        atol=1e-12,
    )
    np.testing.assert_array_equal(log.gps_fix.values[:, 0], [m.Status for m in messages["GPS"]])
    for instance, name in enumerate(("MAG", "MAG2", "MAG3")):
        if not messages.get(name):
            assert instance not in log.mag
            continue
        expected = np.array([[m.MagX, m.MagY, m.MagZ] for m in messages[name]]) * 0.1
        np.testing.assert_array_equal(log.mag[instance].values, expected)
    assert log.damage.bad_records == log.damage.skipped_bytes == log.damage.dropped_samples == 0


def test_shared_logs_give_their_vehicle_types() -> None:
    types = {p.name: load(p).vehicle_type for p in dataflash_files()}
    for name, vehicle in types.items():
        assert vehicle == (1 if "plane" in name else 2), name


@pytest.mark.parametrize("fraction", [0.001, 0.1, 0.5, 0.9, 0.9999])
def test_truncated_shared_log_reads_up_to_the_cut(tmp_path: Path, fraction: float) -> None:
    source = next(p for p in dataflash_files() if "log171" in p.name)
    data = source.read_bytes()
    whole = read_records(source)
    imu_type = whole.formats["IMU"].type
    lengths = {d.type: d.length for d in whole.formats.values()}
    ends = whole.offsets + np.array([lengths[int(t)] for t in whole.types])
    size = int(len(data) * fraction)
    complete = ends <= size
    cut = _write(tmp_path / "cut.bin", data[:size])
    try:
        log = load(cut)
    except OnboardLogError as error:  # cut before the first IMU record
        assert "no IMU samples" in str(error)
        assert not np.any(complete & (whole.types == imu_type))
        return
    imu = log.imus[0]
    assert len(imu.t_us) == np.count_nonzero(complete & (whole.types == imu_type))
    np.testing.assert_array_equal(imu.gyro, load(source).imus[0].gyro[: len(imu.t_us)])
    assert log.damage.truncated_bytes == size - ends[complete][-1]
    assert log.damage.bad_records == log.damage.skipped_bytes == 0


def test_overwritten_bytes_cost_only_the_records_they_hit(tmp_path: Path) -> None:
    source = next(p for p in dataflash_files() if "log171" in p.name)
    data = bytearray(source.read_bytes())
    full = load(source)
    rng = np.random.default_rng(32)
    spots = rng.integers(100_000, len(data) - 1000, 20)
    for spot in spots:
        data[spot : spot + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
    log = load(_write(tmp_path / "hit.bin", bytes(data)))
    assert len(spots) // 2 <= log.damage.bad_records <= 2 * len(spots)
    assert len(spots) * 16 <= log.damage.skipped_bytes <= len(spots) * 64 * 4
    # a time garbled forwards costs that sample, not the rest of the log
    assert log.damage.dropped_samples <= 2 * len(spots)
    for imu, whole in zip(log.imus, full.imus, strict=True):
        assert len(whole.t_us) - 2 * len(spots) <= len(imu.t_us) <= len(whole.t_us)
        # every sample is one of the log's own, at its own time, but for those whose
        # record was hit past its header (DataFlash has no checksum to tell)
        index = np.minimum(np.searchsorted(whole.t_us, imu.t_us), len(whole.t_us) - 1)
        own = (whole.t_us[index] == imu.t_us) & np.all(whole.gyro[index] == imu.gyro, axis=1)
        assert np.count_nonzero(~own) <= len(spots)


def test_a_time_thrown_ahead_costs_one_sample(tmp_path: Path) -> None:
    log = imu_log(samples=3)
    log.record("IMU", 2**40, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)
    for k in range(10):
        log.record("IMU", 2_000_000 + k, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)
    imu = load(log.save(tmp_path / "ahead.bin")).imus[0]
    assert len(imu.t_us) == 13 and imu.t_us[-1] == 2_000_009


# --------------------------------------------------------------------------
# ULog against pyulog
# --------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["pyulog_sample.ulg", "small", "tagged"])
def ulog_pair(request: pytest.FixtureRequest) -> tuple[OnboardLog, dict]:
    from pyulog import ULog

    path = next((p for p in shared("ulog", "*.ulg") if request.param in p.name), None)
    if path is None:
        pytest.skip(f"no shared ULog named *{request.param}*")
    ulog = ULog(str(path))
    topics = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    return load(path), {"topics": topics, "parameters": ulog.initial_parameters}


def _columns(data: dict, field: str, count: int = 3) -> np.ndarray:
    return np.column_stack([data[f"{field}[{i}]"] for i in range(count)]).astype(np.float64)


def test_ulog_equals_pyulog(ulog_pair) -> None:
    log, reference = ulog_pair
    topics = reference["topics"]
    assert (log.format, log.autopilot) == ("ulog", "PX4")
    assert log.vehicle_type == reference["parameters"]["MAV_TYPE"]
    sensors = topics[("sensor_combined", 0)]
    (imu,) = log.imus
    np.testing.assert_array_equal(imu.t_us, sensors["timestamp"])
    np.testing.assert_array_equal(imu.gyro, _columns(sensors, "gyro_rad"))
    np.testing.assert_array_equal(imu.accel, _columns(sensors, "accelerometer_m_s2"))

    attitude = topics[("vehicle_attitude", 0)]
    q = _columns(attitude, "q", 4)
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_euler("ZYX")[:, ::-1]
    assert len(log.attitude.t_us) == len(q)
    difference = log.attitude.values - expected
    assert np.max(np.abs(np.angle(np.exp(1j * difference)))) < 1e-6

    if ("vehicle_magnetometer", 0) in topics:
        field = _columns(topics[("vehicle_magnetometer", 0)], "magnetometer_ga") * 100
        np.testing.assert_array_equal(log.mag[0].values, field)
    gps = topics.get(("vehicle_gps_position", 0))
    if gps is None:
        assert log.gps_velocity is None
    else:
        fixed = gps["fix_type"] >= 3
        ned = np.column_stack([gps[f"vel_{a}_m_s"][fixed] for a in "ned"])
        np.testing.assert_array_equal(log.gps_velocity.values, ned)
        np.testing.assert_array_equal(log.gps_fix.values[:, 0], gps["fix_type"])
    truth = topics.get(("vehicle_attitude_groundtruth", 0))
    assert (log.truth is None) == (truth is None)
    assert log.damage.bad_records == 0


@pytest.mark.parametrize("fraction", [0.3, 0.7, 0.999])
def test_truncated_and_overwritten_ulog_read_what_is_readable(
    tmp_path: Path, fraction: float
) -> None:
    source = next(p for p in shared("ulog", "*.ulg") if p.name == "pyulog_sample.ulg")
    data = source.read_bytes()
    whole = load(source).imus[0]
    cut = load(_write(tmp_path / "cut.ulg", data[: int(len(data) * fraction)])).imus[0]
    assert 0 < len(cut.t_us) <= len(whole.t_us)
    np.testing.assert_array_equal(cut.gyro, whole.gyro[: len(cut.t_us)])

    damaged = bytearray(data)
    start = int(len(data) * fraction)
    rng = np.random.default_rng(int(fraction * 1000))
    damaged[start : start + 4000] = rng.integers(0, 256, 4000, dtype=np.uint8).tobytes()
    log = load(_write(tmp_path / "hit.ulg", bytes(damaged)))
    assert 0 < len(log.imus[0].t_us) <= len(whole.t_us)
    if fraction < 0.9:  # (near the end pyulog stops at the damage without saying so)
        assert log.damage.bad_records == 1
        assert any("corrupt" in note for note in log.notes)


def test_ulog_cut_inside_its_definitions_is_unusable(tmp_path: Path) -> None:
    source = next(p for p in shared("ulog", "*.ulg") if p.name == "pyulog_sample.ulg")
    path = _write(tmp_path / "head.ulg", source.read_bytes()[:3000])
    assert detect(path) == "ulog"
    with pytest.raises(OnboardLogError, match="no sensor_combined"):
        load(path)


# --------------------------------------------------------------------------
# tools/onboard_speed.py
# --------------------------------------------------------------------------


def test_speed_tool_writes_its_section(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tool_module import load_tool

    log = imu_log().save(tmp_path / "plane.bin")
    results = tmp_path / "results.md"
    tool = load_tool("onboard_speed")
    assert tool.main([str(log), "--rounds", "1", "--no-replay", "--results", str(results)]) == 0
    out = capsys.readouterr().out
    assert "| plane.bin | 100 |" in out  # two IMU instances of 50 samples
    section = results.read_text().split("<!-- BEGIN onboard-logs -->\n", 1)[1]
    assert section.startswith("## Onboard logs\n")
    assert f"\n\n{out.strip()}\n\n<!-- END onboard-logs -->\n" in section

    bad = _write(tmp_path / "bad.bin", b"\0" * 100)
    assert tool.main([str(bad), "--rounds", "1", "--no-replay"]) == 2
    assert capsys.readouterr().err.startswith("onboard_speed: bad.bin: neither")
