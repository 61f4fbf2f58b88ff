"""Where a replay's time goes: start-up, decode, filter, encode, write, beside pymavlink.

    .venv/bin/python tools/replay_split.py [--seconds 300] [--rounds 3] [--results [FILE]]

The log is what a ground station records from an autopilot streaming its IMU fast: a
simulated flight (mavest.sim's JSBSim aircraft) at 1 kHz for ``--seconds``, RAW_IMU
every sample, the autopilot's ATTITUDE every 20th, HEARTBEAT at 1 Hz (300 s: 315 303
messages, 15.4 MB). In each of ``--rounds`` rounds, in turn first from one round to the
next, each a fresh process as a user runs it (Python keeping its bytecode, the numba
cache warm):

* the whole command ``mavest replay LOG --out-tlog OUT -q``;
* the same command on a 1 s log of the same kind: its start-up (the interpreter, the
  imports, the compiled kernels loaded from the cache), less its 1 001 samples' share
  at the whole command's time per sample past start-up;
* pymavlink reading the log as its users do, ``mavutil.mavlink_connection(LOG)`` and
  ``recv_match(type="RAW_IMU")`` until the end, its interpreter started alike;

and, in this process, the replay's work one stage at a time through the public
functions the replay itself calls, on blocks of 16 384 records (as the replay takes
them):

* decode: the tlog mapped and indexed, CRCs checked (``TlogReader.scan``), the IMU
  payloads gathered and made SI (``mavlink.bulk.decode_payloads``, ``imu_fields``),
  the autopilot's ATTITUDE (``decode_payloads``), the other messages the replay
  decodes (HEARTBEAT) one by one as it does
  (``mavlink.wire.decode_datagram``);
* filter: ``Estimator.update_batch`` over the decoded samples;
* encode: the answers, ATTITUDE and ATTITUDE_QUATERNION per sample
  (``mavlink.bulk.euler_rows``, ``attitude_packets``);
* write: the input records and the answers laid out as the output tlog
  (``mavlink.bulk.interleave``) and written (``TlogWriter.write_records``).

These stages give the replay's own answers, byte for byte (tests/test_replay_split.py).

What the whole command takes beyond start-up and these four is the replay's own
bookkeeping (the clock, the aiding decisions, the counters and reports, the
comparison with each autopilot ATTITUDE, mavest's HEARTBEATs, the loop and its
thread): "bookkeeping/other", the remainder, in wall time and in CPU time. The replay
runs the filter on a thread of its own beside the rest, so on two free cores its wall
time can be less than the stages' sum; its CPU time cannot. Figures are medians of
the rounds; "×" is pymavlink's wall time over the whole command's, round by round.
``--results`` writes the printed tables as the Replay time split section of
docs/results.md (or FILE).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mavest.estimator import Estimator
from mavest.evaluation import report
from mavest.mavlink import bulk, wire
from mavest.mavlink.messages import IMU_FORMATS, mavlink2, time_boot_ms_many
from mavest.mavlink.tlog import TlogReader, TlogWriter
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import usable_mag
from mavest.service.process import MAVEST
from mavest.service.runners import REPLAY_MESSAGES
from mavest.sim.vehicle import write_autopilot_tlog

TITLE = "Replay time split"
RATE = 1000.0  # Hz, the IMU's
ATTITUDE_EVERY = 20  # IMU samples per autopilot ATTITUDE
STARTUP_SECONDS = 1.0  # the short log, whose replay is the command's start-up
TARGET = 10.0  # × pymavlink's loop, whole command: the replay's aim
# Records indexed and handled at a time in the stages: the replay scans as many.
BLOCK_RECORDS = 16384
STAGES = ("decode", "filter", "encode", "write")
IMU = "RAW_IMU"
IMU_ID = mavlink2.MAVLINK_MSG_ID_RAW_IMU
IMU_DTYPE = bulk.wire_dtype(mavlink2.MAVLink_raw_imu_message)
ATTITUDE_ID = mavlink2.MAVLINK_MSG_ID_ATTITUDE
# What else the replay decodes of this log, one record at a time: the messages it
# wants (REPLAY_MESSAGES) other than the IMU's and the autopilot's ATTITUDE, which it
# decodes in bulk.
ONE_BY_ONE = np.array(sorted(REPLAY_MESSAGES - {IMU_ID, ATTITUDE_ID}), dtype=np.int64)

# The commands timed run as on a user's machine, where Python keeps the bytecode it
# compiles: an environment that forbids that (PYTHONDONTWRITEBYTECODE, as a sandbox's
# may) would make every start compile mavest's modules from source again.
_COMMAND_ENVIRONMENT = {
    name: value for name, value in os.environ.items() if name != "PYTHONDONTWRITEBYTECODE"
}

# pymavlink as its users read a tlog, in a process of its own (run with the log's path).
_PYMAVLINK_LOOP = """
import sys
from pymavlink import mavutil
connection = mavutil.mavlink_connection(sys.argv[1])
samples = 0
while connection.recv_match(type="RAW_IMU") is not None:
    samples += 1
