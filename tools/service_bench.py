"""The service's speed: live latency, replay throughput beside pymavlink, Rerun's cost.

    .venv/bin/python tools/service_bench.py [--seconds 30] [--rate 1000] [--replay-seconds 300]
                                            [--only live|replay|rerun] [--results [FILE]]

Live: ``mavest run udpin:…`` (a separate process, as users run it) is fed a simulated
flight over loopback UDP at ``--rate`` (RAW_IMU and SIMSTATE per sample, VFR_HUD and
GPS at 10 Hz, HEARTBEAT at 1 Hz: the stream of the tlogs below), and every IMU packet
is timed to the ATTITUDE that answers it (matched by ``time_boot_ms``; above 1 kHz, in
order within a millisecond); samples never answered are counted as lost. How it times,
so that what it reports is the service's latency and not the bench's:

- the flight is computed before the clock starts: while timing, the vehicle only sends
  (the streaming vehicle of ``mavest sim`` steps JSBSim in the event loop it
  receives in, where a long step makes sends late and receive times later still);
- the send time is read just before the ``send`` of each IMU packet, which on loopback
  puts it in the service's socket within the call; the arrival time of each ATTITUDE
  is the kernel's stamp (SO_TIMESTAMPNS) of when the service's ``sendto`` put it in
  the vehicle's socket, however late the vehicle reads it. Latency is packet in →
  ATTITUDE out, plus two loopback hops;
- "sender late" is how far behind its schedule the vehicle sent (a sender held up on
  a busy machine sends several samples at once, which the service then queues);
- "service CPU" is the service's user + system CPU over the stream (from /proc).

Beside the streams, the pipeline's own cost: the same flight's datagrams handed to
``Pipeline.on_bytes`` in a fresh process per round (per ``--baseline`` version too,
interleaved), with a UDP link that sends nothing, timed in process CPU per IMU sample.
No sockets, no event loop, no scheduler: the part of the service's CPU that is its
own code (decoding, estimating, answering), which the streams' CPU figure, dominated
on a virtual machine by the sockets' wake-ups, cannot resolve.

``--live-rounds`` streams, each with a fresh service; ``--baseline DIR`` runs the
service from another source tree (e.g. an older checkout) in interleaved rounds, for
a before/after in the same run. ``--realtime`` puts the service's event loop and the
sending loop at SCHED_FIFO priority (root): what the service does when the rest of a
shared machine cannot take its CPU. The rate sweep (``--sweep-rates``, ``--sweep-seconds``
each, a fresh service per rate) reports the highest rate answered without loss and
kept up (the last second's median latency under ``KEPT_UP_MS``; a service that falls
behind builds a backlog that grows through the run) and its p99.

Replay: a 1 kHz simulated flight (``--replay-seconds``) written to a tlog, then the
whole command ``mavest replay FILE --out-tlog OUT`` timed (as a user runs it: Python
keeping its bytecode), beside pymavlink reading every message of the same file
(``recv_msg`` until the end, in the bench's process: its import not counted) and the same command
with ``--one-by-one``, in interleaved rounds; and the command on a 1 s flight, which
is its start-up (imports, the compiled kernels loaded from the cache).
Rerun: a ``--rerun-seconds`` replay with and without ``--rrd`` in interleaved rounds,
sample by sample as the live service works (``--one-by-one``), CPU time (user +
system) of the whole command; the ratio is what recording costs.
``--instructions`` adds the same comparison counted in instructions under valgrind
(callgrind, every thread of the replay, Rerun's encoder and writer included), which a
busy machine does not disturb: 2 s and ``--instruction-seconds`` flights with and
without ``--rrd``, the cost per simulated second taken between the two lengths so that
start-up (imports, the numba cache, opening the recording) falls out; the longer pair
is run twice to show the count repeats. ``--only rerun`` (or live, replay) runs one part.
``--results`` writes the printed tables as the Service section of docs/results.md (or
FILE).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import os
import pickle
import select
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymavlink import mavutil

import mavest
from mavest.evaluation import report
from mavest.mavlink.messages import MAVLink, time_boot_ms
from mavest.service.process import MAVEST, ServiceProcess, free_port
from mavest.sim.vehicle import AUTOPILOTS, TLOG_EPOCH_US, flight_records, write_flight_tlog

PARTS = ("live", "replay", "rerun")


# ---------------------------------------------------------------- live latency
#
# The vehicle of the live part is the simulated flight of the tlogs (flight_records: the
# IMU message and SIMSTATE per sample, VFR_HUD and GPS at 10 Hz, HEARTBEAT at 1 Hz),
# computed before the clock starts, so that sending is all the bench does while it times.

# Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS): the kernel stamps each datagram with the
# CLOCK_REALTIME nanosecond it arrived at the socket (not every Python names it).
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")
LINGER = 1.0  # s after the last IMU packet for the last answers (and a backlog) to come
REPLY_BUFFER = 8 << 20  # bytes of the bench's receive buffer: no answer lost there
KEPT_UP_MS = 10.0  # median latency of the last second under which a rate is kept up


@dataclass(frozen=True)
class PreparedFlight:
    """A flight's packets, grouped by the time they are due, ready to send.

    ``times[i]`` (s from the start) is when group i is due; ``imu[i]`` is its IMU packet
    (empty for a group without one), sent first and timed; ``others[i]`` the rest
    (SIMSTATE, VFR_HUD, GPS, HEARTBEAT, PARAM_VALUE); ``keys[i]`` the ``time_boot_ms``
    the service's ATTITUDE for that IMU sample carries (−1: no IMU in the group).
    """

    rate: float
    times: np.ndarray
    imu: list[bytes]
    others: list[tuple[bytes, ...]]
    keys: np.ndarray

    @property
    def samples(self) -> int:
        return int((self.keys >= 0).sum())


def prepare_flight(seconds: float, rate: float, seed: int = 1) -> PreparedFlight:
    """The simulated vehicle's stream at ``rate`` Hz for ``seconds``, computed now."""
    parser = MAVLink(None)
    imu_name = AUTOPILOTS["ardupilot"].imu_message
    times: list[float] = []
    imu: list[bytes] = []
    others: list[list[bytes]] = []
    keys: list[int] = []
    last_stamp = None
    for stamp, packet in flight_records(seconds, rate, AUTOPILOTS["ardupilot"], seed):
        if stamp != last_stamp:
            times.append((stamp - TLOG_EPOCH_US) * 1e-6)
            imu.append(b"")
            others.append([])
            keys.append(-1)
            last_stamp = stamp
        message = parser.parse_char(packet)
        if message is not None and message.get_type() == imu_name:
            imu[-1] = packet
            # as the service stamps its answer: the sample's time since boot, in ms
            keys[-1] = time_boot_ms(message.time_usec * 1e-6)
        else:
            others[-1].append(packet)
    return PreparedFlight(
        rate, np.array(times), imu, [tuple(o) for o in others], np.array(keys, dtype=np.int64)
    )


