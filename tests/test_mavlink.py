"""MAVLink I/O: units from the definitions, decoding checked against pymavlink's own
reading of real tlogs, the stream clock (wrap, reboot, gaps), tlog reading and writing,
connection strings."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from pymavlink import mavutil

from mavest.datasets import data_root
from mavest.mavlink.clock import WRAP_TICKS, ClockEvent, StreamClock
from mavest.mavlink.links import LinkError, parse_endpoint
from mavest.mavlink.messages import (
    IMU_FORMATS,
    IMU_MESSAGES,
    MAVLink,
    decode_imu,
    mavlink2,
    time_boot_ms,
)
from mavest.mavlink.tlog import TlogError, TlogReader, TlogWriter

G = 9.80665


def _tlogs() -> list[Path]:
    root = data_root()
    if root is None or not (root / "tlogs").is_dir():
        return []
    return sorted((root / "tlogs").glob("*.tlog"))


needs_tlogs = pytest.mark.skipif(
    not _tlogs(),
    reason="real tlogs not found: set MAVEST_DATA to the folder holding tlogs/ "
    "(default ../shared/data)",
)


# ------------------------------------------------------------------ units


def test_units_come_from_the_message_definitions() -> None:
    raw, highres = IMU_FORMATS["RAW_IMU"], IMU_FORMATS["HIGHRES_IMU"]
    assert raw.accel_scale == pytest.approx(G / 1000)  # mG
    assert raw.gyro_scale == pytest.approx(1e-3)  # mrad/s
    assert raw.mag_scale == pytest.approx(0.1)  # mgauss → µT
    assert (raw.time_field, raw.time_scale) == ("time_usec", 1e-6)
    assert (highres.accel_scale, highres.gyro_scale, highres.mag_scale) == (1.0, 1.0, 100.0)
    for name in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        assert IMU_FORMATS[name].time_field == "time_boot_ms"
        assert IMU_FORMATS[name].accel_scale == raw.accel_scale
    # and the definitions really say so (not a table we made up)
    assert mavlink2.MAVLink_raw_imu_message.fieldunits_by_name["xacc"] == "mG"
    assert mavlink2.MAVLink_highres_imu_message.fieldunits_by_name["xgyro"] == "rad/s"


def _packet(encode: str, *fields: object, system: int = 1, component: int = 1) -> object:
    mav = MAVLink(None, srcSystem=system, srcComponent=component)
    packet = getattr(mav, encode)(*fields).pack(mav)
    return MAVLink(None).decode(bytearray(packet))


def test_raw_imu_decodes_to_si_with_its_instance() -> None:
    message = _packet("raw_imu_encode", 123_456_789, 10, -20, -1000, 100, -200, 300, 1, 2, 3, 2, 25)
    sample = decode_imu(message)
    assert sample is not None
    assert sample.stream == (1, 1, "RAW_IMU", 2)
    assert sample.ticks * sample.tick == pytest.approx(123.456789)
    assert sample.accel == pytest.approx((0.1 * G / 10, -0.2 * G / 10, -G))
    assert sample.gyro == pytest.approx((0.1, -0.2, 0.3))
    assert sample.mag == pytest.approx((0.1, 0.2, 0.3))


def test_scaled_imu_instances_are_in_the_name() -> None:
    for name, instance in (("scaled_imu", 0), ("scaled_imu2", 1), ("scaled_imu3", 2)):
        message = _packet(f"{name}_encode", 5000, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0)
        sample = decode_imu(message)
        assert sample is not None and sample.stream.instance == instance
        assert sample.ticks * sample.tick == pytest.approx(5.0)


def test_highres_imu_honours_fields_updated() -> None:
    fields = (1_000_000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0.2, 0.0, 0.4, 1013.0, 0.0, 0.0, 20.0)
    everything = _packet("highres_imu_encode", *fields, 0x1FFF, 0)
    sample = decode_imu(everything)
    assert sample is not None
    assert sample.accel == pytest.approx((0.1, 0.2, -9.8))
    assert sample.mag == pytest.approx((20.0, 0.0, 40.0))  # gauss → µT
    no_mag = decode_imu(_packet("highres_imu_encode", *fields, 0x3F, 0))
    assert no_mag is not None and no_mag.mag is None
    assert decode_imu(_packet("highres_imu_encode", *fields, 0x1FFF & ~0x08, 0)) is None


def test_time_boot_ms_wraps_like_the_field() -> None:
    assert time_boot_ms(1.2345) == 1234
    assert time_boot_ms(WRAP_TICKS / 1000 + 0.5) == 500


# ------------------------------------------------------------------ real tlogs


# (gyro, accel) factors to SI as the MAVLink common.xml documentation states them,
# written out here independently of mavest's table.
_DOCUMENTED_SI = {
    "RAW_IMU": (1e-3, G / 1000),
    "SCALED_IMU": (1e-3, G / 1000),
    "SCALED_IMU2": (1e-3, G / 1000),
    "SCALED_IMU3": (1e-3, G / 1000),
    "HIGHRES_IMU": (1.0, 1.0),
}


def _pymavlink_imu(path: Path) -> list[tuple]:
    """IMU messages as pymavlink's own tlog reader sees them, in SI by the documented units."""
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    out = []
    while (message := connection.recv_match(type=list(IMU_MESSAGES))) is not None:
        name = message.get_type()
        gyro_si, accel_si = _DOCUMENTED_SI[name]
        stamp = message.time_usec if hasattr(message, "time_usec") else message.time_boot_ms
        out.append(
            (
                message.get_srcSystem(),
                message.get_srcComponent(),
                name,
                stamp,
                tuple(getattr(message, f"{axis}gyro") * gyro_si for axis in "xyz"),
                tuple(getattr(message, f"{axis}acc") * accel_si for axis in "xyz"),
            )
        )
    return out


