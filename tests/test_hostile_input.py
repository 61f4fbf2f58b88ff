"""Hostile input, on replay and on the live link: damaged bytes, impossible IMU values,
broken clocks, other systems' messages, a flood.

One clean simulated flight per autopilot flavour is damaged in each named way; the
damaged stream is then replayed (``mavest replay FILE --out-tlog OUT``) and sent over
loopback UDP into the live service (``run_live``, in this process, so its counters can
be read). Each case says what it broke: IMU packets destroyed (pymavlink's robust
parser must not read them either), samples made invalid (they must be counted, by
kind, and never estimated), the log lines the damage must produce. Everything else
that pymavlink reads must get an estimate, answered with one ATTITUDE.
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
import re
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil

from mavest.cli import main
from mavest.estimator.config import EstimatorConfig
from mavest.mavlink.clock import WRAP_TICKS
from mavest.mavlink.messages import IMU_MESSAGES, MAVLink
from mavest.mavlink.tlog import TlogReader, message_ids
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Pipeline
from mavest.service.process import ServiceProcess, free_port
from mavest.service.runners import Outputs, RunReport, run_live
from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

FLIGHT_SECONDS = 8.0
IMU_RATE = 200.0  # Hz: the "normal rate" of the stream
N_IMU = round(FLIGHT_SECONDS * IMU_RATE) + 1
IMU_IDS = message_ids(IMU_MESSAGES)
# The pipeline's counters of samples it did not estimate, and of clock events.
DROPPED = ("rejected", "duplicates", "out_of_order", "off_timeline")
COUNTERS = (*DROPPED, "gaps", "realigned", "reboots", "wraps")

Chunk = tuple[int | None, bytes]  # (tlog timestamp, packet) or (None, loose bytes)


# ------------------------------------------------------------------ the clean flights


@dataclass(frozen=True)
class Flight:
    records: list[tuple[int, bytes]]  # (tlog timestamp µs, packet)
    imu: list[int]  # indices of the IMU records

    def chunks(self) -> list[Chunk]:
        return list(self.records)


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Flight]:
    return clean_flights(tmp_path_factory)


def clean_flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Flight]:
    """One clean 8 s flight at 200 Hz per autopilot flavour, as records."""
    out = {}
    for flavour in ("ardupilot", "px4"):
        path = tmp_path_factory.mktemp("clean") / f"{flavour}.tlog"
        write_flight_tlog(path, FLIGHT_SECONDS, IMU_RATE, AUTOPILOTS[flavour], seed=4)
        records = [(r.timestamp_us, r.packet) for r in TlogReader.open(path, frozenset())]
        imu = [i for i, (_, packet) in enumerate(records) if _message_id(packet) in IMU_IDS]
        assert len(imu) == N_IMU
        out[flavour] = Flight(records, imu)
    return out


def _message_id(packet: bytes) -> int:
    return packet[7] | (packet[8] << 8) | (packet[9] << 16) if packet[0] == 0xFD else packet[5]


def _repacked(packet: bytes, system: int | None = None, **fields: Any) -> bytes:
    """The packet with some fields (or its system id) changed: a valid packet, CRC and all."""
    message = MAVLink(None).decode(bytearray(packet))
    header = message.get_header()
    mav = MAVLink(None, srcSystem=header.srcSystem if system is None else system)
    mav.srcComponent = header.srcComponent
    mav.seq = header.seq
    for name, value in fields.items():
        setattr(message, name, value)
    return message.pack(mav)


# ------------------------------------------------------------------ the damage


@dataclass
class Damage:
    """A damaged stream and what the pipeline must make of it."""

    chunks: list[Chunk]
    imu_readable: int | None  # IMU packets still intact (None: as many as pymavlink reads)
    counters: dict[str, int] = field(default_factory=dict)  # the rest must be 0
    foreign: int = 0  # of the readable IMU packets, those from systems not followed
    mag_dropped: int = 0  # samples estimated without their (unusable) magnetometer
    # the filter sets the magnetometer aside for a while (waiting for calm after a
    # clipped gyro): fewer readings taken than one per update interval
    mag_set_aside: bool = False
    log: tuple[str, ...] = ()  # what the log must say
    args: tuple[str, ...] = ()  # options for the run


def _spread(flight: Flight, count: int, seed: int, skip: int = 50) -> list[int]:
    """Record indices of ``count`` IMU samples, spread out, none among the first ``skip``."""
    rng = random.Random(seed)
    chosen = sorted(rng.sample(range(skip, N_IMU - 1, 3), count))
    return [flight.imu[k] for k in chosen]


def _with_fields(flight: Flight, changes: dict[int, dict[str, Any]]) -> list[Chunk]:
    return [
        (stamp, _repacked(packet, **changes[i]) if i in changes else packet)
        for i, (stamp, packet) in enumerate(flight.records)
    ]


def garbage_between_packets(flight: Flight) -> Damage:
    rng = random.Random(1)
    where = set(rng.sample(range(1, len(flight.records)), 60))
    chunks: list[Chunk] = []
    for i, record in enumerate(flight.records):
        if i in where:
            junk = bytearray(rng.randbytes(rng.randrange(1, 80)))
            for _ in range(3):  # start bytes among the junk: false starts
                junk[rng.randrange(len(junk))] = rng.choice((0xFD, 0xFE))
            chunks.append((None, bytes(junk)))
        chunks.append(record)
    return Damage(chunks, N_IMU)


def false_record_starts(flight: Flight) -> Damage:
    """Junk that looks like a record: a plausible timestamp and a start byte, then noise."""
    rng = random.Random(2)
    where = set(rng.sample(range(1, len(flight.records)), 40))
    chunks: list[Chunk] = []
    for i, (stamp, packet) in enumerate(flight.records):
        if i in where:
            junk = bytes([rng.choice((0xFD, 0xFE))]) + rng.randbytes(rng.randrange(2, 40))
            chunks.append((stamp, junk))
        chunks.append((stamp, packet))
    return Damage(chunks, N_IMU)


def bit_flips_in_imu_packets(flight: Flight) -> Damage:
    rng = random.Random(3)
    broken = set(_spread(flight, 25, seed=3))
    chunks: list[Chunk] = []
    for i, (stamp, packet) in enumerate(flight.records):
        if i in broken:
            flipped = bytearray(packet)
            position = rng.randrange(1, len(packet))  # anything but the start byte
            flipped[position] ^= 1 << rng.randrange(8)
            packet = bytes(flipped)
        chunks.append((stamp, packet))
    return Damage(chunks, N_IMU - 25)


def bit_flips_anywhere(flight: Flight) -> Damage:
    """Flips at random places of the records, timestamps included (none on a live link)."""
    rng = random.Random(4)
    chunks = flight.chunks()
    for _ in range(40):
        i = rng.randrange(len(chunks))
        stamp, packet = chunks[i]
        record = bytearray(stamp.to_bytes(8, "big") + packet)
        record[rng.randrange(len(record))] ^= 1 << rng.randrange(8)
        chunks[i] = (int.from_bytes(record[:8], "big"), bytes(record[8:]))
    return Damage(chunks, None)


def truncated_mid_packet(flight: Flight) -> Damage:
    cut = flight.imu[N_IMU - 300]
    stamp, packet = flight.records[cut]
    return Damage([*flight.records[:cut], (stamp, packet[: len(packet) // 2])], N_IMU - 300)


def record_cut_mid_stream(flight: Flight) -> Damage:
    cuts = set(_spread(flight, 10, seed=5))
    chunks = [
        (stamp, packet[: len(packet) // 2] if i in cuts else packet)
        for i, (stamp, packet) in enumerate(flight.records)
    ]
    return Damage(chunks, N_IMU - 10)


def highres_nan_inf(flight: Flight) -> Damage:
    bad = _spread(flight, 16, seed=6)
    values = [
        {"xgyro": math.nan},
        {"ygyro": math.inf},
        {"zacc": -math.inf},
        {"xacc": math.nan, "yacc": math.nan, "zacc": math.nan},
    ]
    changes = {i: values[k % 4] for k, i in enumerate(bad)}
    mag_only = [i for i in _spread(flight, 24, seed=7) if i not in changes][:6]
    changes |= {i: {"xmag": math.nan} for i in mag_only[:3]}
    changes |= {i: {"zmag": -math.inf} for i in mag_only[3:]}
    return Damage(_with_fields(flight, changes), N_IMU, {"rejected": 16}, mag_dropped=6)


def highres_absurd(flight: Flight) -> Damage:
    bad = _spread(flight, 15, seed=8)
    values = [
        {"xgyro": 1e6},
        {"zacc": 1e20},
        {"yacc": -3.4e38},
        {"zgyro": -60.0},  # beyond any MEMS gyro (2000 °/s ≈ 35 rad/s)
        {"xacc": 600.0},  # 61 g
    ]
    changes = {i: values[k % 5] for k, i in enumerate(bad)}
    mag_only = [i for i in _spread(flight, 20, seed=9) if i not in changes][:4]
    changes |= {i: {"ymag": 1e9} for i in mag_only}
    return Damage(_with_fields(flight, changes), N_IMU, {"rejected": 15}, mag_dropped=4)


def highres_all_zero(flight: Flight) -> Damage:
    zero = dict.fromkeys(("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro"), 0.0)
    zero |= dict.fromkeys(("xmag", "ymag", "zmag"), 0.0)
    changes = {i: zero for i in _spread(flight, 12, seed=10)}
    return Damage(_with_fields(flight, changes), N_IMU, {"rejected": 12})


def raw_imu_saturated(flight: Flight) -> Damage:
    """int16 counts at the type's limit: the sensor (or the firmware's clip) saturated."""
    bad = _spread(flight, 16, seed=11)
    values = [{"xgyro": 32767}, {"zgyro": -32768}, {"zacc": -32768}, {"yacc": 32767}]
    changes = {i: values[k % 4] for k, i in enumerate(bad)}
    return Damage(_with_fields(flight, changes), N_IMU, {"rejected": 16}, mag_set_aside=True)


def raw_imu_all_zero(flight: Flight) -> Damage:
    """A message with nothing in it, and accelerometers reading exactly nothing."""
    zero_all = dict.fromkeys(
        ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag"), 0
    )
    zero_accel = dict.fromkeys(("xacc", "yacc", "zacc"), 0)
    bad = _spread(flight, 14, seed=12)
    changes = {i: zero_all if k % 2 else zero_accel for k, i in enumerate(bad)}
    return Damage(_with_fields(flight, changes), N_IMU, {"rejected": 14})


def _retimed(flight: Flight, new_time: Callable[[int, int], int | None]) -> list[Chunk]:
    """IMU records with ``time_usec`` = new_time(sample number, old time_usec) (None: as is)."""
    sample_of = {index: k for k, index in enumerate(flight.imu)}
    chunks: list[Chunk] = []
    for i, (stamp, packet) in enumerate(flight.records):
        if i in sample_of:
            old = MAVLink(None).decode(bytearray(packet)).time_usec
            new = new_time(sample_of[i], old)
            if new is not None:
                packet = _repacked(packet, time_usec=new)
        chunks.append((stamp, packet))
    return chunks


REBOOT_AT = 1000  # sample number


def reboot(flight: Flight) -> Damage:
    """Time goes back to 3 s after boot and carries on from there."""
    step = round(1e6 / IMU_RATE)

    def new_time(k: int, old: int) -> int | None:
        return 3_000_000 + (k - REBOOT_AT) * step if k >= REBOOT_AT else None

    # the first samples of the new timeline wait for it to be confirmed (StreamClock.confirm),
    # then are estimated: none is lost
    return Damage(
        _retimed(flight, new_time),
        N_IMU,
        {"reboots": 1},
        log=("went back", "re-initialising"),
    )


def jump_forward_hours(flight: Flight) -> Damage:
    def new_time(k: int, old: int) -> int | None:
        return old + 3 * 3600 * 10**6 if k >= REBOOT_AT else None

    return Damage(
        _retimed(flight, new_time),
        N_IMU,
        {"gaps": 1, "realigned": 1},
        log=("attitude re-aligned",),
    )


def one_timestamp_hours_off(flight: Flight) -> Damage:
    """Single corrupted timestamps, hours ahead and back to just after boot: dropped."""
    ahead, back = 700, 1300

    def new_time(k: int, old: int) -> int | None:
        if k == ahead:
            return old + 5 * 3600 * 10**6
        return 500_000 if k == back else None

    return Damage(_retimed(flight, new_time), N_IMU, {"off_timeline": 2})


def duplicated(flight: Flight) -> Damage:
    doubled = set(_spread(flight, 30, seed=13))
    chunks: list[Chunk] = []
    for i, record in enumerate(flight.records):
        chunks.append(record)
        if i in doubled:
            chunks.append(record)
    return Damage(chunks, N_IMU + 30, {"duplicates": 30})


def out_of_order(flight: Flight) -> Damage:
    """Ten pairs of IMU records swapped: the older one of each is late, and dropped."""
    chunks = flight.chunks()
    for index in _spread(flight, 10, seed=14):
        k = flight.imu.index(index)
        a, b = flight.imu[k], flight.imu[k + 1]
        chunks[a], chunks[b] = chunks[b], chunks[a]
    return Damage(chunks, N_IMU, {"out_of_order": 10})


def wrap_32_bit(flight: Flight) -> Damage:
    """time_usec from a 32-bit µs counter that wraps in the middle of the flight."""
    first = MAVLink(None).decode(bytearray(flight.records[flight.imu[0]][1])).time_usec
    step = round(1e6 / IMU_RATE)
    offset = WRAP_TICKS - first - 800 * step - step // 2  # wraps between samples 800 and 801

    def new_time(k: int, old: int) -> int | None:
        return (old + offset) % WRAP_TICKS

    return Damage(_retimed(flight, new_time), N_IMU, {"wraps": 1})


def other_systems(flight: Flight) -> Damage:
    """IMU messages from a second vehicle (wild values) and a ground station, among ours;
    mavest follows system 1 only (--system 1)."""
    foreign = set(_spread(flight, 100, seed=15))
    chunks: list[Chunk] = []
    for i, (stamp, packet) in enumerate(flight.records):
        chunks.append((stamp, packet))
        if i in foreign:
            system = 2 if i % 2 else 255
            chunks.append((stamp, _repacked(packet, system=system, xgyro=30000, zacc=5000)))
    return Damage(
        chunks,
        N_IMU + 100,
        foreign=100,
        log=("ignoring IMU messages from system 2", "ignoring IMU messages from system 255"),
        args=("--system", "1"),
    )


def ground_station_imu(flight: Flight) -> Damage:
    """A ground station (system 255) sending IMU messages: never a vehicle, by default."""
    foreign = set(_spread(flight, 20, seed=16))
    chunks: list[Chunk] = []
    for i, (stamp, packet) in enumerate(flight.records):
        chunks.append((stamp, packet))
        if i in foreign:
            chunks.append((stamp, _repacked(packet, system=255, xgyro=-20000)))
    return Damage(chunks, N_IMU + 20, foreign=20, log=("ignoring IMU messages from system 255",))


CASES: dict[str, tuple[str, Callable[[Flight], Damage]]] = {
    f.__name__: (flavour, f)
    for flavour, f in (
        ("ardupilot", garbage_between_packets),
        ("ardupilot", false_record_starts),
        ("ardupilot", bit_flips_in_imu_packets),
        ("ardupilot", bit_flips_anywhere),
        ("ardupilot", truncated_mid_packet),
        ("ardupilot", record_cut_mid_stream),
        ("px4", highres_nan_inf),
        ("px4", highres_absurd),
        ("px4", highres_all_zero),
        ("ardupilot", raw_imu_saturated),
        ("ardupilot", raw_imu_all_zero),
        ("ardupilot", reboot),
        ("ardupilot", jump_forward_hours),
        ("ardupilot", one_timestamp_hours_off),
        ("ardupilot", duplicated),
        ("ardupilot", out_of_order),
        ("ardupilot", wrap_32_bit),
        ("ardupilot", other_systems),
        ("ardupilot", ground_station_imu),
    )
}


# ------------------------------------------------------------------ what came out


@dataclass
class Outcome:
    """One run's counters for the followed stream, its answers and its log."""

    imu_read: Counter[bytes]  # IMU packets mavest read (its output tlog holds every input)
    streams: int  # IMU streams estimated
    received: int
    estimated: int
    counters: dict[str, int]
    mag_usable: int  # samples with a usable magnetometer reading
    mag_taken: int  # of those, the ones the filter's magnetometer schedule took
    answers: list[tuple[float, float, float]]  # ATTITUDE (roll, pitch, yaw) sent
    log: str