print(samples)
"""


@dataclass(frozen=True)
class Timed:
    """One command's run: wall seconds, CPU seconds (user + system), what it printed."""

    wall: float
    cpu: float
    stdout: str


def run_timed(command: list[str]) -> Timed:
    """Run ``command`` to its end; RuntimeError with its last line if it fails."""
    before = os.times()
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=_COMMAND_ENVIRONMENT)
    wall = time.perf_counter() - start
    after = os.times()
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"{' '.join(command[:4])} … failed ({done.returncode}): {last}")
    cpu = (after.children_user - before.children_user) + (
        after.children_system - before.children_system
    )
    return Timed(wall, cpu, done.stdout)


def replay_command(log: Path, out: Path) -> list[str]:
    return [*MAVEST, "replay", str(log), "--out-tlog", str(out), "-q"]


def pymavlink_command(log: Path) -> list[str]:
    return [sys.executable, "-c", _PYMAVLINK_LOOP, str(log)]


@dataclass(frozen=True)
class StageTimes:
    """The replay's stages run one at a time in this process: seconds each (wall and
    CPU), and what the log held."""

    wall: dict[str, float]
    cpu: dict[str, float]
    records: int
    samples: int
    answers: int  # packets encoded and written (ATTITUDE and ATTITUDE_QUATERNION)


class _Clock:
    """Wall and CPU time spent per stage, added up over the blocks."""

    def __init__(self) -> None:
        self.wall = dict.fromkeys(STAGES, 0.0)
        self.cpu = dict.fromkeys(STAGES, 0.0)
        self._wall = time.perf_counter()
        self._cpu = time.process_time()

    def lap(self, stage: str) -> None:
        """The time since the last lap was ``stage``'s."""
        wall, cpu = time.perf_counter(), time.process_time()
        self.wall[stage] += wall - self._wall
        self.cpu[stage] += cpu - self._cpu
        self._wall, self._cpu = wall, cpu