@needs_tlogs
@pytest.mark.parametrize("path", _tlogs(), ids=lambda p: p.name)
def test_imu_samples_equal_pymavlinks_reading(path: Path) -> None:
    reference = _pymavlink_imu(path)
    ours = []
    for record in TlogReader.open(path):
        sample = decode_imu(record.message) if record.message is not None else None
        if sample is not None:
            key = sample.stream
            ours.append(
                (
                    key.system,
                    key.component,
                    key.message,
                    sample.ticks,
                    tuple(sample.gyro),
                    tuple(sample.accel),
                )
            )
    assert len(ours) == len(reference) > 0
    for mine, theirs in zip(ours, reference, strict=True):
        assert mine[:4] == theirs[:4]
        assert mine[4] == pytest.approx(theirs[4], rel=1e-12, abs=1e-15)
        assert mine[5] == pytest.approx(theirs[5], rel=1e-12, abs=1e-15)


@needs_tlogs
def test_reader_counts_every_message_type_as_pymavlink_does() -> None:
    path = next(p for p in _tlogs() if "UAVLogViewer" in p.name)
    ours: dict[str, int] = {}
    for record in TlogReader.open(path):
        name = record.message.get_type()
        ours[name] = ours.get(name, 0) + 1
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    theirs: dict[str, int] = {}
    while (message := connection.recv_msg()) is not None:
        theirs[message.get_type()] = theirs.get(message.get_type(), 0) + 1
    assert ours == theirs


# ------------------------------------------------------------------ tlog files


def _raw_imu_packets(n: int) -> list[bytes]:
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    return [
        mav.raw_imu_encode(1000 * i, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav)
        for i in range(n)
    ]


def test_writer_and_reader_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "x.tlog"
    packets = _raw_imu_packets(50)
    with TlogWriter(path) as writer:
        for i, packet in enumerate(packets):
            writer.write(1_700_000_000_000_000 + i, packet)
    records = list(TlogReader.open(path))
    assert [r.packet for r in records] == packets
    assert [r.timestamp_us for r in records] == [1_700_000_000_000_000 + i for i in range(50)]


def test_reader_resynchronises_past_garbage_and_truncation(tmp_path: Path) -> None:
    path = tmp_path / "damaged.tlog"
    packets = _raw_imu_packets(20)
    data = bytearray()
    for i, packet in enumerate(packets):
        record = (1_700_000_000_000_000 + i).to_bytes(8, "big") + packet
        if i == 5:
            data += b"\x00garbage\xfe\x03"  # a false start byte among the junk
        if i == 9:
            record = record[:-1] + bytes([record[-1] ^ 0xFF])  # bad CRC
        data += record
    data += data[-20:-5]  # a record cut off
    path.write_bytes(bytes(data))
    reader = TlogReader.open(path)
    records = list(reader)
    assert len(records) == 19  # all but the corrupted one
    assert reader.stats.bad_crc == 1 and reader.stats.skipped_bytes > 0