def _check(outcome: Outcome, damage: Damage, reference: Counter[bytes]) -> None:
    """The damage's expectations against a run; ``reference``: the IMU packets pymavlink's
    robust parsing reads from the same bytes."""
    read = outcome.imu_read
    readable = read.total()
    # nothing read that was not sent whole, and everything pymavlink reads is read
    assert not read - Counter(data for _, data in damage.chunks)
    assert not reference - read, f"pymavlink read {(reference - read).total()} more"
    if damage.imu_readable is not None:
        assert readable == damage.imu_readable
    else:
        assert N_IMU - 40 <= readable <= N_IMU
    assert "Traceback" not in outcome.log
    expected = {name: damage.counters.get(name, 0) for name in COUNTERS}
    assert outcome.counters == expected, outcome.log
    assert outcome.streams == 1
    followed = readable - damage.foreign
    assert outcome.received == followed
    dropped = sum(expected[name] for name in DROPPED)
    assert outcome.estimated == followed - dropped
    assert len(outcome.answers) == outcome.estimated  # one ATTITUDE per estimate
    assert all(math.isfinite(v) for answer in outcome.answers for v in answer)
    # the vehicle is upright and turning gently: a corrupt sample ingested would show
    assert max(abs(roll) for roll, _, _ in outcome.answers) < math.radians(60.0)
    assert outcome.mag_usable == outcome.estimated - damage.mag_dropped
    # one reading per update interval of the flight's time is taken (of 200 Hz readings at
    # 40 Hz updates: 321 over 8 s), give or take where a damaged stretch shifts the schedule
    update_rate = EstimatorConfig().update_rate
    per_update = IMU_RATE / update_rate
    assert outcome.mag_taken <= FLIGHT_SECONDS * update_rate + 2
    if not damage.mag_set_aside:
        assert outcome.mag_taken >= outcome.mag_usable / per_update - 2
    else:  # (measured: 244 of 1585)
        assert 0.5 * outcome.mag_usable / per_update < outcome.mag_taken
    for phrase in damage.log:
        assert phrase in outcome.log, outcome.log


