"""Live latency and replay throughput of the service, beside pymavlink's plain parse.

    .venv/bin/python tools/latency.py [--seconds 30] [--rate 1000] [--replay-seconds 60]

Live: the simulated vehicle streams RAW_IMU at ``--rate`` over loopback UDP to
``mavest run udpin:…`` (a separate process, as users run it) and times every
IMU packet sent → ATTITUDE received, matched by ``time_boot_ms``. Replay: a
1 kHz simulated flight written to a tlog, then the whole command
``mavest replay FILE --out-tlog OUT`` timed, beside pymavlink reading every
message of the same file (``recv_msg`` until the end), in the same run.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from pymavlink import mavutil

from mavest.sim.vehicle import AUTOPILOTS, stream_flight, write_flight_tlog

MAVEST = [sys.executable, "-m", "mavest.cli"]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def live(seconds: float, rate: float) -> dict[str, float]:
    port = _free_udp_port()
    process = subprocess.Popen(
        [*MAVEST, "run", f"udpin:127.0.0.1:{port}"],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    ready = threading.Event()

    def watch() -> None:
        assert process.stderr is not None
        for line in process.stderr:
            if "listening" in line:
                ready.set()

    threading.Thread(target=watch, daemon=True).start()
    if not ready.wait(180):  # a cold numba cache compiles first
        process.kill()
        raise SystemExit("mavest run did not start")
    try:
        report = asyncio.run(stream_flight(f"udpout:127.0.0.1:{port}", rate, seconds=seconds))
    finally:
        process.send_signal(2)
        process.wait(30)
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="live stream length")
    parser.add_argument("--rate", type=float, default=1000.0, help="live IMU rate, Hz")
    parser.add_argument("--replay-seconds", type=float, default=60.0, help="1 kHz tlog length")
    args = parser.parse_args()
    result = live(args.seconds, args.rate)
    print(f"\nLive, {args.rate:g} Hz RAW_IMU over loopback UDP for {args.seconds:g} s")
    print("| sent | answered | latency p50 | p99 | max |")
    print("|---:|---:|---:|---:|---:|")
    print(
        f"| {result['sent']:.0f} | {result['answered %']:.2f} % | {result['p50 ms']:.3f} ms | "
        f"{result['p99 ms']:.3f} ms | {result['max ms']:.2f} ms |"
    )
    with tempfile.TemporaryDirectory() as workdir:
        replayed = replay_throughput(args.replay_seconds, Path(workdir))
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
