"""What smoothing costs: time per sample against the filter's, and memory for an hour at 1 kHz.

    .venv/bin/python tools/smooth_cost.py [--seconds 600] [--rate 1000] [--quick]
                                          [--results [FILE]]

On one simulated flight (``mavest.sim.simulate``, 6-D and 9-D) it times
``mavest.estimate`` and ``mavest.smooth`` (the better of two runs each, after a
short warm-up) and prints their times per sample and the ratio. On a shared machine the times
vary; the ratio less so.

Memory: the peak of what each call allocates (``tracemalloc``, which NumPy reports
to), on the flight and on its first half. The peak is linear in the samples
beyond the smoother's blocks of ``mavest.estimator.smoother.BLOCK`` samples, so the
two give it for any length: printed for an hour at ``--rate``, with the inputs
(t, gyro, accel, mag as float64) and the result alone (an ``EstimateSeries``, which
both calls return). --quick: 140 s of flight (many blocks at 1 kHz). --results writes
the tables as the Smoothing section of docs/results.md (or FILE).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from collections.abc import Callable

from mavest import estimate, smooth
from mavest.estimator import EstimateSeries
from mavest.estimator.smoother import BLOCK
from mavest.evaluation import report
from mavest.sim import simulate

GIB = 2**30
HOUR = 3600.0


def peak_bytes(run: Callable[[], EstimateSeries]) -> tuple[int, int]:
    """(peak bytes allocated during the call, bytes of the result it returns)."""
    tracemalloc.start()
    try:
        result = run()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    held = sum(getattr(result, name).nbytes for name in EstimateSeries.__dataclass_fields__)
    return peak, held


def seconds_of(run: Callable[[], object], runs: int = 2) -> float:
    """The shortest of ``runs`` calls (s)."""
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--seconds", type=float, default=600.0, help="flight length (s)")
    parser.add_argument("--rate", type=float, default=1000.0, help="IMU rate (Hz)")
    parser.add_argument("--quick", action="store_true", help="a 140 s flight")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    with report.results_section(args.results, "Smoothing", __file__, argv, __doc__):
        _measure(args)
    return 0


def _measure(args: argparse.Namespace) -> None:
    seconds = 140.0 if args.quick else args.seconds
    data = simulate(seconds, args.rate, seed=1)
    n = len(data.t)
    warm = slice(0, min(n, 2000))
    for mag in (None, data.mag[warm]):
        estimate(data.t[warm], data.gyro[warm], data.accel[warm], mag)
        smooth(data.t[warm], data.gyro[warm], data.accel[warm], mag)
    print(f"{seconds:g} s at {args.rate:g} Hz ({n} samples); smoother blocks of {BLOCK}")
    print("| input | estimate µs/sample | smooth µs/sample | ratio |")
    print("|---|---|---|---|")
    for label, mag in (("6-D", None), ("9-D", data.mag)):
        filtered = seconds_of(lambda mag=mag: estimate(data.t, data.gyro, data.accel, mag))
        smoothed = seconds_of(lambda mag=mag: smooth(data.t, data.gyro, data.accel, mag))
        print(
            f"| {label} | {filtered / n * 1e6:.2f} | {smoothed / n * 1e6:.2f} | "
            f"{smoothed / filtered:.2f} |"
        )

    hour = round(HOUR * args.rate)
    half = n // 2
    print(f"\npeak memory (tracemalloc), 9-D; one hour at {args.rate:g} Hz is {hour} samples")
    print("| call | peak at N/2 | peak at N | per sample | fixed | an hour |")
    print("|---|---|---|---|---|---|")
    held_per_sample = 0.0
    for name, run in (("estimate", estimate), ("smooth", smooth)):
        peaks = []
        for m in (half, n):
            peak, held = peak_bytes(
                lambda run=run, m=m: run(data.t[:m], data.gyro[:m], data.accel[:m], data.mag[:m])
            )
            peaks.append(peak)
            held_per_sample = held / m
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


if __name__ == "__main__":
    sys.exit(main())
