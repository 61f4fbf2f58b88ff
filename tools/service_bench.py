"""The service's speed: live latency, replay throughput beside pymavlink, Rerun's cost.

    .venv/bin/python tools/service_bench.py [--seconds 30] [--rate 1000] [--replay-seconds 300]

Live: the simulated vehicle streams RAW_IMU at ``--rate`` over loopback UDP to
``mavest run udpin:…`` (a separate process, as users run it) and times every
IMU packet sent → ATTITUDE received, matched by ``time_boot_ms``. Replay: a
1 kHz simulated flight (``--replay-seconds``) written to a tlog, then the whole
command ``mavest replay FILE --out-tlog OUT`` timed, beside pymavlink reading every
message of the same file (``recv_msg`` until the end) and the same command with
``--one-by-one``, in interleaved rounds; and the command on a 1 s flight, which is
its start-up (imports, the compiled kernels loaded from the cache).
Rerun: a ``--rerun-seconds`` replay with and without ``--rrd`` in interleaved rounds,
sample by sample as the live service works (``--one-by-one``), CPU time (user +
system) of the whole command; the ratio is what recording costs.
``--instructions`` adds the same comparison counted in instructions under valgrind
(callgrind, every thread of the replay, Rerun's encoder and writer included), which a
busy machine does not disturb: 2 s and ``--instruction-seconds`` flights with and
without ``--rrd``, the cost per simulated second taken between the two lengths so that
start-up (imports, the numba cache, opening the recording) falls out; the longer pair
is run twice to show the count repeats. ``--only rerun`` (or live, replay) runs one part.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from mavest.service.process import MAVEST, ServiceProcess, free_port
from mavest.sim.vehicle import AUTOPILOTS, stream_flight, write_flight_tlog

PARTS = ("live", "replay", "rerun")


def live(seconds: float, rate: float) -> dict[str, float]:
    port = free_port(socket.SOCK_DGRAM)
    service = ServiceProcess(f"udpin:127.0.0.1:{port}")
    try:
        report = asyncio.run(stream_flight(f"udpout:127.0.0.1:{port}", rate, seconds=seconds))
    finally:
        service.stop()
    return {
        "sent": report.sent,
        "answered %": 100.0 * report.answered_fraction,
        "p50 ms": report.latency_p50_ms,
        "p99 ms": report.latency_p99_ms,
        "max ms": report.latency_max_ms,
    }


def _wall_seconds(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
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
    subprocess.run(startup, check=True, capture_output=True)  # a warm numba cache
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="live stream length")
    parser.add_argument("--rate", type=float, default=1000.0, help="live IMU rate, Hz")
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
    args = parser.parse_args()
    parts = args.only or list(PARTS)
    if "live" in parts:
        result = live(args.seconds, args.rate)
        print(f"\nLive, {args.rate:g} Hz RAW_IMU over loopback UDP for {args.seconds:g} s")
        print("| sent | answered | latency p50 | p99 | max |")
        print("|---:|---:|---:|---:|---:|")
        print(
            f"| {result['sent']:.0f} | {result['answered %']:.2f} % | {result['p50 ms']:.3f} ms | "
            f"{result['p99 ms']:.3f} ms | {result['max ms']:.2f} ms |"
        )
    with tempfile.TemporaryDirectory() as workdir:
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


def print_replay(replayed: dict[str, float], args: argparse.Namespace) -> None:
    messages = replayed["messages"]
    print(
        f"\nReplay of a {args.replay_seconds:g} s 1 kHz tlog ({messages:.0f} messages, "
        f"{replayed['MB']:.1f} MB), wall s, medians of {args.rounds} interleaved rounds"
    )
    print("| | wall s | messages/s | × pymavlink's parse (rounds' range) |")
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
        print("| replay | CPU s | × without (rounds' range) |")
        print("|---|---:|---:|")
        print(f"| without `--rrd` | {cost['without']:.2f} | 1 |")
        print(
            f"| with `--rrd` ({cost['rrd MB']:.1f} MB) | {cost['with']:.2f} | "
            f"{cost['ratio']:.3f} ({cost['ratio min']:.3f}–{cost['ratio max']:.3f}) |"
        )
        return
    print("| replay | CPU s | × without (rounds' range) | instructions / simulated s | × without |")
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
        f"| replay | {SHORT_SECONDS:g} s flight | {seconds:g} s flight | again | repeat "
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