@dataclass
class LiveRun:
    """What one live stream measured; latencies in ms, from kernel timestamps."""

    rate: float
    sent: int  # IMU samples sent
    answered: int  # of those, answered by an ATTITUDE
    latencies: np.ndarray  # ms, IMU packet sent → its ATTITUDE at our socket, per answer
    answered_at: np.ndarray  # s into the stream each answered sample was due (as latencies)
    lateness: np.ndarray  # ms, how long after its due time each IMU packet was sent
    unmatched: int = 0  # ATTITUDE for no sample sent (or answered twice)
    send_errors: int = 0
    seconds: float = 0.0  # the stream's length
    service_cpu_s: float = math.nan  # CPU the service used meanwhile (user + system)

    @property
    def lost(self) -> int:
        return self.sent - self.answered

    @property
    def kept_up(self) -> bool:
        """The service answered the last second's samples within ``KEPT_UP_MS`` (median):
        one that falls behind builds a backlog that grows through the run."""
        if not self.answered:
            return False
        last = self.answered_at >= self.answered_at.max() - 1.0
        return float(np.median(self.latencies[last])) < KEPT_UP_MS

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies, q)) if len(self.latencies) else math.nan

    def row(self) -> dict[str, float]:
        return {
            "rate": self.rate,
            "sent": self.sent,
            "lost": self.lost,
            "answered %": 100.0 * self.answered / self.sent if self.sent else 0.0,
            "p50 ms": self.percentile(50),
            "p99 ms": self.percentile(99),
            "p99.9 ms": self.percentile(99.9),
            "max ms": float(self.latencies.max()) if len(self.latencies) else math.nan,
            "sender late p99 ms": float(np.percentile(self.lateness, 99)),
            "service CPU %": 100.0 * self.service_cpu_s / self.seconds,
            "CPU µs per sample": 1e6 * self.service_cpu_s / self.sent if self.sent else math.nan,
        }


def _kernel_ns(ancillary: list[tuple[int, int, bytes]]) -> int:
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            seconds, nanoseconds = _TIMESPEC.unpack_from(data)
            return seconds * 1_000_000_000 + nanoseconds
    return time.time_ns()  # (never on Linux) the time we read it: later, never earlier


