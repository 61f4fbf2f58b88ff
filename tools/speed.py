"""Per-sample cost of mavest beside VQF (C++) and x-io Fusion (C), measured in one run.

    .venv/bin/python tools/speed.py [--seconds 60] [--rate 200] [--rounds 7]

The same simulated flight (mavest.sim) goes through every filter, both ways a
user would call it:

* online: one Python call per sample, as the live service does
  (``Estimator.update``, ``VQF.update``, ``Ahrs.update_no_magnetometer``);
* batch: one call for the whole recording (``mavest.estimate``,
  ``VQF.updateBatch``; Fusion has no batch call).

Each figure is the median over ``--rounds`` interleaved rounds (the machine is
shared and noisy; interleaving keeps the ratios fair), in µs per sample, with
its ratio to VQF's figure of the same kind from the same run. Compilation is
excluded (the numba cache is warmed first).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

from mavest import Estimator, EstimatorConfig, estimate
from mavest.estimator.config import STANDARD_GRAVITY
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--seconds", type=float, default=60.0, help="flight length (s)")
    parser.add_argument("--rate", type=float, default=200.0, help="IMU rate (Hz)")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds")
    args = parser.parse_args(argv)

    data = simulate(args.seconds, args.rate, motion=Motion(), seed=1)
    t, gyro, accel = data.t, data.gyro, data.accel
    # numpy arrays of float64, C-contiguous: what every filter gets
    gyro = np.ascontiguousarray(gyro)
    accel = np.ascontiguousarray(accel)

    contenders: dict[str, tuple[str, Callable[..., None]]] = {
        "mavest Estimator.update": ("online", _online_mavest),
        "mavest estimate()": ("batch", _batch_mavest),
    }
    vqf = _vqf_filters(args.rate)
    if vqf is not None:
        contenders["VQF update (C++)"] = ("online", vqf[0])
        contenders["VQF updateBatch (C++)"] = ("batch", vqf[1])
    fusion = _fusion_filter(args.rate)
    if fusion is not None:
        contenders["Fusion update (C)"] = ("online", fusion)
    if vqf is None or fusion is None:
        print("peers missing: install the dev extras (pip install -e .[dev])", file=sys.stderr)

    _online_mavest(t[:100], gyro[:100], accel[:100])  # compile / load the numba cache
    _batch_mavest(t[:100], gyro[:100], accel[:100])

    times: dict[str, list[float]] = {name: [] for name in contenders}
    for _ in range(args.rounds):
        for name, (_, run) in contenders.items():
            start = time.perf_counter()
            run(t, gyro, accel)
            times[name].append((time.perf_counter() - start) / t.shape[0] * 1e6)

    median = {name: statistics.median(v) for name, v in times.items()}
    reference = {
        "online": median.get("VQF update (C++)"),
        "batch": median.get("VQF updateBatch (C++)"),
    }
    print(
        f"{t.shape[0]} samples at {args.rate:g} Hz, median of {args.rounds} interleaved rounds;"
        f" mavest {EstimatorConfig().variant}"
    )
    print(f"{'filter':<26} {'kind':<7} {'µs/sample':>10} {'× VQF':>7}")
    for name, (kind, _) in contenders.items():
        ref = reference[kind]
        ratio = f"{median[name] / ref:7.2f}" if ref else "      –"
        print(f"{name:<26} {kind:<7} {median[name]:10.2f} {ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