def time_stages(log: Path, out: Path) -> StageTimes:
    """Decode, filter, encode and write ``log`` to ``out`` as the replay does, through
    the public functions it calls, each stage timed on its own (serially: no thread)."""
    config = ServiceConfig()
    # as the service makes a stream's estimator: its clock confirms the timeline, and
    # it is fed batches
    estimator = Estimator(config.estimator.replace(timeline_confirm=1), batch_fed=True)
    time_scale = IMU_FORMATS[IMU].time_scale
    component = config.output.component_id
    seq = 0
    records_seen = samples = answers = 0
    clock = _Clock()
    reader = TlogReader.open(log, REPLAY_MESSAGES)
    data = reader.array
    clock.lap("decode")
    tlog = TlogWriter(out)
    clock.lap("write")
    try:
        while True:
            records = reader.scan(BLOCK_RECORDS)
            if not len(records):
                break
            rows = np.flatnonzero(records.message_id == IMU_ID)
            payloads = bulk.decode_payloads(data, records.part(rows), IMU_DTYPE)
            fields = bulk.imu_fields(IMU, payloads)
            attitudes = np.flatnonzero(records.message_id == ATTITUDE_ID)
            bulk.decode_payloads(data, records.part(attitudes), bulk.ATTITUDE_DTYPE)
            for row in np.flatnonzero(np.isin(records.message_id, ONE_BY_ONE)).tolist():
                packet = data[int(records.start[row]) + 8 : int(records.end[row])].tobytes()
                if wire.decode_datagram(packet) is None:
                    raise RuntimeError(f"{log}: a record wire.decode_datagram does not take")
            t = fields.ticks * time_scale
            mag = fields.mag.copy()
            usable = fields.mag_fresh & usable_mag(tuple(mag.T))
            mag[~usable] = math.nan
            clock.lap("decode")
            series = estimator.update_batch(t, fields.gyro, fields.accel, mag)
            clock.lap("filter")
            system = config.output.system_id or int(records.system[rows[0]])
            first, second = bulk.attitude_packets(
                time_boot_ms_many(series.t),
                bulk.euler_rows(series.q),
                fields.gyro - series.bias,
                series.q,
                system,
                component,
                seq,
                data[records.start[rows] + 8] == mavlink2.PROTOCOL_MARKER_V1,
            )
            seq = (seq + 2 * rows.shape[0]) % 256
            clock.lap("encode")
            answer_of = np.full(len(records), -1, dtype=np.int64)
            answer_of[rows] = np.arange(rows.shape[0])
            tlog.write_records(*bulk.interleave(data, records, answer_of, first, second))
            clock.lap("write")
            records_seen += len(records)
            samples += rows.shape[0]
            answers += 2 * rows.shape[0]
    finally:
        tlog.close()
    clock.lap("write")
    if reader.position != reader.size:
        raise RuntimeError(f"{log}: a damaged record at byte {reader.position}")
    if tlog.error is not None:
        raise RuntimeError(tlog.error)
    return StageTimes(clock.wall, clock.cpu, records_seen, samples, answers)


@dataclass
class Rounds:
    """Every round's figures, in the order run."""

    whole: list[Timed]
    startup: list[Timed]
    pymavlink: list[Timed]
    stages: list[StageTimes]
    startup_samples: int  # the 1 s log's


def measure(log: Path, short: Path, workdir: Path, rounds: int) -> Rounds:
    """``rounds`` rounds of the four measurements, in turn first from one round to the
    next (so that a drifting machine load favours none), after a warm-up of each."""
    out = workdir / "out.tlog"
    parts = {
        "whole": lambda: run_timed(replay_command(log, out)),
        "startup": lambda: run_timed(replay_command(short, workdir / "out_short.tlog")),
        "pymavlink": lambda: run_timed(pymavlink_command(log)),
        "stages": lambda: time_stages(log, workdir / "out_stages.tlog"),
    }
    # the numba cache and bytecode warm, pymavlink's dialect loaded once, the kernels
    # loaded in this process
    run_timed(replay_command(short, workdir / "out_short.tlog"))
    run_timed(pymavlink_command(short))
    startup_samples = time_stages(short, workdir / "out_stages.tlog").samples
    results: dict[str, list] = {name: [] for name in parts}
    order = list(parts)
    for i in range(rounds):
        for name in order if i % 2 == 0 else order[::-1]:
            results[name].append(parts[name]())
    return Rounds(**results, startup_samples=startup_samples)


def records_in(path: Path) -> int:
    """The records of a tlog up to its first damaged one."""
    reader = TlogReader.open(path)
    while len(reader.scan(BLOCK_RECORDS)):
        pass
    return reader.stats.records