def drive(address: tuple[str, int], flight: PreparedFlight, linger: float = LINGER) -> LiveRun:
    """Send ``flight`` to ``address`` on its schedule and time every answer.

    Each IMU packet's send time is read (CLOCK_REALTIME) just before the ``send`` that
    puts it in the service's socket: on loopback the kernel delivers it within that
    call. Each ATTITUDE's arrival time is the kernel's own stamp (SO_TIMESTAMPNS) of
    when the service's ``sendto`` put it in our socket, so however late this loop reads
    it (busy sending, descheduled) the latency is the service's: packet in → ATTITUDE
    out, plus two loopback hops. Between sends the loop waits in ``select`` on the
    socket and takes the answers as they come, unparsed; matching them to samples
    (by ``time_boot_ms``, in order within a millisecond) is done after the run.
    """
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, REPLY_BUFFER)
    sock.connect(address)
    sock.setblocking(False)
    replies: list[tuple[bytes, int]] = []
    ancillary_size = socket.CMSG_SPACE(_TIMESPEC.size)
    count = len(flight.times)
    sent_ns = np.zeros(count, dtype=np.int64)
    lateness = np.zeros(count)
    send_errors = 0

    def take_replies() -> None:
        while True:
            try:
                data, ancillary, _, _ = sock.recvmsg(2048, ancillary_size)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:  # ICMP: the service is not (yet) listening
                continue
            replies.append((data, _kernel_ns(ancillary)))

    times, imu, others = flight.times, flight.imu, flight.others
    clock = time.perf_counter
    gc_was_enabled = gc.isenabled()
    gc.disable()  # the bench's own pauses would only delay sends, but keep the grid exact
    try:
        start = clock() + 0.05
        for i in range(count):
            due = start + times[i]
            while (wait := due - clock()) > 0.0:
                readable, _, _ = select.select([sock], [], [], wait)
                if readable:
                    take_replies()
            packet = imu[i]
            try:
                if packet:
                    sent_ns[i] = time.time_ns()
                    sock.send(packet)
                for other in others[i]:
                    sock.send(other)
            except OSError:  # ICMP refusal of an earlier packet, a full buffer
                send_errors += 1
            lateness[i] = clock() - due
        end = clock() + linger
        while (wait := end - clock()) > 0.0:
            readable, _, _ = select.select([sock], [], [], wait)
            if readable:
                take_replies()
    finally:
        if gc_was_enabled:
            gc.enable()
        sock.close()
    return _score(flight, sent_ns, lateness * 1e3, replies, send_errors)


def _score(
    flight: PreparedFlight,
    sent_ns: np.ndarray,
    lateness_ms: np.ndarray,
    replies: list[tuple[bytes, int]],
    send_errors: int,
) -> LiveRun:
    """Match each ATTITUDE to the sample it answers: same ``time_boot_ms``, and within
    one millisecond (rates above 1 kHz) the samples in the order they were sent."""
    waiting: dict[int, deque[int]] = {}
    for i in np.flatnonzero(flight.keys >= 0):
        waiting.setdefault(int(flight.keys[i]), deque()).append(int(i))
    parser = MAVLink(None)
    parser.robust_parsing = True
    latencies: list[int] = []
    answered_at: list[float] = []
    unmatched = 0
    for data, arrived_ns in replies:
        for message in parser.parse_buffer(data) or ():
            if message.get_type() != "ATTITUDE":
                continue
            queue = waiting.get(message.time_boot_ms)
            if not queue:
                unmatched += 1
                continue
            sample = queue.popleft()
            latencies.append(arrived_ns - int(sent_ns[sample]))
            answered_at.append(float(flight.times[sample]))
    imu_groups = flight.keys >= 0
    return LiveRun(
        rate=flight.rate,
        sent=flight.samples,
        answered=len(latencies),
        latencies=np.array(latencies, dtype=np.float64) * 1e-6,
        answered_at=np.array(answered_at),
        lateness=lateness_ms[imu_groups],
        unmatched=unmatched,
        send_errors=send_errors,
        seconds=float(flight.times[-1]) + LINGER,
    )


def live(
    seconds: float,
    rate: float,
    flight: PreparedFlight | None = None,
    service_path: str = "",
    realtime: bool = False,
) -> LiveRun:
    """One ``mavest run udpin:…`` process fed ``flight`` (made here if not given).

    ``service_path``: run the service from that source tree (PYTHONPATH) instead of
    this one's, to compare two versions of it in the same run. ``realtime``: the
    service's event loop and this sending loop at SCHED_FIFO priority, which the
    machine's other work cannot preempt (needs CAP_SYS_NICE, e.g. root).
    """
    flight = flight if flight is not None else prepare_flight(seconds, rate)
    port = free_port(socket.SOCK_DGRAM)
    environment, directory = _tree(service_path)
    service = ServiceProcess(f"udpin:127.0.0.1:{port}", env=environment, cwd=directory)
    try:
        with _realtime(service.process.pid) if realtime else contextlib.nullcontext():
            cpu_before = _cpu_of(service.process.pid)
            run = drive(("127.0.0.1", port), flight)
            run.service_cpu_s = _cpu_of(service.process.pid) - cpu_before
        return run
    finally:
        service.stop()


REALTIME_PRIORITY = 10  # SCHED_FIFO's 1–99: above every ordinary process, below the kernel's


