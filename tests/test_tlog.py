"""Reading tlogs whose recording is odd but whole: a recording clock that jumps and
stays (a ground station set by NTP mid-log), garbage before the first record, and
inputs that are not files at all (a pipe, a device), which are refused at once."""

from __future__ import annotations

import logging
import os
import random
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from test_bulk import _assert_same_both_ways

from mavest.cli import main
from mavest.mavlink.messages import MAVLink
from mavest.mavlink.tlog import TlogError, TlogReader
from mavest.service.config import ServiceConfig

T0 = 1_700_000_000_000_000  # November 2023, µs
N = 2000  # RAW_IMU samples: 10 s at 200 Hz
YEAR_US = int(365.25 * 86_400 * 10**6)
Record = tuple[int, bytes]


def _records(stamp: Callable[[int], int]) -> list[Record]:
    """A vehicle's RAW_IMU at 200 Hz (its own clock steady) and a HEARTBEAT each second,
    each recorded at ``stamp(i)`` for the i-th sample."""
    mav = MAVLink(None, srcSystem=1, srcComponent=1)
    records = []
    for i in range(N):
        if i % 200 == 0:
            records.append((stamp(i), mav.heartbeat_encode(2, 3, 0, 0, 0, 3).pack(mav)))
        imu = mav.raw_imu_encode(i * 5000, 0, 0, -1000, 0, 0, 0, 200, 0, 400, 0, 0)
        records.append((stamp(i), imu.pack(mav)))
    return records


def _bytes(records: list[Record]) -> bytes:
    return b"".join(stamp.to_bytes(8, "big") + packet for stamp, packet in records)


def _steady(i: int) -> int:
    return T0 + i * 5000


def _set_by_ntp(i: int) -> int:
    """A ground station with no clock (1970, a minute after power-on) that learns the
    time 2.5 s in."""
    return (60_000_000 if i < N // 4 else T0) + i * 5000


# ------------------------------------------------------------------ the recording clock


@pytest.mark.parametrize(
    ("stamp", "said"),
    [
        (lambda i: _steady(i) + (10 * YEAR_US if i >= N // 2 else 0), "forward by 10.0 years"),
        (_set_by_ntp, "forward by 53.9 years"),
        (lambda i: _steady(i) - (10 * YEAR_US if i >= N // 2 else 0), "back by 10.0 years"),
        (lambda i: _steady(i) + (5 * 86_400 * 10**6 if i >= N // 2 else 0), "by 5.0 days"),
    ],
    ids=["years-forward", "1970-to-now", "years-back", "days-forward"],
)
def test_a_clock_that_jumps_and_stays_is_read_on(
    stamp: Callable[[int], int], said: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="mavest")
    records = _records(stamp)
    path = tmp_path / "jump.tlog"
    path.write_bytes(_bytes(records))
    reader = TlogReader.open(path)
    assert [(r.timestamp_us, r.packet) for r in reader] == records
    assert reader.stats.skipped_bytes == reader.stats.bad_crc == 0
    lines = [record.getMessage() for record in caplog.records]
    jumps = [line for line in lines if "recording clock jumped" in line]
    assert len(jumps) == 1 and said in jumps[0] and jumps[0].startswith("jump.tlog: "), lines


@pytest.mark.parametrize("spike", [2**62, 0, T0 + 10 * YEAR_US, T0 - 10 * YEAR_US])
@pytest.mark.parametrize("where", [5, N // 2, N + N // 200 - 2])  # (of N + N / 200 records)
def test_a_single_absurd_timestamp_is_still_skipped(
    spike: int, where: int, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="mavest")
    records = _records(_steady)
    damaged = list(records)
    damaged[where] = (spike, records[where][1])
    path = tmp_path / "spike.tlog"
    path.write_bytes(_bytes(damaged))
    reader = TlogReader.open(path)
    assert [(r.timestamp_us, r.packet) for r in reader] == records[:where] + records[where + 1 :]
    assert reader.stats.skipped_bytes == 8 + len(records[where][1])
    assert not [r for r in caplog.records if "clock jumped" in r.getMessage()]


def test_a_replay_across_a_jump_estimates_and_writes_every_record(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    records = _records(_set_by_ntp)
    path, out = tmp_path / "ntp.tlog", tmp_path / "out.tlog"
    path.write_bytes(_bytes(records))
    assert main(["replay", str(path), "--out-tlog", str(out)]) == 0
    captured = capsys.readouterr()
    assert f"{N} of {N} samples" in captured.out and "damaged input" not in captured.out
    assert captured.err.count("recording clock jumped forward by 53.9 years") == 1, captured.err
    # mavest's own messages (component 191) aside, every input record, as it was
    kept = [(r.timestamp_us, r.packet) for r in TlogReader.open(out) if r.packet[6] == 1]
    assert kept == records


def test_both_replay_paths_agree_across_a_jump(tmp_path: Path) -> None:
    path = tmp_path / "ntp.tlog"
    path.write_bytes(_bytes(_records(_set_by_ntp)))
    report = _assert_same_both_ways(path, ServiceConfig(), tmp_path)
    assert report.skipped_bytes == 0


# ------------------------------------------------------------------ garbage first


@pytest.mark.parametrize("junk", [4_500, 5_000, 300_000, (1 << 20) - 5_000])
def test_garbage_before_a_tlog_is_skipped(junk: int, tmp_path: Path) -> None:
    records = _records(_steady)
    path = tmp_path / "junk.tlog"
    path.write_bytes(random.Random(junk).randbytes(junk) + _bytes(records))
    reader = TlogReader.open(path)
    assert [(r.timestamp_us, r.packet) for r in reader] == records
    assert reader.stats.skipped_bytes == junk


@pytest.mark.parametrize(
    "content",
    [
        random.Random(1).randbytes((1 << 20) + 5_000) + _bytes(_records(_steady)),
        random.Random(2).randbytes(3 << 20),
        # a raw capture (packets without timestamps) after garbage: not a tlog either
        random.Random(3).randbytes(5_000) + b"".join(p for _, p in _records(_steady)),
    ],
    ids=["tlog-beyond-the-search", "random", "raw-capture-after-garbage"],
)
def test_what_is_not_a_tlog_within_the_search_is_refused(content: bytes, tmp_path: Path) -> None:
    path = tmp_path / "input.tlog"
    path.write_bytes(content)
    with pytest.raises(TlogError, match=r"not a MAVLink telemetry log .* first 1 MiB"):
        TlogReader.open(path)


# ------------------------------------------------------------------ not a file


def test_a_pipe_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "flight.tlog"
    os.mkfifo(fifo)
    outcome: list[BaseException | TlogReader] = []

    def read() -> None:
        try:
            outcome.append(TlogReader.open(fifo))
        except BaseException as error:  # any outcome: the test says which it wanted
            outcome.append(error)

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    thread.join(timeout=20.0)
    if thread.is_alive():  # blocked opening the pipe: let it go, and fail
        writer = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.close(writer)
        thread.join(timeout=20.0)
        pytest.fail("opening a pipe waited for a writer")
    assert isinstance(outcome[0], TlogError) and "a pipe" in str(outcome[0])


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero here")
def test_a_device_is_one_line_and_exit_2(capsys: pytest.CaptureFixture) -> None:
    assert main(["replay", "/dev/zero"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/dev/zero is a device" in err, err