# ------------------------------------------------------------------ replay


def _tlog_bytes(chunks: list[Chunk]) -> bytes:
    return b"".join(
        data if stamp is None else stamp.to_bytes(8, "big") + data for stamp, data in chunks
    )


def _pymavlink_imu(path: Path) -> Counter[bytes]:
    """The IMU packets pymavlink's robust tlog reading finds in the file (not ours)."""
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    packets: Counter[bytes] = Counter()
    while (m := connection.recv_match(type=list(IMU_MESSAGES))) is not None:
        if m.get_srcComponent() != 191:
            packets[bytes(m.get_msgbuf())] += 1
    connection.close()
    return packets


_STREAM = re.compile(r"^  \S+\[\d+\] from \d+/\d+( → ATTITUDE)?: (\d+) of (\d+) samples", re.M)
_PROBLEM = re.compile(
    r"(\d+) (rejected|duplicates?|out of order|off the timeline|gaps?|"
    r"re-aligned|reboots?|wraps?)\b"
)
_SUMMARY_NAMES = {
    "rejected": "rejected",
    "duplicate": "duplicates",
    "duplicates": "duplicates",
    "out of order": "out_of_order",
    "off the timeline": "off_timeline",
    "gap": "gaps",
    "gaps": "gaps",
    "re-aligned": "realigned",
    "reboot": "reboots",
    "reboots": "reboots",
    "wrap": "wraps",
    "wraps": "wraps",
}
_MAG = re.compile(
    r"heading from the magnetometer \(9-D\): [\d.]+ % used of the (\d+) readings taken "
    r"\(of (\d+) usable\)"
)