@contextlib.contextmanager
def _realtime(service_pid: int) -> Iterator[None]:
    """The service's main thread (its event loop) and this thread at SCHED_FIFO."""
    fifo = os.sched_param(REALTIME_PRIORITY)
    try:
        os.sched_setscheduler(service_pid, os.SCHED_FIFO, fifo)
        os.sched_setscheduler(0, os.SCHED_FIFO, fifo)
    except PermissionError:
        raise SystemExit("--realtime needs the right to set SCHED_FIFO (CAP_SYS_NICE)") from None
    try:
        yield
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _cpu_of(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rate_sweep(rates: list[float], seconds: float, realtime: bool = False) -> list[LiveRun]:
    """The live stream at each rate in turn, a fresh service for each, ``seconds`` each."""
    return [live(seconds, rate, realtime=realtime) for rate in rates]


def highest_sustained(runs: list[LiveRun]) -> LiveRun | None:
    """The fastest run that lost nothing and kept up (None: none did)."""
    clean = [run for run in runs if run.sent > 0 and run.lost == 0 and run.kept_up]
    return max(clean, key=lambda run: run.rate) if clean else None


# The commands timed run as on a user's machine, where Python keeps the bytecode it
# compiles: an environment that forbids that (PYTHONDONTWRITEBYTECODE, as a sandbox's
# may) makes every start compile mavest's modules from source again (0.08 s).
_COMMAND_ENVIRONMENT = {
    name: value for name, value in os.environ.items() if name != "PYTHONDONTWRITEBYTECODE"
}


def _wall_seconds(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env=_COMMAND_ENVIRONMENT)
    return time.perf_counter() - start


def _pymavlink_parse(path: Path) -> int:
    """Every message of a tlog through pymavlink's reader (robust, as users read logs)."""
    connection = mavutil.mavlink_connection(str(path), robust_parsing=True)
    messages = 0
    while connection.recv_msg() is not None:
        messages += 1
    connection.close()
    return messages


def replay_throughput(seconds: float, workdir: Path, rounds: int) -> dict[str, float]:
    """Wall time of the whole ``mavest replay FILE --out-tlog OUT`` on a 1 kHz flight,
    beside pymavlink's parse of the same file and mavest's one-record-at-a-time path,
    in interleaved rounds (medians); and the command on a 1 s flight: its start-up."""
    flight = workdir / "flight_1khz.tlog"
    write_flight_tlog(flight, seconds, 1000.0, AUTOPILOTS["ardupilot"], seed=1)
    short = workdir / "flight_1s.tlog"
    write_flight_tlog(short, 1.0, 1000.0, AUTOPILOTS["ardupilot"], seed=1)
    out = workdir / "out.tlog"
    fast = [*MAVEST, "replay", str(flight), "--out-tlog", str(out), "-q"]
    one_by_one = [*fast, "--one-by-one"]
    startup = [*MAVEST, "replay", str(short), "--out-tlog", str(out), "-q"]
    # a warm numba cache (and bytecode)
    subprocess.run(startup, check=True, capture_output=True, env=_COMMAND_ENVIRONMENT)
    times: dict[str, list[float]] = {"fast": [], "one": [], "pymavlink": [], "startup": []}
    messages = 0
    for _ in range(rounds):
        times["fast"].append(_wall_seconds(fast))
        start = time.perf_counter()
        messages = _pymavlink_parse(flight)
        times["pymavlink"].append(time.perf_counter() - start)
        times["one"].append(_wall_seconds(one_by_one))
        times["startup"].append(_wall_seconds(startup))
    median = {name: float(np.median(values)) for name, values in times.items()}
    ratios = np.array(times["pymavlink"]) / np.array(times["fast"])
    return {
        "messages": messages,
        "mavest replay s": median["fast"],
        "one by one s": median["one"],
        "pymavlink parse s": median["pymavlink"],
        "startup s": median["startup"],
        "ratio": float(np.median(ratios)),
        "ratio min": float(ratios.min()),
        "ratio max": float(ratios.max()),
        "one by one ratio": median["pymavlink"] / median["one"],
        "MB": flight.stat().st_size / 1e6,
    }


def _cpu_seconds(command: list[str]) -> float:
    """User + system CPU time of a child process."""
    before = os.times()
    subprocess.run(command, check=True, capture_output=True)
    after = os.times()
    return (after.children_user - before.children_user) + (
        after.children_system - before.children_system
    )


def rerun_cost(seconds: float, workdir: Path, rounds: int) -> dict[str, float]:
    """CPU s of the replay without and with ``--rrd``, and their ratio.

    The two are run back to back in each round, in turn first (ABBA), so that
    a drift in the shared machine's speed falls on both alike; the ratio is the
    median of the rounds' ratios, with their spread.
    """
    flight = workdir / "flight_rerun.tlog"
    write_flight_tlog(flight, seconds, 1000.0, AUTOPILOTS["ardupilot"], seed=2)
    # sample by sample, as the live service works: a recording needs each estimate as it
    # comes, so a replay with --rrd takes that path anyway
    plain = [*MAVEST, "replay", str(flight), "-q", "--one-by-one"]
    recorded = [*plain, "--rrd", str(workdir / "x.rrd")]
    _cpu_seconds(plain)  # warm the caches
    without, with_rrd = [], []
    for i in range(rounds):
        if i % 2:
            with_rrd.append(_cpu_seconds(recorded))
            without.append(_cpu_seconds(plain))
        else:
            without.append(_cpu_seconds(plain))
            with_rrd.append(_cpu_seconds(recorded))
    ratios = np.array(with_rrd) / np.array(without)
    return {
        "without": float(np.median(without)),
        "with": float(np.median(with_rrd)),
        "ratio": float(np.median(ratios)),
        "ratio min": float(ratios.min()),
        "ratio max": float(ratios.max()),
        "rrd MB": (workdir / "x.rrd").stat().st_size / 1e6,
    }


# What llvmlite sees of the CPU, printed by a child process.
_CPU_PROBE = (
    "import llvmlite.binding as ll; print(ll.get_host_cpu_name()); "
    "print(ll.get_host_cpu_features().flatten())"
)
SHORT_SECONDS = 2.0  # the shorter flight of --instructions


def _instruction_environment(workdir: Path) -> dict[str, str]:
    """The environment for counting: numba compiling for the CPU valgrind shows, cached.

    valgrind's virtual CPU has fewer features than the host (here haswell without adx,
    sha, ... on a znver3): numba keys its cache on the CPU, so a replay under valgrind
    would miss the cache and compile every kernel at valgrind's speed, and count it. So
    the kernels are compiled for valgrind's CPU (NUMBA_CPU_NAME/FEATURES) by a native
    run first, into a cache of their own; a fixed hash seed makes the runs alike.
    """
    probe = subprocess.run(
        ["valgrind", "--tool=none", "-q", sys.executable, "-c", _CPU_PROBE],
        check=True,
        capture_output=True,
        text=True,
    )
    name, features = probe.stdout.split()[:2]
    return {
        **os.environ,
        "NUMBA_CPU_NAME": name,
        "NUMBA_CPU_FEATURES": features,
        "MAVEST_CACHE_DIR": str(workdir / "numba-valgrind-cpu"),
        "PYTHONHASHSEED": "0",
    }


def _instructions(command: list[str], out: Path, environment: dict[str, str]) -> int:
    """Instructions executed by a command (all its threads, not its children)."""
    subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            "--trace-children=no",
            f"--callgrind-out-file={out}",
            *command,
        ],
        check=True,
        capture_output=True,
        env=environment,
    )
    with out.open() as lines:
        for line in lines:
            if line.startswith("summary:"):
                return int(line.split()[1])
    raise RuntimeError(f"no summary in {out}")