@pytest.mark.parametrize(
    ("content", "message"),
    [(None, "no such file"), (b"", "is empty"), (b"hello, this is text" * 100, "not a MAVLink")],
)
def test_unusable_files_are_a_clear_error(tmp_path: Path, content: bytes | None, message: str):
    path = tmp_path / "input.tlog"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(TlogError, match=message):
        TlogReader.open(path)
    with pytest.raises(TlogError, match="directory"):
        TlogReader.open(tmp_path)


# ------------------------------------------------------------------ the clock


def _readings(ticks: list[int], tick: float = 1e-3, **kwargs: float) -> list[ClockEvent]:
    clock = StreamClock(**kwargs)
    return [clock.read(t, tick).event for t in ticks]


def test_clock_names_duplicates_late_packets_and_gaps() -> None:
    events = _readings([1000, 1010, 1010, 1005, 1020, 1030, 2000, 2010])
    assert events == [
        ClockEvent.FIRST,
        ClockEvent.NEXT,
        ClockEvent.DUPLICATE,
        ClockEvent.OUT_OF_ORDER,
        ClockEvent.NEXT,
        ClockEvent.NEXT,
        ClockEvent.GAP,
        ClockEvent.NEXT,
    ]


def test_clock_undoes_the_32_bit_wrap() -> None:
    clock = StreamClock()
    start = WRAP_TICKS - 2500  # µs: 2.5 ms before the wrap
    times = []
    for k in range(6):
        ticks = (start + 1000 * k) % WRAP_TICKS
        reading = clock.read(ticks, 1e-6)
        times.append(reading.t)
        if k == 3:
            assert reading.event is ClockEvent.WRAPPED
    assert all(b - a == pytest.approx(1e-3) for a, b in itertools.pairwise(times))


def test_reboot_needs_the_new_timeline_to_continue() -> None:
    # a single corrupt timestamp far back is dropped; a reboot (time stays back) is believed
    glitch = _readings([50_000, 50_010, 1_000, 50_020, 50_030])
    assert glitch[2] is ClockEvent.OFF_TIMELINE and glitch[3] is ClockEvent.NEXT
    reboot = _readings([50_000, 50_010, 1_000, 1_010, 1_020, 1_030])
    assert reboot[2:] == [
        ClockEvent.OFF_TIMELINE,
        ClockEvent.OFF_TIMELINE,
        ClockEvent.REBOOT,
        ClockEvent.NEXT,
    ]
    jump = _readings([1_000, 1_010, 10**9, 1_020])  # one timestamp hours ahead
    assert jump[2] is ClockEvent.OFF_TIMELINE and jump[3] is ClockEvent.NEXT


# ------------------------------------------------------------------ connection strings


@pytest.mark.parametrize(
    ("text", "kind", "where"),
    [
        ("udpin:0.0.0.0:14550", "udpin", ("0.0.0.0", 14550)),
        ("udp:127.0.0.1:14550", "udpin", ("127.0.0.1", 14550)),
        ("udpout:10.0.0.2:14550", "udpout", ("10.0.0.2", 14550)),
        ("tcp:127.0.0.1:5760", "tcp", ("127.0.0.1", 5760)),
        ("tcpin:0.0.0.0:5760", "tcpin", ("0.0.0.0", 5760)),
    ],
)
def test_connection_strings_as_pymavlink_users_write_them(text: str, kind: str, where: tuple):
    endpoint = parse_endpoint(text)
    assert (endpoint.kind, (endpoint.host, endpoint.port)) == (kind, where)


def test_serial_devices_and_mistakes() -> None:
    assert parse_endpoint("/dev/ttyACM0", baud=921600).baud == 921600
    assert parse_endpoint("serial:/dev/ttyUSB0:57600").device == "/dev/ttyUSB0"
    for bad in ("udpin:14550", "http://x:1", "tcp:host:99999"):
        with pytest.raises(LinkError):
            parse_endpoint(bad)
