"""What smoothing costs: time per sample against the filter's, and memory for an hour at 1 kHz.

    .venv/bin/python tools/smooth_cost.py [--seconds 600] [--rate 1000] [--quick]
                                          [--replay-seconds 3600] [--results [FILE]]

On one simulated flight (``mavest.sim.simulate``, 6-D and 9-D) it times
``mavest.estimate``, ``mavest.smooth`` and ``smooth_blocks`` (the same estimates a
block at a time, its forward pass run again instead of held; its blocks are taken and
dropped) (the better of two runs each, after a short warm-up) and prints their times
per sample and the ratios to the filter's. On a shared machine the times vary; the
ratios less so.

Memory: the peak of what each call allocates (``tracemalloc``, which NumPy reports
to), on the flight and on its first half. The peak is linear in the samples
beyond the smoother's blocks of ``mavest.estimator.smoother.BLOCK`` samples, so the
two give it for any length: printed for an hour at ``--rate``, with the inputs
(t, gyro, accel, mag as float64) and the result alone (an ``EstimateSeries``, which
estimate and smooth return).

And what a user's command holds: ``mavest replay LOG -q`` and ``mavest replay LOG
--smooth -q``, each a process of its own, on the tlog of a simulated flight of
``--replay-seconds`` (an hour by default; JSBSim's aircraft as ``mavest demo`` flies
it, RAW_IMU at ``--rate``, ATTITUDE every 20th sample): their peak resident memory
(the kernel's count, everything the process holds) and wall time (started from a small
Python process, which counts it). ``--replay-seconds
0`` leaves this out. --quick: 140 s of flight (many blocks at 1 kHz), and a 140 s
replay. --results writes the tables as the Smoothing section of docs/results.md (or
FILE).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

from mavest import estimate, smooth
from mavest.estimator import EstimateSeries
from mavest.estimator.smoother import BLOCK, smooth_blocks
from mavest.evaluation import report
from mavest.service.process import MAVEST
from mavest.sim import simulate
from mavest.sim.vehicle import write_autopilot_tlog

GIB = 2**30
HOUR = 3600.0
QUICK = 140.0  # s of flight with --quick
# the replay's memory target: an hour's log at 1 kHz smoothed in this much
TARGET_BYTES = 1.5e9


def peak_bytes(run: Callable[[], EstimateSeries | None]) -> tuple[int, int]:
    """(peak bytes allocated during the call, bytes of the result it returns: 0 for
    none)."""
    tracemalloc.start()
    try:
        result = run()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    if result is None:
        return peak, 0
    held = sum(getattr(result, name).nbytes for name in EstimateSeries.__dataclass_fields__)
    return peak, held


def smooth_by_blocks(*args: object) -> None:
    """smooth_blocks run through, each block taken and dropped."""
    for _ in smooth_blocks(*args):  # type: ignore[arg-type]
        pass


# Runs the command given and prints its peak resident memory (kB): from a process this
# small, as a child's count starts from what its parent held when it forked (this tool
# holds hundreds of MB of flight when it starts the replays).
_PEAK_OF_CHILD = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
if done.returncode:
    sys.exit((done.stderr.decode(errors="replace").strip().splitlines() or ["?"])[-1])
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def command_peak(command: list[str]) -> tuple[int, float]:
    """(peak resident bytes, wall s) of ``command`` run to its end in a process of its
    own; RuntimeError with its last line if it fails."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", _PEAK_OF_CHILD, *command], capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(f"{' '.join(command[3:6])} … failed: {done.stderr.strip()}")
    return int(done.stdout) * 1024, wall  # (Linux counts kB)


