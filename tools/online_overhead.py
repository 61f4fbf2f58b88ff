"""What ``Estimator.update`` costs beyond the filter step: a sample in, an estimate out.

    .venv/bin/python tools/online_overhead.py [--seconds 10] [--rate 200] [--rounds 25]
                                              [--markdown] [--results [FILE]]

The same simulated flight goes through ``Estimator.update`` one sample at a time
(with the sample's vectors as float64 arrays, as tuples of floats, as arrays with
a magnetometer and a known acceleration, and with its time stuck, so that every
step is skipped at almost no cost) and through ``update_batch``, one compiled loop
over the same steps: the batch's per-sample time is the step's own cost, the
difference the online call's overhead. Where the extension ``_online`` is built,
the Python path (numba's entry point, what runs without it) is measured beside it.
Each figure is the fastest of ``--rounds`` interleaved rounds (the least disturbed
by a shared machine), in µs per sample. --results writes the table (as Markdown) as
the Online overhead section of docs/results.md (or FILE).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from mavest import Estimator
from mavest.estimator import estimator as estimator_module
from mavest.evaluation import report
from mavest.sim import Motion, simulate


def _estimator(python_path: bool) -> Estimator:
    """A new estimator, on the Python path if asked (else the one mavest chose)."""
    chosen = estimator_module._ONLINE
    if python_path:
        from mavest.estimator.online import PythonOnline

        estimator_module._ONLINE = PythonOnline
    try:
        return Estimator()
    finally:
        estimator_module._ONLINE = chosen


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=10.0, help="flight length (s)")
    parser.add_argument("--rate", type=float, default=200.0, help="IMU rate (Hz)")
    parser.add_argument("--rounds", type=int, default=25, help="interleaved rounds")
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    markdown = args.markdown or args.results is not None

    data = simulate(args.seconds, args.rate, motion=Motion(), seed=1)
    t = data.t
    gyro, accel = np.ascontiguousarray(data.gyro), np.ascontiguousarray(data.accel)
    mag, linear_accel = np.ascontiguousarray(data.mag), np.ascontiguousarray(data.linear_accel)
    gyro_tuples = [tuple(v) for v in gyro.tolist()]
    accel_tuples = [tuple(v) for v in accel.tolist()]
    n = t.shape[0]

    def arrays(estimator: Estimator) -> None:
        update = estimator.update
        for i in range(n):
            update(t[i], gyro[i], accel[i])

    def tuples(estimator: Estimator) -> None:
        update = estimator.update
        for i in range(n):
            update(t[i], gyro_tuples[i], accel_tuples[i])

    def aided(estimator: Estimator) -> None:
        update = estimator.update
        for i in range(n):
            update(t[i], gyro[i], accel[i], mag[i], linear_accel[i])

    def skipped(estimator: Estimator) -> None:
        update = estimator.update
        update(t[0], gyro[0], accel[0])
        for i in range(n):  # time not increasing: each step only says so, at almost no cost
            update(t[0], gyro[i], accel[i])

    t_stuck = np.full(n, t[0])

    paths = ["extension", "python"] if estimator_module._COMPILED is not None else ["python"]
    runs: dict[str, tuple[Callable[[], None], str]] = {}
    for path in paths:
        python_path = path == "python"
        runs[f"update, arrays ({path})"] = (lambda p=python_path: arrays(_estimator(p)), "6-D")
        runs[f"update, tuples ({path})"] = (lambda p=python_path: tuples(_estimator(p)), "6-D")
        runs[f"update, mag + aid ({path})"] = (lambda p=python_path: aided(_estimator(p)), "9-D")
        runs[f"update, skipped ({path})"] = (lambda p=python_path: skipped(_estimator(p)), "skip")
    runs["update_batch"] = (lambda: Estimator().update_batch(t, gyro, accel), "6-D")
    runs["update_batch, mag + aid"] = (
        lambda: Estimator().update_batch(t, gyro, accel, mag, linear_accel),
        "9-D",
    )
    runs["update_batch, skipped"] = (lambda: Estimator().update_batch(t_stuck, gyro, accel), "skip")

    for run, _ in runs.values():  # load the compiled code
        run()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, (run, _) in runs.items():
            start = time.perf_counter()
            run()
            times[name].append((time.perf_counter() - start) / n * 1e6)
    fastest = {name: min(v) for name, v in times.items()}
    batch = {
        "6-D": fastest["update_batch"],
        "9-D": fastest["update_batch, mag + aid"],
        "skip": fastest["update_batch, skipped"],
    }

    with report.results_section(args.results, "Online overhead", __file__, argv, __doc__):
        print(f"{n} samples at {args.rate:g} Hz, fastest of {args.rounds} interleaved rounds")
        if markdown:
            print("\n| call | µs/sample | − batch |\n|---|---:|---:|")
        else:
            print(f"{'call':<32} {'µs/sample':>10} {'− batch':>9}")
        for name, (_, kind) in runs.items():
            overhead = fastest[name] - batch[kind]
            if markdown:
                print(f"| {name} | {fastest[name]:.2f} | {overhead:.2f} |")
            else:
                print(f"{name:<32} {fastest[name]:10.2f} {overhead:9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