def _answers(path: Path) -> list[tuple[float, float, float]]:
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    out = []
    while (m := connection.recv_match(type="ATTITUDE")) is not None:
        if m.get_srcComponent() == 191:
            out.append((m.roll, m.pitch, m.yaw))
    connection.close()
    return out


def _replayed(summary: str, log: str, out_tlog: Path) -> Outcome:
    streams = _STREAM.findall(summary)
    primary = next(s for s in streams if s[0])
    block = summary[summary.index(" → ATTITUDE") :].split("\n")[1]
    counters = dict.fromkeys(COUNTERS, 0)
    for value, name in _PROBLEM.findall(block):
        counters[_SUMMARY_NAMES[name]] = int(value)
        # one of a thing reads as one ("1 reboot"), more as more
        if name.rstrip("s") in ("duplicate", "gap", "reboot", "wrap"):
            assert (int(value) == 1) == (not name.endswith("s")), block
    mag = _MAG.search(summary)
    return Outcome(
        _pymavlink_imu(out_tlog),
        len(streams),
        int(primary[2]),
        int(primary[1]),
        counters,
        int(mag.group(2)) if mag else 0,
        int(mag.group(1)) if mag else 0,
        _answers(out_tlog),
        log,
    )


@pytest.mark.parametrize("case", list(CASES))
def test_replay_of_a_damaged_tlog(
    case: str, flights: dict[str, Flight], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    flavour, make = CASES[case]
    damage = make(flights[flavour])
    path, out = tmp_path / "damaged.tlog", tmp_path / "out.tlog"
    path.write_bytes(_tlog_bytes(damage.chunks))
    code = main(["replay", str(path), "--out-tlog", str(out), *damage.args])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    outcome = _replayed(captured.out, captured.err, out)
    _check(outcome, damage, _pymavlink_imu(path))


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.tlog", b"", "is empty"),
        ("random.tlog", random.Random(5).randbytes(50_000), "not a MAVLink telemetry log"),
        ("zeros.tlog", bytes(10_000), "not a MAVLink telemetry log"),
        # onboard logs by their first bytes, with nothing to replay after them
        ("flight.bin", b"\xa3\x95\x80\x80" + random.Random(6).randbytes(5000), "no IMU samples"),
        ("log.ulg", b"ULog\x01\x12\x35" + bytes(5000), "no sensor_combined (IMU) samples"),
        ("folder.tlog", None, "is a directory"),
        ("missing/flight.tlog", None, "no such file"),
    ],
)
def test_unusable_files_are_one_line_and_exit_2(
    name: str, content: bytes | None, message: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    elif name == "folder.tlog":
        path.mkdir()
    out = tmp_path / "out.tlog"
    assert main(["replay", str(path), "--out-tlog", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and message in captured.err, captured.err
    assert captured.err.startswith("mavest: ") and captured.out == ""


def test_mavlink_without_timestamps_is_not_a_tlog(
    flights: dict[str, Flight], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A raw MAVLink capture (a serial dump): packets, but no tlog timestamps."""
    path = tmp_path / "capture.tlog"
    path.write_bytes(b"".join(packet for _, packet in flights["ardupilot"].records))
    assert main(["replay", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a MAVLink telemetry log" in err, err


# ------------------------------------------------------------------ the live link


class _LogLines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def _datagrams(chunks: list[Chunk]) -> list[bytes]:
    """What a vehicle (or the noise on its radio) sends: one datagram per chunk."""
    return [data for _, data in chunks]


def _parsed_imu(datagrams: list[bytes]) -> Counter[bytes]:
    """The IMU packets pymavlink's robust parser finds in the datagrams, read as one stream."""
    parser = MAVLink(None)
    parser.robust_parsing = True
    packets: Counter[bytes] = Counter()
    for datagram in datagrams:
        try:
            messages = parser.parse_buffer(datagram) or ()
        except Exception:
            continue
        packets.update(bytes(m.get_msgbuf()) for m in messages if m.get_type() in IMU_MESSAGES)
    return packets


def _serve(
    datagrams: list[bytes],
    config: ServiceConfig,
    monkeypatch: pytest.MonkeyPatch,
    out_tlog: Path,
) -> tuple[RunReport, list[bytes], list[str]]:
    """Send the datagrams to ``run_live`` (each batch handled before the next is sent,
    so that the kernel never drops one); its report, its replies and its log."""
    delivered = 0
    on_bytes = Pipeline.on_bytes

    def counting(self: Pipeline, link: Any, data: bytes, peer: Any) -> None:
        nonlocal delivered
        delivered += 1
        on_bytes(self, link, data, peer)

    monkeypatch.setattr(Pipeline, "on_bytes", counting)
    lines = _LogLines()
    logger = logging.getLogger("mavest")
    monkeypatch.setattr(logger, "handlers", [lines])
    monkeypatch.setattr(logger, "propagate", False)
    logger.setLevel(logging.INFO)
    replies: list[bytes] = []

    async def session() -> RunReport:
        port = free_port(socket.SOCK_DGRAM)
        stop, ready = asyncio.Event(), asyncio.Event()
        service = asyncio.create_task(
            run_live(
                f"udpin:127.0.0.1:{port}",
                config,
                outputs=Outputs(tlog=out_tlog),
                stop=stop,
                ready=ready,
                status_period=0,
            )
        )
        await asyncio.wait_for(ready.wait(), 120)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
            sock.setblocking(False)
            for start in range(0, len(datagrams), 32):
                for datagram in datagrams[start : start + 32]:
                    sock.sendto(datagram, ("127.0.0.1", port))
                deadline = time.monotonic() + 10.0
                while delivered < min(start + 32, len(datagrams)):
                    assert time.monotonic() < deadline, "the service stopped reading"
                    await asyncio.sleep(0.0005)
                _drain(sock, replies)
            await asyncio.sleep(0.05)
            _drain(sock, replies)
        stop.set()
        return await service

    report = asyncio.run(session())
    return report, replies, lines.lines


def _drain(sock: socket.socket, into: list[bytes]) -> None:
    while True:
        try:
            into.append(sock.recv(65536))
        except BlockingIOError:
            return


def _live_answers(replies: list[bytes]) -> list[tuple[float, float, float]]:
    parser = MAVLink(None)
    answers = []
    for reply in replies:
        for m in parser.parse_buffer(reply) or ():
            if m.get_type() == "ATTITUDE" and m.get_srcComponent() == 191:
                answers.append((m.roll, m.pitch, m.yaw))
    return answers


def _config(args: tuple[str, ...]) -> ServiceConfig:
    if args[:1] == ("--system",):
        return ServiceConfig().replace(input={"system": int(args[1])})
    assert not args
    return ServiceConfig()


@pytest.mark.parametrize("case", list(CASES))
def test_live_link_with_damaged_input(
    case: str, flights: dict[str, Flight], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    flavour, make = CASES[case]
    damage = make(flights[flavour])
    datagrams = _datagrams(damage.chunks)
    out = tmp_path / "live.tlog"
    report, replies, lines = _serve(datagrams, _config(damage.args), monkeypatch, out)
    pipeline = report.pipeline
    assert not report.interrupted
    streams = list(pipeline.streams.values())
    stats = streams[0].stats
    outcome = Outcome(
        _pymavlink_imu(out),
        len(streams),
        stats.received,
        stats.estimated,
        {name: getattr(stats, name) for name in COUNTERS},
        stats.mag_usable,
        stats.mag_taken,
        _live_answers(replies),
        "\n".join(lines),
    )
    _check(outcome, damage, _parsed_imu(datagrams))


# ------------------------------------------------------------------ a flood


FLOOD_SECONDS = 3.0
FLOOD_RATE = 10 * IMU_RATE  # valid IMU packets per second, and as many invalid ones


def _raw_imu(
    mav: MAVLink, time_usec: int, accel: tuple[int, int, int], gyro: tuple[int, int, int]
) -> bytes:
    """RAW_IMU in mG and mrad/s, with a steady magnetometer reading."""
    return mav.raw_imu_encode(time_usec, *accel, *gyro, 200, 30, 400, 0, 3500).pack(mav)


def _flood_packets(count: int) -> tuple[list[bytes], list[bytes], dict[str, int]]:
    """``count`` valid RAW_IMU packets of a vehicle at rest (system 1) at FLOOD_RATE, and
    as many invalid ones beside them; how many of each invalid kind."""
    rng = random.Random(17)
    vehicle = MAVLink(None, srcSystem=1, srcComponent=1)
    ground_station = MAVLink(None, srcSystem=255, srcComponent=190)
    step = round(1e6 / FLOOD_RATE)
    kinds = ("garbage", "bit_flip", "cut", "saturated", "zero", "ground_station", "duplicate")
    sent = dict.fromkeys(kinds, 0)
    valid, invalid = [], []
    for k in range(count):
        time_usec = 20_000_000 + k * step
        noise = [rng.randint(-3, 3) for _ in range(6)]
        accel = (noise[0], noise[1], -1000 + noise[2])
        packet = _raw_imu(vehicle, time_usec, accel, (noise[3], noise[4], noise[5]))
        valid.append(packet)
        kind = kinds[k % len(kinds)]
        sent[kind] += 1
        if kind == "garbage":
            bad = rng.randbytes(rng.randrange(1, 60))
        elif kind == "bit_flip":
            flipped = bytearray(packet)
            flipped[rng.randrange(1, len(packet))] ^= 1 << rng.randrange(8)
            bad = bytes(flipped)
        elif kind == "cut":
            bad = packet[: rng.randrange(1, len(packet))]
        elif kind == "saturated":
            bad = _raw_imu(vehicle, time_usec, (0, 0, -1000), (32767, 0, 0))
        elif kind == "zero":
            bad = _raw_imu(vehicle, time_usec, (0, 0, 0), (0, 0, 0))
        elif kind == "ground_station":
            bad = _raw_imu(ground_station, time_usec, (0, 0, -1000), (0, 0, 0))
        else:
            bad = packet
        invalid.append(bad)
    return valid, invalid, sent


def test_live_flood_of_valid_and_invalid_packets() -> None:
    count = round(FLOOD_SECONDS * FLOOD_RATE)
    valid, invalid, sent = _flood_packets(count)
    port = free_port(socket.SOCK_DGRAM)
    service = ServiceProcess(f"udpin:127.0.0.1:{port}", "--request-rate", "0")
    replies: list[bytes] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.setblocking(False)
        batch = 10  # valid packets per send, each with an invalid one after it
        start = time.monotonic()
        for first in range(0, count, batch):
            # keep to the flood's rate (no faster: a burst is not what is tested)
            ahead = start + first / FLOOD_RATE - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            for k in range(first, min(first + batch, count)):
                sock.sendto(valid[k], ("127.0.0.1", port))
                sock.sendto(invalid[k], ("127.0.0.1", port))
            _drain(sock, replies)
        elapsed = time.monotonic() - start
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            time.sleep(0.01)
            _drain(sock, replies)
    assert elapsed < 1.5 * FLOOD_SECONDS  # the flood really was at its rate
    assert service.process.poll() is None, "".join(service.log)  # still serving
    code, summary = service.stop()
    log = "".join(service.log)
    assert code == 0 and "Traceback" not in log, log

    answered = _live_answers(replies)
    assert len(answered) >= 0.95 * count, (len(answered), summary)
    assert all(abs(roll) < 0.05 and abs(pitch) < 0.05 for roll, pitch, _ in answered)
    (line,) = _STREAM.findall(summary)
    estimated, received = int(line[1]), int(line[2])
    problems = {
        _SUMMARY_NAMES[name]: int(value)
        for value, name in _PROBLEM.findall(summary.split(" → ATTITUDE")[1].split("\n")[1])
    }
    # every valid packet (all but a few the kernel may drop) was estimated, nothing else
    assert 0.97 * count <= estimated <= count, summary
    invalid_samples = sent["saturated"] + sent["zero"] + sent["duplicate"]
    assert estimated + invalid_samples >= received, summary
    assert 0.97 * (sent["saturated"] + sent["zero"]) <= problems.get("rejected", 0), summary
    assert problems.get("rejected", 0) <= sent["saturated"] + sent["zero"], summary
    assert 0.97 * sent["duplicate"] <= problems.get("duplicates", 0) <= sent["duplicate"]
    damaged = re.search(r"damaged input: (\d+) bad packets", summary)
    assert damaged and int(damaged.group(1)) >= sent["garbage"] + sent["bit_flip"], summary
    assert "ignoring IMU messages from system 255" in log
    assert "saturated" in log and "accelerometer all zero" in log