def seconds_of(run: Callable[[], object], runs: int = 2) -> float:
    """The shortest of ``runs`` calls (s)."""
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=600.0, help="flight length (s)")
    parser.add_argument("--rate", type=float, default=1000.0, help="IMU rate (Hz)")
    parser.add_argument("--quick", action="store_true", help="a 140 s flight and replay")
    parser.add_argument(
        "--replay-seconds",
        type=float,
        default=HOUR,
        help="the replayed log's flight (s); 0: no replays",
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    with report.results_section(args.results, "Smoothing", __file__, argv, __doc__):
        _measure(args)
    return 0


def _measure(args: argparse.Namespace) -> None:
    seconds = QUICK if args.quick else args.seconds
    data = simulate(seconds, args.rate, seed=1)
    n = len(data.t)
    warm = slice(0, min(n, 2000))
    for mag in (None, data.mag[warm]):
        for run in (estimate, smooth, smooth_by_blocks):
            run(data.t[warm], data.gyro[warm], data.accel[warm], mag)
    print(f"{seconds:g} s at {args.rate:g} Hz ({n} samples); smoother blocks of {BLOCK}")
    print(
        "| input | estimate µs/sample | smooth µs/sample | ratio | "
        "smooth_blocks µs/sample | ratio |"
    )
    print("|---|---|---|---|---|---|")
    for label, mag in (("6-D", None), ("9-D", data.mag)):
        times = [
            seconds_of(lambda run=run, mag=mag: run(data.t, data.gyro, data.accel, mag))
            for run in (estimate, smooth, smooth_by_blocks)
        ]
        filtered, smoothed, by_blocks = times
        print(
            f"| {label} | {filtered / n * 1e6:.2f} | {smoothed / n * 1e6:.2f} | "
            f"{smoothed / filtered:.2f} | {by_blocks / n * 1e6:.2f} | "
            f"{by_blocks / filtered:.2f} |"
        )

    hour = round(HOUR * args.rate)
    half = n // 2
    print(f"\npeak memory (tracemalloc), 9-D; one hour at {args.rate:g} Hz is {hour} samples")
    print("| call | peak at N/2 | peak at N | per sample | fixed | an hour |")
    print("|---|---|---|---|---|---|")
    held_per_sample = 0.0
    for name, run in (
        ("estimate", estimate),
        ("smooth", smooth),
        ("smooth_blocks (blocks dropped)", smooth_by_blocks),
    ):
        peaks = []
        for m in (half, n):
            peak, held = peak_bytes(
                lambda run=run, m=m: run(data.t[:m], data.gyro[:m], data.accel[:m], data.mag[:m])
            )
            peaks.append(peak)
            held_per_sample = max(held_per_sample, held / m)
        slope = (peaks[1] - peaks[0]) / (n - half)
        fixed = peaks[1] - slope * n
        an_hour = fixed + slope * hour
        print(
            f"| {name} | {peaks[0] / 2**20:.0f} MiB | {peaks[1] / 2**20:.0f} MiB | "
            f"{slope:.0f} B | {fixed / 2**20:.0f} MiB | "
            f"{an_hour / GIB:.2f} GiB ({an_hour / 1e9:.2f} GB) |"
        )
    inputs = sum(a.nbytes for a in (data.t, data.gyro, data.accel, data.mag)) / n
    print(
        f"\nof which the result (EstimateSeries): {held_per_sample:.0f} B a sample, "
        f"{held_per_sample * hour / GIB:.2f} GiB an hour; the inputs (float64): "
        f"{inputs:.0f} B a sample, {inputs * hour / GIB:.2f} GiB an hour"
    )
    replay_seconds = QUICK if args.quick else args.replay_seconds
    if replay_seconds > 0:
        _measure_replays(replay_seconds, args.rate)


def _measure_replays(seconds: float, rate: float) -> None:
    with tempfile.TemporaryDirectory() as folder:
        log = Path(folder) / "flight.tlog"
        write_autopilot_tlog(log, seconds, rate)
        size = log.stat().st_size
        rows = []
        for label, options in (("", []), (" --smooth", ["--smooth"])):
            peak, wall = command_peak([*MAVEST, "replay", str(log), "-q", *options])
            rows.append((f"`mavest replay LOG{label} -q`", peak, wall))
    samples = round(seconds * rate) + 1
    print(
        f"\nthe whole command, a process of its own: a simulated flight's tlog, {seconds:g} s, "
        f"RAW_IMU at {rate:g} Hz ({samples} samples), ATTITUDE every 20th "
        f"({size / 1e6:.0f} MB)"
    )
    print("| command | peak resident memory | wall s |")
    print("|---|---|---|")
    for label, peak, wall in rows:
        print(f"| {label} | {peak / GIB:.2f} GiB ({peak / 1e9:.2f} GB) | {wall:.1f} |")
    smoothed = rows[1][1]
    met = "within" if smoothed <= TARGET_BYTES else "**beyond**"
    print(f"\nsmoothed: {smoothed / 1e9:.2f} GB, {met} the {TARGET_BYTES / 1e9:g} GB aimed at")


if __name__ == "__main__":
    sys.exit(main())
