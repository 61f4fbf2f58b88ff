"""The replay's fast path against the one-record-at-a-time path and against pymavlink.

The fast path (mavest.mavlink.bulk, mavest.service.bulk) must give exactly what the
pipeline gives record by record: the same output tlog, byte for byte, the same
counters and comparisons. Its parts are checked against pymavlink on the same bytes:
record boundaries, decoded fields, packed ATTITUDE and ATTITUDE_QUATERNION.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import math
import os
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from test_hostile_input import CASES, Flight, _message_id, _repacked, _tlog_bytes, clean_flights

from mavest.estimator.config import STANDARD_GRAVITY
from mavest.evaluation.online import ESTIMATE, REFERENCE, EulerComparison
from mavest.mavlink import bulk, framing
from mavest.mavlink.clock import WRAP_TICKS, ClockEvent, StreamClock
from mavest.mavlink.messages import IMU_MESSAGES, MAVLink, decode_imu, mavlink2
from mavest.mavlink.tlog import TlogReader, TlogWriter
from mavest.service.config import ServiceConfig
from mavest.service.runners import Outputs, RunReport, format_summary, replay
from mavest.sim.vehicle import AUTOPILOTS, write_autopilot_tlog, write_flight_tlog

CONFIGS = Path(__file__).parent.parent / "configs"


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Flight]:
    return clean_flights(tmp_path_factory)


# ------------------------------------------------------------------ both paths


def _replay(path: Path, config: ServiceConfig, out: Path, fast: bool) -> RunReport:
    return asyncio.run(replay(path, config, Outputs(tlog=out), progress=False, fast=fast))


def _state(report: RunReport) -> dict[str, Any]:
    """Everything a replay leaves behind that is not a wall-clock time."""
    pipeline = report.pipeline
    summary = format_summary(report)
    summary = re.sub(r"messages in [\d.]+ s", "", summary)
    summary = re.sub(r"\([\d.]+ k samples/s\)", "", summary)
    summary = re.sub(r"wrote \S+", "", summary)
    return {
        "summary": summary,
        "messages_in": pipeline.messages_in,
        "sent": pipeline.sent,
        "bad_packets": pipeline.bad_packets,
        "ignored_imu": dict(pipeline.ignored_imu),
        "records": report.records,
        "streams": {
            str(key): (
                dataclasses.asdict(stream.stats),
                dataclasses.astuple(stream.vs_truth.result()),
                stream.vs_truth.unmatched,
                dataclasses.astuple(stream.vs_autopilot.result()),
                stream.vs_autopilot.unmatched,
                stream.estimator.q.tolist(),
                stream.estimator.cov.tolist(),
                stream.next_output,
                stream.primary,
            )
            for key, stream in pipeline.streams.items()
        },
        "vehicles": {
            key: (v.last_t, v.airspeed, v.airspeed_t, v.gps.accel, v.gps.accel_t, v.declination)
            for key, v in pipeline.vehicles.items()
        },
    }


def _assert_same_both_ways(path: Path, config: ServiceConfig, tmp_path: Path) -> RunReport:
    fast_out, slow_out = tmp_path / "fast.tlog", tmp_path / "slow.tlog"
    fast = _replay(path, config, fast_out, fast=True)
    slow = _replay(path, config, slow_out, fast=False)
    assert fast_out.read_bytes() == slow_out.read_bytes()
    assert _state(fast) == _state(slow)
    return fast


def _bulk_samples(report: RunReport) -> int:
    return sum(s.stats.estimated for s in report.pipeline.streams.values())


@pytest.mark.parametrize("case", list(CASES))
def test_damaged_replay_is_the_same_both_ways(
    case: str, flights: dict[str, Flight], tmp_path: Path
) -> None:
    flavour, make = CASES[case]
    damage = make(flights[flavour])
    path = tmp_path / "damaged.tlog"
    path.write_bytes(_tlog_bytes(damage.chunks))
    config = ServiceConfig()
    if damage.args:  # e.g. --system 1
        config = config.replace(input={"system": int(damage.args[-1])})
    _assert_same_both_ways(path, config, tmp_path)


@pytest.fixture(scope="module")
def turning_flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Clean 12 s flights at 400 Hz with GPS, airspeed and truth: ArduPilot and PX4."""
    out = {}
    for flavour in ("ardupilot", "px4"):
        path = tmp_path_factory.mktemp("turns") / f"{flavour}.tlog"
        write_flight_tlog(path, 12.0, 400.0, AUTOPILOTS[flavour], seed=3)
        out[flavour] = path
    return out


@pytest.mark.parametrize(
    ("flavour", "config_file", "changes"),
    [
        ("ardupilot", "ardupilot.toml", {}),
        ("ardupilot", "default.toml", {}),
        ("ardupilot", "ardupilot.toml", {"output": {"attitude_rate": 50.0}}),
        ("ardupilot", "ardupilot.toml", {"output": {"attitude_quaternion": False}}),
        ("ardupilot", "ardupilot.toml", {"input": {"acceleration_aiding": "airspeed"}}),
        ("ardupilot", "ardupilot.toml", {"input": {"acceleration_aiding": "off"}}),
        ("ardupilot", "ardupilot.toml", {"output": {"heartbeat_rate": 0.0}}),
        # our HEARTBEATs take sequence numbers among the answers packed at once: more
        # of them than answers, and from a system of our own
        (
            "ardupilot",
            "ardupilot.toml",
            {"output": {"heartbeat_rate": 50.0, "attitude_rate": 20.0}},
        ),
        ("ardupilot", "ardupilot.toml", {"output": {"system_id": 250}}),
        ("px4", "px4.toml", {}),
    ],
)
def test_clean_flight_is_the_same_both_ways(
    flavour: str,
    config_file: str,
    changes: dict[str, dict[str, Any]],
    turning_flights: dict[str, Path],
    tmp_path: Path,
) -> None:
    config = ServiceConfig.from_toml(CONFIGS / config_file)
    if changes:
        config = config.replace(**changes)
    report = _assert_same_both_ways(turning_flights[flavour], config, tmp_path)
    assert _bulk_samples(report) == 4801


