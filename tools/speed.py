"""Per-sample cost of mavest beside VQF (C++) and x-io Fusion (C), measured in one run.

    .venv/bin/python tools/speed.py [--seconds 60] [--rate 200 [400 1000 ...]] [--rounds 7]
                                    [--markdown] [--results [FILE]]

The same simulated flight (mavest.sim) goes through every filter, both ways a
user would call it:

* online: one Python call per sample, as the live service does
  (``Estimator.update``, ``VQF.update``, ``Ahrs.update_no_magnetometer``);
* batch: one call for the whole recording (``mavest.estimate``,
  ``VQF.updateBatch``; Fusion has no batch call).

Each figure is the median over ``--rounds`` interleaved rounds (the machine is
shared and noisy; interleaving keeps the ratios fair), in µs per sample, with
its ratio to VQF's figure of the same kind from the same run. Compilation is
excluded (the numba cache is warmed first). One table per ``--rate``;
--results writes them (as Markdown) as the Speed section of docs/results.md (or FILE).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

from mavest import Estimator, EstimatorConfig, estimate
from mavest.estimator.config import STANDARD_GRAVITY
from mavest.evaluation import report
from mavest.sim import Motion, simulate


def _online_mavest(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
    est = Estimator()
    update = est.update
    for i in range(t.shape[0]):
        update(t[i], gyro[i], accel[i])


def _batch_mavest(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
    estimate(t, gyro, accel)


def _vqf_filters(rate: float) -> tuple[Callable[..., None], Callable[..., None]] | None:
    try:
        from vqf import VQF
    except ImportError:
        return None

    def online(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        f = VQF(1.0 / rate)
        update = f.update
        for i in range(t.shape[0]):
            update(gyro[i], accel[i])

    def batch(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        VQF(1.0 / rate).updateBatch(gyro, accel)

    return online, batch


def _fusion_filter(rate: float) -> Callable[..., None] | None:
    try:
        import imufusion
    except ImportError:
        return None

    def online(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        settings = imufusion.AhrsSettings()
        settings.convention = imufusion.CONVENTION_NED  # FRD body, specific force in g
        settings.sample_rate = rate
        ahrs = imufusion.Ahrs()
        ahrs.set_settings(settings)
        ahrs.set_sample_period(1.0 / rate)
        gyro_deg = np.degrees(gyro)
        accel_g = accel / STANDARD_GRAVITY
        update = ahrs.update_no_magnetometer
        for i in range(t.shape[0]):
            update(gyro_deg[i], accel_g[i])

    return online


def measure(seconds: float, rate: float, rounds: int) -> tuple[int, dict[str, tuple[str, float]]]:
    """The flight's sample count, and per filter its kind and median µs per sample."""
    data = simulate(seconds, rate, motion=Motion(), seed=1)
    t = data.t
    # numpy arrays of float64, C-contiguous: what every filter gets
    gyro = np.ascontiguousarray(data.gyro)
    accel = np.ascontiguousarray(data.accel)

    contenders: dict[str, tuple[str, Callable[..., None]]] = {
        "mavest Estimator.update": ("online", _online_mavest),
        "mavest estimate()": ("batch", _batch_mavest),
    }
    vqf = _vqf_filters(rate)
    if vqf is not None:
        contenders["VQF update (C++)"] = ("online", vqf[0])
        contenders["VQF updateBatch (C++)"] = ("batch", vqf[1])
    fusion = _fusion_filter(rate)
    if fusion is not None:
        contenders["Fusion update (C)"] = ("online", fusion)
    if vqf is None or fusion is None:
        print("peers missing: install the dev extras (pip install -e .[dev])", file=sys.stderr)

    _online_mavest(t[:100], gyro[:100], accel[:100])  # compile / load the numba cache
    _batch_mavest(t[:100], gyro[:100], accel[:100])

    times: dict[str, list[float]] = {name: [] for name in contenders}
    for _ in range(rounds):
        for name, (_, run) in contenders.items():
            start = time.perf_counter()
            run(t, gyro, accel)
            times[name].append((time.perf_counter() - start) / t.shape[0] * 1e6)
    return t.shape[0], {
        name: (kind, statistics.median(times[name])) for name, (kind, _) in contenders.items()
    }


def print_table(
    samples: int, rate: float, rounds: int, medians: dict[str, tuple[str, float]], markdown: bool
) -> None:
    """One rate's figures, each beside VQF's of the same kind."""
    reference = {
        kind: medians[name][1] if name in medians else None
        for kind, name in (("online", "VQF update (C++)"), ("batch", "VQF updateBatch (C++)"))
    }
    print(
        f"{samples} samples at {rate:g} Hz, median of {rounds} interleaved rounds; "
        f"mavest {EstimatorConfig().variant}"
    )
    if markdown:
        print("\n| filter | kind | µs/sample | × VQF |\n|---|---|---:|---:|")
    else:
        print(f"{'filter':<26} {'kind':<7} {'µs/sample':>10} {'× VQF':>7}")
    for name, (kind, median) in medians.items():
        ref = reference[kind]
        ratio = f"{median / ref:.2f}" if ref else "–"
        if markdown:
            print(f"| {name} | {kind} | {median:.2f} | {ratio} |")
        else:
            print(f"{name:<26} {kind:<7} {median:10.2f} {ratio:>7}")


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=60.0, help="flight length (s)")
    parser.add_argument(
        "--rate", type=float, nargs="+", default=[200.0], help="IMU rates (Hz), one table each"
    )
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds")
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    markdown = args.markdown or args.results is not None

    measured = [(rate, *measure(args.seconds, rate, args.rounds)) for rate in args.rate]
    with report.results_section(args.results, "Speed", __file__, argv, __doc__):
        for i, (rate, samples, medians) in enumerate(measured):
            if i:
                print()
            print_table(samples, rate, args.rounds, medians, markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
