"""The service's speed: live latency, replay throughput beside pymavlink, Rerun's cost.

    .venv/bin/python tools/service_bench.py [--seconds 30] [--rate 1000] [--replay-seconds 60]

Live: the simulated vehicle streams RAW_IMU at ``--rate`` over loopback UDP to
``mavest run udpin:…`` (a separate process, as users run it) and times every
IMU packet sent → ATTITUDE received, matched by ``time_boot_ms``. Replay: a
1 kHz simulated flight written to a tlog, then the whole command
``mavest replay FILE --out-tlog OUT`` timed, beside pymavlink reading every
message of the same file (``recv_msg`` until the end), in the same run.
Rerun: the same replay with and without ``--rrd`` in interleaved rounds, CPU
time (user + system) of the whole command; the ratio is what recording costs.
``--only rerun`` (or live, replay) runs one part.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import tempfile
import time
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


def replay_throughput(seconds: float, workdir: Path) -> dict[str, float]:
    flight = workdir / "flight_1khz.tlog"
    write_flight_tlog(flight, seconds, 1000.0, AUTOPILOTS["ardupilot"], seed=1)
    out = workdir / "out.tlog"
    subprocess.run([*MAVEST, "replay", str(flight), "-q"], check=True, capture_output=True)
    start = time.perf_counter()
    subprocess.run(
        [*MAVEST, "replay", str(flight), "--out-tlog", str(out), "-q"],
        check=True,
        capture_output=True,
    )
    ours = time.perf_counter() - start
    start = time.perf_counter()
    connection = mavutil.mavlink_connection(str(flight), robust_parsing=True)
    messages = 0
    while connection.recv_msg() is not None:
        messages += 1
    theirs = time.perf_counter() - start
    return {
        "messages": messages,
        "mavest replay s": ours,
        "pymavlink parse s": theirs,
        "ratio": theirs / ours,
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
    plain = [*MAVEST, "replay", str(flight), "-q"]
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="live stream length")
    parser.add_argument("--rate", type=float, default=1000.0, help="live IMU rate, Hz")
    parser.add_argument("--replay-seconds", type=float, default=60.0, help="1 kHz tlog length")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds for Rerun's cost")
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
            print_replay(replay_throughput(args.replay_seconds, Path(workdir)), args)
        if "rerun" in parts:
            print_rerun(rerun_cost(args.replay_seconds, Path(workdir), args.rounds), args)
    return 0


def print_replay(replayed: dict[str, float], args: argparse.Namespace) -> None:
    rate_ours = replayed["messages"] / replayed["mavest replay s"]
    rate_theirs = replayed["messages"] / replayed["pymavlink parse s"]
    print(f"\nReplay of a {args.replay_seconds:g} s 1 kHz tlog ({replayed['messages']} messages)")
    print("| | wall s | messages/s | vs pymavlink parse |")
    print("|---|---:|---:|---:|")
    print(
        f"| `mavest replay --out-tlog` (whole command) | {replayed['mavest replay s']:.2f} | "
        f"{rate_ours:,.0f} | {replayed['ratio']:.2f}× |"
    )
    print(
        f"| pymavlink `recv_msg` loop | {replayed['pymavlink parse s']:.2f} | "
        f"{rate_theirs:,.0f} | 1× |"
    )


def print_rerun(cost: dict[str, float], args: argparse.Namespace) -> None:
    print(
        f"\nRerun recording at 1 kHz ({args.replay_seconds:g} s replay, CPU s of the whole "
        f"command, medians of {args.rounds} interleaved rounds)"
    )
    print("| replay | CPU s | × without (rounds' range) |")
    print("|---|---:|---:|")
    print(f"| without `--rrd` | {cost['without']:.2f} | 1 |")
    print(
        f"| with `--rrd` ({cost['rrd MB']:.1f} MB) | {cost['with']:.2f} | "
        f"{cost['ratio']:.3f} ({cost['ratio min']:.3f}–{cost['ratio max']:.3f}) |"
    )


if __name__ == "__main__":
    raise SystemExit(main())