@pytest.mark.parametrize(("first", "most"), [(1, 1), (5, 37), (3000, 3000)])
def test_parts_of_any_size_give_the_same_replay(
    first: int,
    most: int,
    turning_flights: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The filter's parts (small, growing, one sample) change nothing a replay gives."""
    from mavest.service import bulk as service_bulk

    config = ServiceConfig.from_toml(CONFIGS / "ardupilot.toml")
    monkeypatch.setattr(service_bulk, "_FIRST_PART", first)
    monkeypatch.setattr(service_bulk, "_PART", most)
    report = _assert_same_both_ways(turning_flights["ardupilot"], config, tmp_path)
    assert _bulk_samples(report) == 4801


@pytest.mark.parametrize("with_rrd", [False, True])
def test_most_samples_go_through_the_compiled_path(
    with_rrd: bool,
    turning_flights: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mavest.service import bulk as service_bulk

    feeds: list[service_bulk.BulkFeed] = []
    original = service_bulk.BulkFeed.__init__

    def remember(self: service_bulk.BulkFeed, *args: Any) -> None:
        original(self, *args)
        feeds.append(self)

    monkeypatch.setattr(service_bulk.BulkFeed, "__init__", remember)
    config = ServiceConfig.from_toml(CONFIGS / "ardupilot.toml")
    outputs = Outputs(tlog=tmp_path / "out.tlog", rrd=tmp_path / "out.rrd" if with_rrd else None)
    asyncio.run(replay(turning_flights["ardupilot"], config, outputs, progress=False))
    assert len(feeds) == 1
    # all but the first sample and those the airspeed correction needs one by one
    assert feeds[0].bulk_samples > 0.9 * 4801


def _heartbeat(system: int, component: int, mav_type: int, autopilot: int) -> bytes:
    mav = MAVLink(None, srcSystem=system, srcComponent=component)
    return mav.heartbeat_encode(mav_type, autopilot, 0, 0, mavlink2.MAV_STATE_ACTIVE).pack(mav)


# HEARTBEATs put into a flight (a fixed wing, system 1) now and then; how many of all
# the HEARTBEATs then go one at a time (the rest are taken in their place in bulk)
_HEARTBEATS = {
    "the vehicle's own again": (
        (1, 1, mavlink2.MAV_TYPE_FIXED_WING, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA),
        1,  # the first of the flight: a new vehicle
    ),
    "a ground station's": (
        (255, 190, mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID),
        1,
    ),
    "a second vehicle's": (
        (2, 1, mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA),
        2,  # and its first
    ),
    "the vehicle's, now a copter": (
        (1, 1, mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA),
        None,  # each, and the vehicle's own after it: airspeed aiding goes off and on
    ),
}


@pytest.mark.parametrize("sender", list(_HEARTBEATS))
def test_heartbeats_mid_flight_are_the_same_both_ways(
    sender: str, turning_flights: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mavest.service import bulk as service_bulk

    header, alone = _HEARTBEATS[sender]
    packet = _heartbeat(*header)
    records = []
    injected = 0
    for i, record in enumerate(TlogReader.open(turning_flights["ardupilot"], frozenset())):
        records.append((record.timestamp_us, record.packet))
        if i % 997 == 500:
            records.append((record.timestamp_us, packet))
            injected += 1
    path = tmp_path / "beats.tlog"
    path.write_bytes(_tlog_bytes(records))
    beats_alone = 0
    original = service_bulk.BulkFeed._alone

    def count(self: service_bulk.BulkFeed, index: framing.RecordIndex, row: int) -> None:
        nonlocal beats_alone
        beats_alone += int(index.message_id[row]) == mavlink2.MAVLINK_MSG_ID_HEARTBEAT
        original(self, index, row)

    monkeypatch.setattr(service_bulk.BulkFeed, "_alone", count)
    config = ServiceConfig.from_toml(CONFIGS / "ardupilot.toml")
    report = _assert_same_both_ways(path, config, tmp_path)
    assert injected >= 8 and _bulk_samples(report) == 4801
    if alone is not None:
        assert beats_alone == alone
    else:
        assert beats_alone > 2 * injected
        assert 0 < report.streams[0].stats.airspeed_aided < 4801


def test_heartbeats_go_on_after_the_recording_clock_is_set_back(
    turning_flights: dict[str, Path], tmp_path: Path
) -> None:
    """A recording clock set back a day mid-log (a ground station's clock corrected):
    mavest's HEARTBEATs go on at their rate from there, the same both ways, instead of
    waiting a day of record time for the clock to come back."""
    records = [
        (r.timestamp_us, r.packet)
        for r in TlogReader.open(turning_flights["ardupilot"], frozenset())
    ]
    half = len(records) // 2
    day_us = 86_400 * 10**6
    shifted = records[:half] + [(stamp - day_us, packet) for stamp, packet in records[half:]]
    path = tmp_path / "set_back.tlog"
    path.write_bytes(_tlog_bytes(shifted))
    _assert_same_both_ways(path, ServiceConfig(), tmp_path)
    jump_us = shifted[half][0]
    ours = [
        record.timestamp_us
        for record in TlogReader.open(tmp_path / "fast.tlog", frozenset({0}))
        if record.message is not None and record.message.get_srcComponent() == 191
    ]
    after = [stamp for stamp in ours if stamp >= jump_us and stamp < jump_us + day_us // 2]
    seconds_after = (shifted[-1][0] - jump_us) * 1e-6  # (about 6 s at 1 Hz)
    assert len(after) >= seconds_after - 1, (len(after), seconds_after)
    assert len(ours) - len(after) >= seconds_after - 1  # and before it, as ever


def _shared_tlogs() -> list[Path]:
    root = Path(os.environ.get("MAVEST_DATA", Path(__file__).parents[2] / "shared" / "data"))
    return sorted((root / "tlogs").glob("*.tlog"))


@pytest.mark.skipif(not _shared_tlogs(), reason="no tlogs in $MAVEST_DATA/tlogs (shared data)")
@pytest.mark.parametrize("path", _shared_tlogs(), ids=lambda p: p.name)
def test_real_tlogs_are_the_same_both_ways(path: Path, tmp_path: Path) -> None:
    _assert_same_both_ways(path, ServiceConfig(), tmp_path)


# ------------------------------------------------------------------ the autopilot's ATTITUDE

_ATTITUDE = mavlink2.MAVLINK_MSG_ID_ATTITUDE
_RAW_IMU = mavlink2.MAVLINK_MSG_ID_RAW_IMU


@pytest.fixture(scope="module")
def autopilot_log(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[int, bytes]]:
    """What an autopilot logs, 4 s at 500 Hz: HEARTBEAT, RAW_IMU and its own ATTITUDE
    after every 10th sample; as records."""
    path = tmp_path_factory.mktemp("autopilot") / "autopilot.tlog"
    write_autopilot_tlog(path, 4.0, 500.0, attitude_every=10)
    return [(r.timestamp_us, r.packet) for r in TlogReader.open(path, frozenset())]


def _shifted(packet: bytes, **offsets: int) -> bytes:
    """The packet with these fields moved by these amounts."""
    message = MAVLink(None).decode(bytearray(packet))
    return _repacked(packet, **{name: getattr(message, name) + d for name, d in offsets.items()})


def _before_any_estimate(records: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    """ATTITUDE before the first IMU sample, and while the stream's first 40 samples are
    rejected (no acceleration): before the stream has an estimate."""
    out = [(records[0][0], p) for _, p in records if _message_id(p) == _ATTITUDE][:3]
    rejected = 0
    for stamp, packet in records:
        if _message_id(packet) == _RAW_IMU and rejected < 40:
            packet = _repacked(packet, xacc=0, yacc=0, zacc=0)
            rejected += 1
        out.append((stamp, packet))
    return out


def _two_vehicles_and_a_ground_station(
    records: list[tuple[int, bytes]],
) -> list[tuple[int, bytes]]:
    """Each record again from a second vehicle (system 2) right after it, and the
    ATTITUDE again from a ground station, which is no vehicle."""
    out = []
    for stamp, packet in records:
        out.append((stamp, packet))
        out.append((stamp, _repacked(packet, system=2)))
        if _message_id(packet) == _ATTITUDE:
            out.append((stamp, _repacked(packet, system=255)))
    return out


def _some_from_before_a_restart(records: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    """The IMU's time 100 s on, and the ATTITUDE's but for every third: those were sent
    before the autopilot restarted (more than a minute behind), so not compared."""
    out = []
    attitudes = 0
    for stamp, packet in records:
        if _message_id(packet) == _RAW_IMU:
            packet = _shifted(packet, time_usec=100_000_000)
        elif _message_id(packet) == _ATTITUDE:
            if attitudes % 3:
                packet = _shifted(packet, time_boot_ms=100_000)
            attitudes += 1
        out.append((stamp, packet))
    return out


_ATTITUDE_CASES = {
    "as logged": lambda records: records,
    "before any estimate": _before_any_estimate,
    "two vehicles and a ground station": _two_vehicles_and_a_ground_station,
    "some from before a restart": _some_from_before_a_restart,
}


@pytest.mark.parametrize("case", list(_ATTITUDE_CASES))
def test_the_autopilots_attitude_is_compared_the_same_both_ways(
    case: str, autopilot_log: list[tuple[int, bytes]], tmp_path: Path
) -> None:
    records = _ATTITUDE_CASES[case](autopilot_log)
    path = tmp_path / "autopilot.tlog"
    path.write_bytes(_tlog_bytes(records))
    config = ServiceConfig().replace(input={"settle_time": 1.0})
    report = _assert_same_both_ways(path, config, tmp_path)
    compared = [s.vs_autopilot.count for s in report.pipeline.streams.values()]
    assert all(compared) and len(compared) == (2 if "two" in case else 1)
    attitudes = sum(_message_id(p) == _ATTITUDE for _, p in autopilot_log)
    if case == "some from before a restart":
        # those of the last 3 s (after the settling second), but for every third
        assert compared[0] == pytest.approx(2 / 3 * 3 / 4 * attitudes, abs=2)


def test_the_autopilots_attitude_goes_in_bulk(
    autopilot_log: list[tuple[int, bytes]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once a stream is known, the autopilot's ATTITUDE is taken with the estimates in
    bulk, not one message at a time."""
    from mavest.service.pipeline import Pipeline

    path = tmp_path / "autopilot.tlog"
    path.write_bytes(_tlog_bytes(autopilot_log))
    alone: list[str] = []
    original = Pipeline.on_message

    def count(self: Pipeline, message: Any, timestamp_us: int) -> None:
        alone.append(message._type)
        original(self, message, timestamp_us)

    monkeypatch.setattr(Pipeline, "on_message", count)
    config = ServiceConfig().replace(input={"settle_time": 1.0})
    report = _replay(path, config, tmp_path / "out.tlog", fast=True)
    assert "ATTITUDE" not in alone
    assert [s.vs_autopilot.count for s in report.pipeline.streams.values()] == [151]


# ------------------------------------------------------------------ the rules, once


def _within(v: tuple[float, float, float], limit: float) -> bool:
    return all(-limit <= x <= limit for x in v)  # (chained: a NaN fails both)


def test_sample_rules_decide_alike_on_one_sample_and_on_columns() -> None:
    """The pipeline's sample rules take one sample (numbers) live and a block (columns)
    in replay: each way the same verdicts as a plain statement of the rule, a bool for
    one sample; NaN, infinities, -0.0 and values at and just past the limits among them."""
    from mavest.service.pipeline import (
        MAX_ACCEL,
        MAX_GYRO,
        MAX_MAG,
        MAX_TIME,
        usable_mag,
        valid_sample,
    )

    values = [0.0, -0.0, 1.0, -MAX_GYRO, MAX_GYRO, math.nextafter(MAX_GYRO, math.inf)]
    values += [MAX_ACCEL, -math.nextafter(MAX_ACCEL, math.inf), MAX_MAG, 1e9]
    values += [math.inf, -math.inf, math.nan]
    rng = random.Random(2)

    def axes() -> tuple[float, float, float]:  # mostly plain readings, a third odd
        return tuple(  # type: ignore[return-value]
            rng.choice(values) if rng.random() < 0.3 else rng.uniform(-20.0, 20.0) for _ in range(3)
        )

    times = [0.0, 1e3, 1.7e9, math.nextafter(MAX_TIME, 0.0), MAX_TIME, 1.8e13]
    samples = [(axes(), axes(), axes(), rng.random() < 0.1, rng.choice(times)) for _ in range(5000)]
    expected_valid, expected_mag = [], []
    for gyro, accel, mag, saturated, time in samples:
        expected_valid.append(
            _within(gyro, MAX_GYRO)
            and _within(accel, MAX_ACCEL)
            and not saturated
            and accel != (0.0, 0.0, 0.0)
            and time < MAX_TIME
        )
        expected_mag.append(mag != (0.0, 0.0, 0.0) and _within(mag, MAX_MAG))
        one = valid_sample(gyro, accel, saturated, time)
        assert type(one) is bool and one == expected_valid[-1]
        one = usable_mag(mag)
        assert type(one) is bool and one == expected_mag[-1]
    assert 0.05 * len(samples) < sum(expected_valid) < 0.95 * len(samples)
    gyro, accel, mag = (np.array([s[k] for s in samples]) for k in range(3))
    saturated, time = (np.array([s[k] for s in samples]) for k in (3, 4))
    block = valid_sample(tuple(gyro.T), tuple(accel.T), saturated, time)
    assert block.tolist() == expected_valid
    assert usable_mag(tuple(mag.T)).tolist() == expected_mag


def test_step_counts_and_news_alike_on_one_step_and_on_a_block() -> None:
    """count_estimated, is_news and heading_source_due take one step live and a block in
    replay: each way what a plain statement of the rule gives."""
    from mavest.estimator.layout import StepFlags
    from mavest.service.pipeline import (
        MAG_WAIT,
        Stream,
        StreamStats,
        count_estimated,
        heading_source_due,
        is_news,
    )

    bits = [value for name, value in vars(StepFlags).items() if name.isupper()]
    bits = [value for value in bits if value & (value - 1) == 0]  # (one bit each)
    rng = random.Random(5)
    flags = [sum({rng.choice(bits) for _ in range(rng.randrange(4))}) for _ in range(3000)]
    flags = [f | StepFlags.ACCEL_AIDED if rng.random() < 0.2 else f for f in flags]
    usable = [rng.random() < 0.6 for _ in flags]
    used = [rng.random() < 0.5 for _ in flags]

    def taken(f: int, u: bool) -> bool:
        not_taken = StepFlags.MAG_BETWEEN_UPDATES | StepFlags.MAG_SET_ASIDE
        return u and not f & (not_taken | StepFlags.NOT_INITIALISED)

    expected = StreamStats(
        estimated=len(flags),
        not_started=sum(bool(f & StepFlags.NOT_INITIALISED) for f in flags),
        gps_aided=sum(bool(f & StepFlags.ACCEL_AIDED) for f in flags),
        mag_usable=sum(usable),
        mag_taken=sum(taken(f, u) for f, u in zip(flags, usable, strict=True)),
        mag_used=sum(taken(f, u) and m for f, u, m in zip(flags, usable, used, strict=True)),
        updates=sum(not f & (StepFlags.BETWEEN_UPDATES | StepFlags.NOT_INITIALISED) for f in flags),
        accel_far_from_g=sum(
            bool(f & StepFlags.ACCEL_REJECTED_NORM)
            and not f & (StepFlags.BETWEEN_UPDATES | StepFlags.NOT_INITIALISED)
            for f in flags
        ),
    )
    one_by_one = StreamStats()
    for f, u, m in zip(flags, usable, used, strict=True):
        count_estimated(one_by_one, f, u, m)
    block = StreamStats()
    count_estimated(block, np.array(flags), np.array(usable), np.array(used))
    assert one_by_one == expected and block == expected
    assert expected.mag_taken < expected.mag_usable and expected.mag_used > 0

    news = StepFlags.GAP_REALIGNED | StepFlags.TILT_REOPENED | StepFlags.DIVERGED
    news |= StepFlags.UNHEALTHY_RESET | StepFlags.CLIP_REALIGNED | StepFlags.HEADING_ALIGNED
    news |= StepFlags.HEADING_REOPENED | StepFlags.MAG_REFERENCE_CHANGED
    expected_news = [bool(f & news) for f in flags]
    assert [is_news(f) for f in flags] == expected_news
    assert is_news(np.array(flags)).tolist() == expected_news
    assert 0 < sum(expected_news) < len(flags)

    stream = Stream(None, None)  # type: ignore[arg-type]  (only its flag is read)
    spans = [0.0, MAG_WAIT / 2, math.nextafter(MAG_WAIT, 0.0), MAG_WAIT, 10.0, math.nan]
    for said in (False, True):
        stream.heading_source_reported = said
        due = [not said and span >= MAG_WAIT for span in spans]
        assert [bool(heading_source_due(stream, span)) for span in spans] == due
        assert heading_source_due(stream, np.array(spans)).tolist() == due


def test_imu_routes_in_the_pipelines_order() -> None:
    """route_imu: a system not followed is ignored before anything else; a stale sample
    is passed by; a known stream estimates; a declined one passes by; else it is new."""
    from mavest.mavlink.messages import StreamKey
    from mavest.service.pipeline import ImuRoute, Pipeline

    pipeline = Pipeline(ServiceConfig())
    ground = StreamKey(255, 190, "RAW_IMU", 0)
    key = StreamKey(1, 1, "RAW_IMU", 0)
    assert pipeline.route_imu(ground, True) == (ImuRoute.IGNORED, None)
    assert pipeline.route_imu(ground, False) == (ImuRoute.IGNORED, None)
    assert pipeline.route_imu(key, True) == (ImuRoute.NEW, None)
    assert pipeline.route_imu(key, False) == (ImuRoute.PASSED_BY, None)
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    raw = mav.raw_imu_encode(1000, 0, 0, -1000, 0, 0, 0, 200, 0, 400, 0, 3500)
    pipeline.on_message(mavlink2.MAVLink(None).decode(bytearray(raw.pack(mav))), 0)
    stream = pipeline.streams[key]
    assert pipeline.route_imu(key, True) == (ImuRoute.ESTIMATED, stream)
    assert pipeline.route_imu(key, False) == (ImuRoute.PASSED_BY, None)
    scaled = StreamKey(1, 1, "SCALED_IMU2", 1)  # RAW_IMU is preferred: declined
    assert pipeline.route_imu(scaled, True) == (ImuRoute.NEW, None)
    pipeline.on_message(
        mavlink2.MAVLink(None).decode(
            bytearray(mav.scaled_imu2_encode(1000, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(mav))
        ),
        0,
    )
    assert scaled not in pipeline.streams
    assert pipeline.route_imu(scaled, True) == (ImuRoute.PASSED_BY, None)


# ------------------------------------------------------------------ decoding


def test_wire_types_are_pymavlink_layouts() -> None:
    rng = np.random.default_rng(0)
    for message_class in mavlink2.mavlink_map.values():
        dtype = bulk.wire_dtype(message_class)
        raw = rng.integers(0, 256, size=dtype.itemsize, dtype=np.uint8)
        ours = raw.view(dtype)[0]
        theirs = list(message_class.unpacker.unpack(raw.tobytes()))
        for name, length in zip(
            message_class.ordered_fieldnames, message_class.array_lengths, strict=True
        ):
            value = ours[name]
            if value.dtype.kind == "S":  # a string: one item in struct's tuple
                expected = theirs.pop(0)
                assert value == expected.rstrip(b"\0") or length == 0
                continue
            count = length if length else 1
            expected_values = [theirs.pop(0) for _ in range(count)]
            assert np.array_equal(
                np.atleast_1d(value), np.array(expected_values, dtype=value.dtype), equal_nan=True
            ), (message_class.msgname, name)
        assert not theirs


def _imu_packets(name: str, count: int, seed: int) -> list[bytes]:
    """Packets of ``name`` with random field values, MAVLink 1 and 2 mixed."""
    rng = random.Random(seed)
    message_class = mavlink2.mavlink_map[getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")]
    packets = []
    for i in range(count):
        values = []
        for field_name, field_type in zip(
            message_class.fieldnames, message_class.fieldtypes, strict=True
        ):
            if field_type == "float":
                value: Any = rng.choice([0.0, rng.uniform(-30, 30), rng.uniform(-1e3, 1e3)])
            elif field_type.startswith("int"):
                bits = int(field_type[3:-2])
                value = rng.choice([0, -(1 << (bits - 1)), (1 << (bits - 1)) - 1])
                value = rng.choice([value, rng.randrange(-(1 << (bits - 1)), 1 << (bits - 1))])
            else:
                bits = int(field_type[4:-2])
                value = rng.randrange(0, 1 << min(bits, 40))
            if field_name == "fields_updated":
                value = rng.choice([0xFFFF, 0x3F, 0x1FF, 0x1F, rng.randrange(0, 1 << 16)])
            values.append(value)
        mav = MAVLink(None, srcSystem=1, srcComponent=1)
        message = message_class(*values)
        packets.append(message.pack(mav, force_mavlink1=bool(i % 3 == 0)))
    return packets


@pytest.mark.parametrize("name", IMU_MESSAGES)
def test_imu_fields_equal_decode_imu(name: str) -> None:
    packets = _imu_packets(name, 300, seed=len(name))
    data = b"".join((10**6 + i).to_bytes(8, "big") + p for i, p in enumerate(packets))
    array = np.frombuffer(data, dtype=np.uint8)
    index = framing.scan(array, 0, -1, 1000)
    assert len(index) == len(packets)
    message_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")
    fields = bulk.imu_fields(
        name, bulk.decode_payloads(array, index, bulk.wire_dtype(mavlink2.mavlink_map[message_id]))
    )
    for i, packet in enumerate(packets):
        sample = decode_imu(MAVLink(None).decode(bytearray(packet)))
        assert fields.inertial_fresh[i] == (sample is not None)
        if sample is None:
            continue
        assert fields.ticks[i] == sample.ticks
        assert tuple(fields.gyro[i]) == sample.gyro
        assert tuple(fields.accel[i]) == sample.accel
        assert fields.mag_fresh[i] == (sample.mag is not None)
        if sample.mag is not None:
            assert tuple(fields.mag[i]) == sample.mag
        assert fields.instance[i] == sample.stream.instance
        assert fields.saturated[i] == sample.saturated


@pytest.mark.parametrize("name", ["GPS_RAW_INT", "GLOBAL_POSITION_INT", "VFR_HUD"])
def test_aiding_fields_equal_pymavlink(name: str) -> None:
    """The GPS and airspeed fields the fast path follows, decoded in bulk, against
    pymavlink's messages of the same packets (MAVLink 1 and 2, trailing zeros cut)."""
    from mavest.service import bulk as service_bulk
    from mavest.service.pipeline import AIDING_FIELDS, AidingFields
    from mavest.service.runners import REPLAY_MESSAGES

    packets = _imu_packets(name, 300, seed=len(name))
    data = b"".join((10**6 + i).to_bytes(8, "big") + p for i, p in enumerate(packets))
    array = np.frombuffer(data, dtype=np.uint8)
    index = framing.scan(array, 0, -1, 1000)
    assert len(index) == len(packets)
    decoded = service_bulk._Decoded(array, index, service_bulk.record_kinds(REPLAY_MESSAGES))
    fields = {
        "GPS_RAW_INT": ["fix_type"],
        "GLOBAL_POSITION_INT": ["vx", "vy", "vz", "time_boot_ms"],
        "VFR_HUD": ["airspeed"],
    }[name]
    assert list(AIDING_FIELDS[name]) == fields
    for i, packet in enumerate(packets):
        message = MAVLink(None).decode(bytearray(packet))
        for field in fields:
            assert decoded.aiding[field][i] == getattr(message, field), field
        assert AidingFields.of(message) == AidingFields(
            message.get_msgId(), **{field: decoded.aiding[field][i].item() for field in fields}
        )


# ------------------------------------------------------------------ encoding


@pytest.mark.parametrize("mixed_versions", [False, True])
@pytest.mark.parametrize("with_quaternion", [True, False])
def test_attitude_packets_are_pymavlink_packets(
    with_quaternion: bool, mixed_versions: bool
) -> None:
    rng = np.random.default_rng(7)
    n = 600
    stamps = rng.integers(0, 1 << 32, n)
    euler = rng.uniform(-math.pi, math.pi, (n, 3))
    rates = rng.normal(0.0, 1.0, (n, 3))
    q = rng.normal(size=(n, 4))
    # zeros at the end of a payload are cut in MAVLink 2: some rows end in zeros
    rates[::5] = 0.0
    euler[::10, 2] = 0.0
    q[::7, 3] = 0.0
    # MAVLink 1 rows (samples that came as MAVLink 1) as the MAVLink 1 dialect packs them
    version1 = rng.random(n) < 0.5 if mixed_versions else np.zeros(n, dtype=bool)
    mav = MAVLink(None, srcSystem=42, srcComponent=191)
    mav1 = mavlink1.MAVLink(None, srcSystem=42, srcComponent=191)
    mav.seq = 200  # the sequence number wraps inside the batch

    def pymavlinks(encode: str, *fields: Any, v1: bool) -> bytes:
        packer = mav1 if v1 else mav
        packer.seq = mav.seq
        packet = getattr(packer, encode)(*fields).pack(packer)
        mav.seq = (mav.seq + 1) % 256
        return packet

    first, second = bulk.attitude_packets(
        stamps, euler, rates, q if with_quaternion else None, 42, 191, 200, version1
    )
    for i in range(n):
        stamp, rate, v1 = int(stamps[i]), [float(r) for r in rates[i]], bool(version1[i])
        expected = pymavlinks("attitude_encode", stamp, *map(float, euler[i]), *rate, v1=v1)
        assert first.data[i, : first.length[i]].tobytes() == expected
        if with_quaternion:
            assert second is not None
            fields = (stamp, *map(float, q[i]), *rate)
            expected = pymavlinks("attitude_quaternion_encode", *fields, v1=v1)
            assert second.data[i, : second.length[i]].tobytes() == expected
        else:
            assert second is None


# ------------------------------------------------------------------ clock and comparison


@pytest.mark.parametrize("seed", range(6))
def test_clock_run_equals_reading_one_by_one(seed: int) -> None:
    rng = random.Random(seed)
    ticks = [rng.randrange(0, 10**6)]
    for _ in range(3000):
        step = rng.choice([1000] * 40 + [1001, 999, 0, -5, 9000, 80000, -700000, 10**9])
        ticks.append(ticks[-1] + step)
    ticks = [t % WRAP_TICKS if rng.random() < 0.999 else t for t in ticks]
    tick = 1e-6
    one, run = StreamClock(), StreamClock()
    i = 0
    while i < len(ticks):
        times = run.read_run(np.array(ticks[i:], dtype=np.int64), tick)
        count = len(times)
        if count:
            run.take_run(np.array(ticks[i : i + count], dtype=np.int64), tick, count)
            for k in range(count):
                reading = one.read(ticks[i + k], tick)
                assert reading.event is ClockEvent.NEXT and reading.t == times[k]
            i += count
        else:
            reading = one.read(ticks[i], tick)
            assert reading == run.read(ticks[i], tick)
            # a plain next sample the run would have taken; a confirmed jump it leaves
            assert reading.event is not ClockEvent.NEXT or reading.dt > run.max_jump
            i += 1
        assert run.period == one.period


def _reference_comparison(
    items: list[tuple[int, float, tuple[float, float, float]]],
    settle: float,
    history: int,
    max_span: float,
) -> tuple[int, list[float], int]:
    """EulerComparison's rules written plainly: lists, no rings, no compiled code."""
    ours: list[tuple[float, tuple[float, float, float]]] = []
    pending: list[tuple[float, tuple[float, float, float]]] = []
    start = None
    sums = [0.0] * 4
    count = unmatched = 0

    def wrap(a: float) -> float:
        return (a + math.pi) % (2 * math.pi) - math.pi

    def resolve(t: float, ref: tuple[float, float, float]) -> None:
        nonlocal count, unmatched
        window = ours[-history:]
        if start is None or not window or t < window[0][0]:
            unmatched += 1
            return
        after = next(i for i, (te, _) in enumerate(window) if te >= t or i == len(window) - 1)
        t1, e1 = window[after]
        if after == 0 or t1 == t:
            est = e1
        else:
            t0, e0 = window[after - 1]
            if t1 - t0 > max_span:
                unmatched += 1
                return
            w = (t - t0) / (t1 - t0)
            est = (
                e0[0] + w * wrap(e1[0] - e0[0]),
                e0[1] + w * (e1[1] - e0[1]),
                e0[2] + w * wrap(e1[2] - e0[2]),
            )
        if t - start < settle:
            return
        down_a = (-math.sin(est[1]), math.sin(est[0]) * math.cos(est[1]))
        down_a += (math.cos(est[0]) * math.cos(est[1]),)
        down_b = (-math.sin(ref[1]), math.sin(ref[0]) * math.cos(ref[1]))
        down_b += (math.cos(ref[0]) * math.cos(ref[1]),)
        dot = sum(a * b for a, b in zip(down_a, down_b, strict=True))
        sums[0] += wrap(est[0] - ref[0]) ** 2
        sums[1] += (est[1] - ref[1]) ** 2
        sums[2] += math.acos(max(-1.0, min(1.0, dot))) ** 2
        sums[3] += wrap(est[2] - ref[2]) ** 2
        count += 1

    for kind, t, euler in items:
        if kind == ESTIMATE:
            if start is None:
                start = t
            if ours and t <= ours[-1][0]:
                continue
            ours.append((t, euler))
            while pending and pending[0][0] <= t:
                resolve(*pending.pop(0))
        elif ours and t <= ours[-1][0]:
            resolve(t, euler)
        else:
            pending.append((t, euler))
            if len(pending) > 64:
                pending.pop(0)
                unmatched += 1
    return count, sums, unmatched


@pytest.mark.parametrize("seed", range(8))
def test_comparison_follows_its_rules_one_by_one_and_in_bulk(seed: int) -> None:
    rng = np.random.default_rng(seed)
    history = int(rng.integers(3, 40))
    items = []
    t = 0.0
    for _ in range(2500):
        if rng.random() < 0.5:
            t += float(rng.exponential(0.01)) * (1 if rng.random() > 0.05 else -1)
            items.append((ESTIMATE, t, tuple(rng.uniform(-3.2, 3.2, 3).tolist())))
        else:
            items.append((REFERENCE, t + float(rng.normal(0, 0.03)), tuple(rng.uniform(-3, 3, 3))))
    count, sums, unmatched = _reference_comparison(items, 0.5, history, 0.05)
    one = EulerComparison(0.5, history, 0.05)
    for kind, ti, euler in items:
        (one.add_estimate if kind == ESTIMATE else one.add_reference)(ti, euler)
    many = EulerComparison(0.5, history, 0.05)
    kinds = np.array([k for k, _, _ in items], dtype=np.int64)
    times = np.array([ti for _, ti, _ in items])
    eulers = np.array([e for _, _, e in items])
    for part in np.array_split(np.arange(len(items)), 7):
        many.add_many(kinds[part], times[part], eulers[part])
    n = max(count, 1)
    expected = [math.degrees(math.sqrt(s / n)) for s in sums]
    for comparison in (one, many):
        result = comparison.result()
        assert (result.count, comparison.unmatched) == (count, unmatched)
        values = [result.roll_rms, result.pitch_rms, result.inclination_rms, result.yaw_rms]
        assert values == pytest.approx(expected, rel=1e-12)
    assert dataclasses.astuple(one.result()) == dataclasses.astuple(many.result())


# ------------------------------------------------------------------ a recording


def test_a_recording_holds_the_same_both_ways(
    turning_flights: dict[str, Path], tmp_path: Path
) -> None:
    config = ServiceConfig.from_toml(CONFIGS / "ardupilot.toml")
    _assert_same_recording_both_ways(turning_flights["ardupilot"], config, tmp_path)


def test_a_recording_with_two_autopilots_attitude_holds_the_same_both_ways(
    autopilot_log: list[tuple[int, bytes]], tmp_path: Path
) -> None:
    path = tmp_path / "autopilot.tlog"
    path.write_bytes(_tlog_bytes(_two_vehicles_and_a_ground_station(autopilot_log)))
    config = ServiceConfig().replace(input={"settle_time": 1.0})
    recordings = _assert_same_recording_both_ways(path, config, tmp_path)
    assert any(entity.endswith("vs_autopilot") for entity in recordings)


def _assert_same_recording_both_ways(
    path: Path, config: ServiceConfig, tmp_path: Path
) -> dict[str, Any]:
    from test_rerun import _scalars

    recordings = {}
    for fast in (True, False):
        rrd = tmp_path / f"{fast}.rrd"
        outputs = Outputs(tlog=tmp_path / f"{fast}.tlog", rrd=rrd)
        asyncio.run(replay(path, config, outputs, progress=False, fast=fast))
        recordings[fast] = _scalars(rrd)
    assert (tmp_path / "True.tlog").read_bytes() == (tmp_path / "False.tlog").read_bytes()
    fast, one_by_one = recordings[True], recordings[False]
    assert fast.keys() == one_by_one.keys()
    for entity, (t, values, receive) in one_by_one.items():
        if entity.endswith("processing_us"):  # a time measured, not a result
            continue
        assert np.array_equal(fast[entity][0], t), entity
        assert np.allclose(fast[entity][1], values, rtol=0, atol=1e-9, equal_nan=True), entity
        assert fast[entity][2] == receive, entity
    return fast


@pytest.mark.parametrize("free", [0, 70_000, 150_001, 10**7])
def test_records_written_in_bulk_end_at_a_whole_record_on_a_full_disk(
    free: int, flights: dict[str, Flight], tmp_path: Path
) -> None:
    """Runs of records at once (from the array, past the writer's buffer) and one at a
    time, mixed, on a disk that fills up: the file is the start of what was written,
    cut after a whole record, and the writer counts the records on it."""
    from test_faults import _SmallDisk  # (a module of heavy imports: only here)

    records = flights["ardupilot"].records * 3
    data = _tlog_bytes(records)
    array = np.frombuffer(data, dtype=np.uint8)
    index = framing.scan(array, 0, -1, 1 << 20)
    assert len(index) == len(records)
    path = tmp_path / "out.tlog"
    writer = TlogWriter(path)
    writer._file = _SmallDisk(writer._file, free)  # type: ignore[assignment]
    position = 0
    for size in itertools.cycle([1, 3000, 17, 1]):  # small runs, and ones past the buffer
        if position >= len(records):
            break
        part = index.part(slice(position, position + size))
        if size == 1:
            writer.write(int(part.stamp[0]), data[int(part.start[0]) + 8 : int(part.end[0])])
        else:
            run = array[int(part.start[0]) : int(part.end[-1])]
            writer.write_records(run, part.end - part.start[0])
        position += size
    writer.close()
    written = path.read_bytes()
    assert data.startswith(written)
    ends = [0, *(index.end - index.start[0]).tolist()]
    assert len(written) in ends and written == data[: ends[writer.records]]
    assert (writer.error is None) == (free >= len(data))
    assert len(written) <= free


@pytest.mark.parametrize("fast", [True, False], ids=["bulk", "one-by-one"])
def test_an_autopilot_attitude_that_is_no_angle_is_not_compared(tmp_path: Path, fast: bool) -> None:
    # a vehicle's ATTITUDE of NaN, infinity or 1e30 rad made the comparison NaN (or its
    # RMS absurd) and, into a recording, printed NumPy's warnings; it is passed over
    import warnings

    flight = tmp_path / "flight.tlog"
    write_autopilot_tlog(flight, 30.0, 200.0, seed=4)
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    spoilt = tmp_path / "spoilt.tlog"
    writer = TlogWriter(spoilt)
    bad = (math.nan, math.inf, -math.inf, 1e30)
    count = 0
    for record in TlogReader.open(flight):
        writer.write(record.timestamp_us, record.packet)
        if record.message is not None and record.message.get_type() == "ATTITUDE":
            x = bad[count % len(bad)]
            count += 1
            m = record.message
            packet = encoder.attitude_encode(m.time_boot_ms, x, x, x, 0.0, 0.0, 0.0)
            writer.write(record.timestamp_us, packet.pack(encoder))
    writer.close()
    assert count > 100
    clean = asyncio.run(replay(flight, ServiceConfig(), fast=fast))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = asyncio.run(
            replay(spoilt, ServiceConfig(), Outputs(rrd=tmp_path / "o.rrd"), fast=fast)
        )
    (ours,), (theirs,) = report.streams, clean.streams
    assert ours.vs_autopilot.result() == theirs.vs_autopilot.result()
    assert ours.vs_autopilot.references == theirs.vs_autopilot.references


@pytest.mark.parametrize("fast", [True, False], ids=["bulk", "one-by-one"])
def test_a_time_no_clock_reads_is_a_rejected_sample(
    tmp_path: Path, fast: bool, caplog: pytest.LogCaptureFixture
) -> None:
    # time_usec from 1e16 (317 years): estimated, its rows were lost from the recording
    # (Rerun's time is int64 nanoseconds) with NumPy's and Rerun's warnings printed
    import warnings

    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "far.tlog"
    writer = TlogWriter(path)
    for k in range(400):
        stamp = 1_700_000_000_000_000 + 5000 * k
        packet = encoder.raw_imu_encode(10**16 + 5000 * k, 0, 0, -1000, 1, -2, 3, 0, 0, 0)
        writer.write(stamp, packet.pack(encoder))
    writer.close()
    with warnings.catch_warnings(), caplog.at_level("WARNING", logger="mavest"):
        warnings.simplefilter("error")
        config = ServiceConfig().replace(input={"imu": "RAW_IMU"})
        report = asyncio.run(replay(path, config, Outputs(rrd=tmp_path / "o.rrd"), fast=fast))
    (stream,) = report.streams
    assert stream.stats.estimated == 0 and stream.stats.rejected == 400
    # (the start of the line: a run's repeat limiter may add a count of held lines)
    said = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(
        f"{stream.key}: sample rejected, its time beyond 9e+09 s (285 years): no clock's "
        "(all such are counted as rejected)"
    )


@pytest.mark.parametrize("fast", [True, False], ids=["bulk", "one-by-one"])
@pytest.mark.parametrize(("one_g", "unit"), [(1000.0, "mg"), (9806.65, "mm/s²")])
def test_an_accelerometer_in_another_unit_is_named(
    tmp_path: Path, fast: bool, one_g: float, unit: str, caplog: pytest.LogCaptureFixture
) -> None:
    """HIGHRES_IMU is in m/s²: a sender's accelerometer in mg or mm/s² reads 1000 or 9807
    at rest, beyond any sensor's range, and the line rejecting it names the unit."""
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "highres.tlog"
    writer = TlogWriter(path)
    rng = np.random.default_rng(5)
    for k in range(400):
        accel = np.array([0.0, 0.0, -one_g]) + rng.normal(0.0, 0.02 * one_g, 3)
        packet = encoder.highres_imu_encode(
            5000 * k, *accel, 0.01, -0.02, 0.03, 0.2, 0.0, 0.4, 1000.0, 0.0, 0.0, 20.0, 0x1FFF
        )
        writer.write(1_700_000_000_000_000 + 5000 * k, packet.pack(encoder))
    writer.close()
    with caplog.at_level("WARNING", logger="mavest"):
        config = ServiceConfig().replace(input={"imu": "HIGHRES_IMU"})
        report = asyncio.run(replay(path, config, Outputs(), fast=fast))
    (stream,) = report.streams
    assert stream.stats.estimated == 0 and stream.stats.rejected == 400
    said = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(
        f"{stream.key}: sample rejected, accelerometer beyond any sensor's range: looks "
        f"like {unit}, mavest wants m/s² (multiply by {STANDARD_GRAVITY / one_g:.6g})"
    ), said


@pytest.mark.parametrize("fast", [True, False], ids=["bulk", "one-by-one"])
def test_samples_dropped_as_repeated_or_late_are_said_once(
    tmp_path: Path, fast: bool, caplog: pytest.LogCaptureFixture
) -> None:
    # (counted in the summary only: two vehicles sharing an id were followed as one,
    # the answers drifting to the other's attitude, without a word while it ran)
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [
        encoder.raw_imu_encode(1_000_000 + 5000 * k, 0, 0, -1000, 1, -2, 3, 0, 0, 0).pack(encoder)
        for k in range(2000)
    ]
    order: list[int] = []
    for k in range(2000):
        order.append(k)
        if k % 10 == 9:
            order.append(k)  # the same again
        if k % 50 == 49:
            order.append(k - 3)  # one late
    path = tmp_path / "repeats.tlog"
    writer = TlogWriter(path)
    for n, k in enumerate(order):
        writer.write(1_700_000_000_000_000 + 1000 * n, packets[k])
    writer.close()
    with caplog.at_level("WARNING", logger="mavest"):
        report = asyncio.run(replay(path, ServiceConfig(), fast=fast))
    (stream,) = report.streams
    assert (stream.stats.duplicates, stream.stats.out_of_order) == (200, 40)
    said = [r.getMessage() for r in caplog.records if ": dropped (" in r.getMessage()]
    assert [line.split(": dropped")[0] for line in said] == [
        f"{stream.key}: a sample with the time of the one before",
        f"{stream.key}: a sample older than the one before",
    ]