def rerun_instructions(seconds: float, workdir: Path, jobs: int) -> dict[str, float]:
    """Instructions of the replay without and with ``--rrd`` at two flight lengths.

    The marginal cost per simulated second, (long − short) / (seconds − 2), leaves out
    what does not grow with the flight (start-up, the static entities, the bodies'
    shapes, the last flush); at 1 kHz a file's batch is 32768 rows, so both lengths
    flush once, at the end, and each further batch would add ~30 ``send_columns`` calls
    per 32.8 s of flight (the whole long run's ratio is shown too). The long pair is run
    twice: a count that repeats shows nothing compiled or timed differently.
    """
    environment = _instruction_environment(workdir)
    flights = {}
    for length in (SHORT_SECONDS, seconds):
        flights[length] = workdir / f"flight_instructions_{length:g}s.tlog"
        write_flight_tlog(flights[length], length, 1000.0, AUTOPILOTS["ardupilot"], seed=2)

    def command(length: float, rrd: bool, run: int = 0) -> list[str]:
        plain = [*MAVEST, "replay", str(flights[length]), "-q", "--one-by-one"]
        return [*plain, "--rrd", str(workdir / f"i{length:g}_{run}.rrd")] if rrd else plain

    # warm the cache (compiled for valgrind's CPU) natively: nothing compiles when counted
    subprocess.run(command(SHORT_SECONDS, True), check=True, capture_output=True, env=environment)
    runs = {
        (rrd, length, run): command(length, rrd, run)
        for rrd in (False, True)
        for length, run in ((SHORT_SECONDS, 0), (seconds, 0), (seconds, 1))
    }
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = {
            key: pool.submit(_instructions, cmd, workdir / f"callgrind.{i}", environment)
            for i, (key, cmd) in enumerate(runs.items())
        }
        counts = {key: future.result() for key, future in futures.items()}
    result: dict[str, float] = {"seconds": seconds}
    for rrd, name in ((False, "without"), (True, "with")):
        short, long_, again = (
            counts[rrd, SHORT_SECONDS, 0],
            counts[rrd, seconds, 0],
            counts[rrd, seconds, 1],
        )
        result[f"{name} short"] = short
        result[f"{name} long"] = long_
        result[f"{name} again"] = again
        result[f"{name} per s"] = (long_ - short) / (seconds - SHORT_SECONDS)
    result["ratio"] = result["with per s"] / result["without per s"]
    result["whole ratio"] = result["with long"] / result["without long"]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=30.0, help="live stream length")
    parser.add_argument("--rate", type=float, default=1000.0, help="live IMU rate, Hz")
    parser.add_argument(
        "--live-rounds", type=int, default=3, help="live streams (per service version)"
    )
    parser.add_argument(
        "--baseline",
        default="",
        help="also measure live the mavest source tree in this directory (its PYTHONPATH), "
        "in rounds interleaved with this one: before/after a change in the same run",
    )
    parser.add_argument(
        "--sweep-rates",
        default="1000,2000,4000,8000,16000",
        help="IMU rates (Hz, comma-separated) for the highest rate without loss; '' skips",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="live: the service and the sending loop at SCHED_FIFO priority (needs root), "
        "out of reach of the machine's other load",
    )
    parser.add_argument("--sweep-seconds", type=float, default=5.0, help="stream length per rate")
    parser.add_argument("--replay-seconds", type=float, default=300.0, help="1 kHz tlog length")
    parser.add_argument(
        "--rerun-seconds", type=float, default=30.0, help="1 kHz tlog length for Rerun's cost"
    )
    parser.add_argument(
        "--rounds", type=int, default=3, help="interleaved rounds (replay, Rerun's cost)"
    )
    parser.add_argument(
        "--instructions",
        action="store_true",
        help="also count Rerun's cost in instructions under valgrind (a few minutes)",
    )
    parser.add_argument(
        "--instruction-seconds",
        type=float,
        default=8.0,
        help="the longer 1 kHz flight counted (the shorter is 2 s)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="valgrind runs at a time")
    parser.add_argument(
        "--only",
        choices=PARTS,
        action="append",
        help="run only this part (repeatable; default: all of them)",
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    parts = args.only or list(PARTS)
    with (
        report.results_section(args.results, "Service", __file__, argv, __doc__),
        tempfile.TemporaryDirectory() as workdir,
    ):
        if "live" in parts:
            flight = prepare_flight(args.seconds, args.rate)
            services = {f"mavest {mavest.__version__}": ""}
            if args.baseline:
                services = {f"{args.baseline}": args.baseline, **services}
            print_live(live_rounds(flight, services, args.live_rounds, args.realtime), args)
            print_pipeline_cost(pipeline_cost(flight, services, args.live_rounds))
            if args.sweep_rates:
                rates = [float(r) for r in args.sweep_rates.split(",")]
                print_sweep(rate_sweep(rates, args.sweep_seconds, args.realtime), args)
        if "replay" in parts:
            replayed = replay_throughput(args.replay_seconds, Path(workdir), args.rounds)
            print_replay(replayed, args)
        if "rerun" in parts:
            cost = rerun_cost(args.rerun_seconds, Path(workdir), args.rounds)
            counted = None
            if args.instructions:
                counted = rerun_instructions(args.instruction_seconds, Path(workdir), args.jobs)
            print_rerun(cost, counted, args)
    return 0


# Run in a fresh process (the source tree under test on its PYTHONPATH): feed the
# pickled datagrams to a pipeline twice (the first pass loads and warms everything),
# print the second pass's process CPU per IMU sample in µs.
_PIPELINE_COST = """
import pickle, sys, time
from mavest.mavlink.links import UdpLink, parse_endpoint
from mavest.service.config import ServiceConfig
from mavest.service.pipeline import Pipeline

class Silent(UdpLink):
    def send(self, packet):
        pass

datagrams, samples = pickle.load(open(sys.argv[1], "rb"))
link = Silent(parse_endpoint("udpin:127.0.0.1:14550"))  # never opened
peer = ("127.0.0.1", 14550)
for attempt in range(2):
    pipeline = Pipeline(ServiceConfig(), links=[link], now_us=lambda: time.time_ns() // 1000)
    start = time.process_time()
    for datagram in datagrams:
        pipeline.on_bytes(link, datagram, peer)
    cpu = time.process_time() - start
import mavest
print(mavest.__file__, 1e6 * cpu / samples)
"""


def pipeline_cost(
    flight: PreparedFlight, services: dict[str, str], rounds: int
) -> dict[str, list[float]]:
    """µs of CPU per IMU sample of ``Pipeline.on_bytes`` on ``flight``'s datagrams, per
    service version (label → source tree, "" for this one), ``rounds`` times each (ABBA)."""
    datagrams = [
        packet
        for imu, others in zip(flight.imu, flight.others, strict=True)
        for packet in ((imu,) if imu else ()) + others
    ]
    costs: dict[str, list[float]] = {label: [] for label in services}
    with tempfile.TemporaryDirectory() as workdir:
        flight_file = Path(workdir) / "datagrams.pickle"
        flight_file.write_bytes(pickle.dumps((datagrams, flight.samples)))
        for label, path in _abba(services, rounds):
            environment, directory = _tree(path)
            done = subprocess.run(
                [sys.executable, "-c", _PIPELINE_COST, str(flight_file)],
                env=environment,
                cwd=directory,
                capture_output=True,
                text=True,
            )
            if done.returncode != 0:
                raise RuntimeError(f"pipeline cost of {label}: {done.stderr.strip()}")
            where, cost = done.stdout.split()
            expected = Path(path) if path else Path(mavest.__file__).parent.parent
            if not Path(where).resolve().is_relative_to(expected.resolve()):
                raise RuntimeError(f"{label} ran the mavest in {where}, not {expected}")
            costs[label].append(float(cost))
    return costs


def _tree(path: str) -> tuple[dict[str, str] | None, str | None]:
    """The environment and working directory that run the mavest of source tree ``path``
    ("" for this one): its PYTHONPATH, and the tree itself as the working directory,
    which ``python -m`` and ``python -c`` put on sys.path before PYTHONPATH."""
    if not path:
        return None, None
    return {**os.environ, "PYTHONPATH": path}, path


def _abba(services: dict[str, str], rounds: int) -> Iterator[tuple[str, str]]:
    """(label, source tree) of each run: ``rounds`` rounds, the versions in turn first
    from one round to the next (ABBA), so that a drifting machine load favours none."""
    order = list(services.items())
    for i in range(rounds):
        yield from order if i % 2 == 0 else order[::-1]


def print_pipeline_cost(costs: dict[str, list[float]]) -> None:
    print("\nPipeline alone (Pipeline.on_bytes in process, no sockets): CPU per IMU sample")
    print("\n| service | rounds (µs) | median |")
    print("|---|---|---:|")
    for label, values in costs.items():
        rounds = ", ".join(f"{v:.0f}" for v in values)
        print(f"| {label} | {rounds} | {float(np.median(values)):.0f} µs |")


def live_rounds(
    flight: PreparedFlight, services: dict[str, str], rounds: int, realtime: bool = False
) -> dict[str, list[LiveRun]]:
    """``flight`` sent to each service version (label → source tree, "" for this one)
    ``rounds`` times, the versions in turn first from one round to the next (ABBA)."""
    runs: dict[str, list[LiveRun]] = {label: [] for label in services}
    for label, path in _abba(services, rounds):
        runs[label].append(live(0.0, flight.rate, flight, path, realtime))
    return runs


def print_live(runs: dict[str, list[LiveRun]], args: argparse.Namespace) -> None:
    print(
        f"\nLive, {args.rate:g} Hz RAW_IMU (+ SIMSTATE per sample) over loopback UDP for "
        f"{args.seconds:g} s; latency = IMU packet sent → its ATTITUDE at the vehicle's "
        "socket (kernel timestamp)"
        + ("; service and sender at SCHED_FIFO" if args.realtime else "")
    )
    print(
        "\n| service | run | sent | lost | latency p50 | p99 | p99.9 | max | sender late p99 "
        "| service CPU |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for label, label_runs in runs.items():
        for number, run in enumerate(label_runs, 1):
            print(_live_row(label, str(number), run.row()))
        if len(label_runs) > 1:
            rows = [run.row() for run in label_runs]
            median = {key: float(np.median([row[key] for row in rows])) for key in rows[0]}
            print(_live_row(label, "**median**", median))


def _live_row(label: str, run: str, row: dict[str, float]) -> str:
    return (
        f"| {label} | {run} | {row['sent']:.0f} | {row['lost']:.0f} | {row['p50 ms']:.3f} ms | "
        f"{row['p99 ms']:.3f} ms | {row['p99.9 ms']:.2f} ms | {row['max ms']:.2f} ms | "
        f"{row['sender late p99 ms']:.3f} ms | {row['service CPU %']:.0f} % "
        f"({row['CPU µs per sample']:.0f} µs/sample) |"
    )


def print_sweep(runs: list[LiveRun], args: argparse.Namespace) -> None:
    print(
        f"\nRate sweep: {args.sweep_seconds:g} s at each rate, a fresh service for each"
        + ("; service and sender at SCHED_FIFO" if args.realtime else "")
    )
    print(
        "\n| IMU rate | sent | lost | kept up | latency p50 | p99 | max | sender late p99 "
        "| service CPU |"
    )
    print("|---:|---:|---:|---|---:|---:|---:|---:|---:|")
    for run in runs:
        row = run.row()
        print(
            f"| {run.rate:g} Hz | {run.sent} | {run.lost} | {'yes' if run.kept_up else 'no'} | "
            f"{row['p50 ms']:.3f} ms | {row['p99 ms']:.3f} ms | {row['max ms']:.2f} ms | "
            f"{row['sender late p99 ms']:.3f} ms | {row['service CPU %']:.0f} % |"
        )
    best = highest_sustained(runs)
    if best is None:
        print("\nhighest rate without loss (and kept up): none of these")
    else:
        print(
            f"\nhighest rate without loss (and kept up): {best.rate:g} Hz "
            f"(p99 {best.percentile(99):.3f} ms)"
        )


def print_replay(replayed: dict[str, float], args: argparse.Namespace) -> None:
    messages = replayed["messages"]
    print(
        f"\nReplay of a {args.replay_seconds:g} s 1 kHz tlog ({messages:.0f} messages, "
        f"{replayed['MB']:.1f} MB), wall s, medians of {args.rounds} interleaved rounds"
    )
    print("\n| | wall s | messages/s | × pymavlink's parse (rounds' range) |")
    print("|---|---:|---:|---:|")
    print(
        f"| `mavest replay FILE --out-tlog OUT` (whole command) | "
        f"{replayed['mavest replay s']:.2f} | {messages / replayed['mavest replay s']:,.0f} | "
        f"**{replayed['ratio']:.2f}** ({replayed['ratio min']:.2f}–{replayed['ratio max']:.2f}) |"
    )
    print(
        f"| the same with `--one-by-one` | {replayed['one by one s']:.2f} | "
        f"{messages / replayed['one by one s']:,.0f} | {replayed['one by one ratio']:.2f} |"
    )
    print(
        f"| pymavlink `recv_msg` loop | {replayed['pymavlink parse s']:.2f} | "
        f"{messages / replayed['pymavlink parse s']:,.0f} | 1 |"
    )
    print(f"| `mavest replay` of a 1 s flight (start-up) | {replayed['startup s']:.2f} | | |")


def print_rerun(
    cost: dict[str, float], counted: dict[str, float] | None, args: argparse.Namespace
) -> None:
    print(
        f"\nRerun recording at 1 kHz ({args.rerun_seconds:g} s replay, CPU s of the whole "
        f"command, medians of {args.rounds} interleaved rounds"
        + (
            "; instructions per simulated second under valgrind, between "
            f"{SHORT_SECONDS:g} s and {args.instruction_seconds:g} s flights)"
            if counted
            else ")"
        )
    )
    if counted is None:
        print("\n| replay | CPU s | × without (rounds' range) |")
        print("|---|---:|---:|")
        print(f"| without `--rrd` | {cost['without']:.2f} | 1 |")
        print(
            f"| with `--rrd` ({cost['rrd MB']:.1f} MB) | {cost['with']:.2f} | "
            f"{cost['ratio']:.3f} ({cost['ratio min']:.3f}–{cost['ratio max']:.3f}) |"
        )
        return
    print(
        "\n| replay | CPU s | × without (rounds' range) | instructions / simulated s | × without |"
    )
    print("|---|---:|---:|---:|---:|")
    print(
        f"| without `--rrd` | {cost['without']:.2f} | 1 | "
        f"{counted['without per s'] / 1e6:,.1f} M | 1 |"
    )
    print(
        f"| with `--rrd` ({cost['rrd MB']:.1f} MB) | {cost['with']:.2f} | "
        f"{cost['ratio']:.3f} ({cost['ratio min']:.3f}–{cost['ratio max']:.3f}) | "
        f"{counted['with per s'] / 1e6:,.1f} M | **{counted['ratio']:.4f}** |"
    )
    seconds = counted["seconds"]
    print(
        f"\nInstructions (valgrind --tool=callgrind, all threads), whole commands; the "
        f"{seconds:g} s one twice"
    )
    print(
        f"\n| replay | {SHORT_SECONDS:g} s flight | {seconds:g} s flight | again | repeat "
        f"difference | ({seconds:g} s − {SHORT_SECONDS:g} s) / {seconds - SHORT_SECONDS:g} s |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for name in ("without", "with"):
        long_, again = counted[f"{name} long"], counted[f"{name} again"]
        print(
            f"| {name} `--rrd` | {counted[f'{name} short']:,.0f} | {long_:,.0f} | "
            f"{again:,.0f} | {100.0 * (again - long_) / long_:+.3f} % | "
            f"{counted[f'{name} per s']:,.0f} |"
        )
    print(
        f"| × without | {counted['with short'] / counted['without short']:.4f} | "
        f"{counted['whole ratio']:.4f} | | | **{counted['ratio']:.4f}** |"
    )


if __name__ == "__main__":
    raise SystemExit(main())