def check(measured: Rounds, replayed: Path) -> None:
    """The contenders did the same work: pymavlink read every sample the stages took,
    and the replay's output tlog (``replayed``) holds at least the input's records and
    two answers per sample, as the stages wrote (RuntimeError otherwise)."""
    stages = measured.stages[0]
    for timed in measured.pymavlink:
        if int(timed.stdout.split()[-1]) != stages.samples:
            raise RuntimeError(
                f"pymavlink read {timed.stdout.strip()} RAW_IMU, not {stages.samples}"
            )
    written = records_in(replayed)
    if written < stages.records + stages.answers:
        raise RuntimeError(
            f"the replay wrote {written} records, not the {stages.records} read and "
            f"{stages.answers} answers"
        )


def _median(values: list[float]) -> float:
    return float(np.median(values))


def split(measured: Rounds) -> dict[str, dict[str, float]]:
    """Per stage (start-up, the four, bookkeeping/other, the whole command): seconds of
    wall and CPU time, medians of the rounds, and the wall's range over them.

    Start-up is the 1 s log's command less its own samples' share, at the whole
    command's time per sample past start-up (the two commands' difference over their
    samples' difference): so start-up and the samples' time add up to the whole
    command, however short the log. The remainder is taken round by round: the whole
    command less start-up and the four stages of the same round."""
    samples = measured.stages[0].samples
    short = measured.startup_samples
    rows: dict[str, dict[str, list[float]]] = {}

    def add(name: str, wall: float, cpu: float) -> None:
        row = rows.setdefault(name, {"wall": [], "cpu": []})
        row["wall"].append(wall)
        row["cpu"].append(cpu)

    for whole, startup, stages in zip(
        measured.whole, measured.startup, measured.stages, strict=True
    ):
        fixed_wall = startup.wall - short * (whole.wall - startup.wall) / (samples - short)
        fixed_cpu = startup.cpu - short * (whole.cpu - startup.cpu) / (samples - short)
        add("start-up", fixed_wall, fixed_cpu)
        for stage in STAGES:
            add(stage, stages.wall[stage], stages.cpu[stage])
        add(
            "bookkeeping/other",
            whole.wall - fixed_wall - sum(stages.wall.values()),
            whole.cpu - fixed_cpu - sum(stages.cpu.values()),
        )
        add("whole command", whole.wall, whole.cpu)
    return {
        name: {
            "wall": _median(row["wall"]),
            "cpu": _median(row["cpu"]),
            "low": min(row["wall"]),
            "high": max(row["wall"]),
        }
        for name, row in rows.items()
    }


def ratios(measured: Rounds) -> np.ndarray:
    """pymavlink's wall time over the whole command's, round by round."""
    pairs = zip(measured.pymavlink, measured.whole, strict=True)
    return np.array([pymavlink.wall / whole.wall for pymavlink, whole in pairs])


WHAT = {
    "start-up": "the command on a 1 s log, less its samples",
    "decode": "`TlogReader.scan`, `decode_payloads`, `imu_fields`, `wire.decode_datagram`",
    "filter": "`Estimator.update_batch`",
    "encode": "`euler_rows`, `attitude_packets`",
    "write": "`interleave`, `TlogWriter.write_records`",
    "bookkeeping/other": "the whole command less the rest",
    "whole command": "`mavest replay LOG --out-tlog OUT -q`",
}


def print_tables(measured: Rounds, log: Path, seconds: float, rounds: int) -> None:
    stages = measured.stages[0]
    samples = stages.samples
    megabytes = log.stat().st_size / 1e6
    print(
        f"Replay of a {seconds:g} s simulated flight's tlog: {samples:,} RAW_IMU at "
        f"{RATE:g} Hz, ATTITUDE every {ATTITUDE_EVERY}th sample, HEARTBEAT at 1 Hz "
        f"({stages.records:,} messages, {megabytes:.1f} MB); wall s, medians of {rounds} "
        f"interleaved round{'s' if rounds != 1 else ''}, each command a fresh process"
    )
    figures = {
        "`mavest replay LOG --out-tlog OUT -q` (whole command)": measured.whole,
        "`mavest replay` of a 1 s log (start-up)": measured.startup,
        'pymavlink `mavlink_connection(LOG)`, `recv_match(type="RAW_IMU")` loop': (
            measured.pymavlink
        ),
    }
    print("\n| command | wall s | rounds' range | CPU s | IMU samples/s |")
    print("|---|---:|---:|---:|---:|")
    for label, runs in figures.items():
        walls = [run.wall for run in runs]
        wall = _median(walls)
        rate = f"{samples / wall:,.0f}" if "start-up" not in label else ""
        print(
            f"| {label} | {wall:.2f} | {min(walls):.2f}–{max(walls):.2f} | "
            f"{_median([run.cpu for run in runs]):.2f} | {rate} |"
        )
    ratio = ratios(measured)
    verdict = "reached" if float(np.median(ratio)) >= TARGET else "**not reached**"
    budget = _median([run.wall for run in measured.pymavlink]) / TARGET
    parts = split(measured)
    left = budget - parts["start-up"]["wall"]
    print(
        f"\npymavlink's loop / mavest's whole command: **{float(np.median(ratio)):.1f}×** "
        f"(rounds' range {ratio.min():.1f}–{ratio.max():.1f}); {TARGET:g}× is {verdict}: "
        f"it needs the whole command in {budget:.2f} s, start-up included; "
        + (
            f"after this start-up, {1e6 * left / samples:.2f} µs a sample."
            if left > 0.0
            else "this start-up alone takes longer."
        )
    )
    whole = parts["whole command"]
    print(
        f"\nWhere a sample's time goes, µs per IMU sample ({samples:,} samples; start-up "
        "spread over them). The stages are the replay's work through the functions it "
        "calls, one at a time in the measuring process; bookkeeping/other is the "
        "remainder."
    )
    print("\n| stage | timed | wall µs/sample | rounds' range | share | CPU µs/sample |")
    print("|---|---|---:|---:|---:|---:|")
    for name, figure in parts.items():
        bold = "**" if name == "whole command" else ""
        print(
            f"| {bold}{name}{bold} | {WHAT[name]} | {bold}{1e6 * figure['wall'] / samples:.2f}"
            f"{bold} | {1e6 * figure['low'] / samples:.2f}–{1e6 * figure['high'] / samples:.2f}"
            f" | {100.0 * figure['wall'] / whole['wall']:.0f} % | "
            f"{1e6 * figure['cpu'] / samples:.2f} |"
        )
    print(
        f"\nThe filter runs on a thread of its own in the replay, beside the rest: the "
        f"whole command took {whole['cpu'] / whole['wall']:.2f} s of CPU per wall second."
    )


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=300.0, help="the log's flight, s")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    if args.seconds <= STARTUP_SECONDS or args.rounds < 1:
        parser.error(f"--seconds must be over {STARTUP_SECONDS:g} and --rounds at least 1")
    with tempfile.TemporaryDirectory() as folder:
        workdir = Path(folder)
        log, short = workdir / "flight.tlog", workdir / "flight_1s.tlog"
        for path, seconds in ((log, args.seconds), (short, STARTUP_SECONDS)):
            write_autopilot_tlog(path, seconds, RATE, attitude_every=ATTITUDE_EVERY)
        try:
            measured = measure(log, short, workdir, args.rounds)
            check(measured, workdir / "out.tlog")
        except RuntimeError as error:
            report.progress("replay_split", str(error))
            return 2
        with report.results_section(args.results, TITLE, __file__, argv, __doc__):
            print_tables(measured, log, args.seconds, args.rounds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
