"""The ``mavest`` command line.

Until the live MAVLink service lands, the commands are ``demo`` (the estimator
on a simulated flight, scored against the truth) and ``estimate`` (the same on
a CSV of IMU samples). A user's mistake ends with a one-line message and exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from mavest import __version__
from mavest._jit import cache_is_warm
from mavest.estimator import ConfigError, EstimatorConfig, estimate
from mavest.evaluation.metrics import rmse_deg, signed_heading_error
from mavest.sim import ImuNoise, Motion, simulate


class UsageError(Exception):
    """A mistake in what the user asked for; printed as one line, exit code 2."""


def _load_config(path: Path | None) -> EstimatorConfig:
    if path is None:
        return EstimatorConfig()
    try:
        return EstimatorConfig.from_toml(path)
    except ConfigError as error:
        raise UsageError(str(error)) from None


# --------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------


def _demo(args: argparse.Namespace) -> int:
    config = _load_config(args.config)
    motion = Motion(
        velocity_sigma=0.5,
        velocity_time=2.0,
        burst_magnitude=3.0,
        burst_duration=1.0,
        burst_interval=20.0,
    )
    noise = ImuNoise(gyro_bias_sigma=math.radians(0.5))
    print(
        f"mavest {__version__} demo: a simulated {args.seconds:g} s flight at {args.rate:g} Hz "
        f"(seed {args.seed})\n"
        "  roll ±30°, pitch ±20°, turning; velocity varying by 0.5 m/s, 3 m/s² bursts;\n"
        "  gyro bias about 0.5°/s per axis, white noise of a good MEMS IMU; filter: "
        f"{config.variant}\n"
    )
    data = simulate(args.seconds, args.rate, noise=noise, motion=motion, seed=args.seed)
    if not cache_is_warm():
        print("  (first run: compiling the filter, about a minute; later runs start at once)\n")
    # compile (or load the cache) before timing
    estimate(data.t[:50], data.gyro[:50], data.accel[:50], config=config)
    start = time.perf_counter()
    out = estimate(data.t, data.gyro, data.accel, config=config)
    elapsed = time.perf_counter() - start

    settled = data.t >= 10.0
    heading = np.degrees(signed_heading_error(out.q, data.q_true))
    scores = rmse_deg(out.q, data.q_true, settled)
    euler_error = np.degrees(_wrap(out.euler - _euler(data.q_true)))
    bias_error = np.degrees(np.abs(out.bias[-1] - data.bias_true[-1]))
    bias_sigma = np.degrees(np.sqrt(np.diag(out.cov[-1])[3:]))
    tilt_sigma = np.degrees(np.sqrt(0.5 * (out.cov[:, 0, 0] + out.cov[:, 1, 1])))

    rows = [
        ("tilt (inclination) RMSE", f"{scores['inclination']:.3f}°", "after 10 s"),
        (
            "  its 1σ claimed by the filter",
            f"{np.sqrt(np.mean(tilt_sigma[settled] ** 2)):.3f}°",
            "",
        ),
        ("roll RMSE", f"{_rms(euler_error[settled, 0]):.3f}°", ""),
        ("pitch RMSE", f"{_rms(euler_error[settled, 1]):.3f}°", ""),
        (
            "heading drift",
            f"{_wrap_deg(heading[-1] - heading[0]):.2f}°",
            "over the flight; 6-D: nothing corrects it",
        ),
        ("gyro bias error at the end", _triple(bias_error, "°/s"), "x, y, z"),
        ("  its 1σ claimed by the filter", _triple(bias_sigma, "°/s"), ""),
        ("accelerometer used", f"{100 * out.accel_used.mean():.1f} %", "of samples"),
        ("  inflated as disturbed", f"{100 * np.mean(out.flags & 16 != 0):.1f} %", "χ² gate"),
        ("cost", f"{elapsed / len(data.t) * 1e6:.2f} µs/sample", f"{len(data.t)} samples"),
    ]
    peer = _vqf_inclination(data, settled)
    if peer is not None:
        rows.insert(2, ("  VQF on the same samples", f"{peer:.3f}°", "its defaults"))
    width = max(len(r[0]) for r in rows)
    for label, value, note in rows:
        print(f"  {label:<{width}}  {value:>22}  {note}")
    print("\nEvery number is against the simulator's truth; `make test` checks the math.")
    return 0


def _vqf_inclination(data: object, settled: np.ndarray) -> float | None:
    """VQF's score on the same flight when the package is installed (a dev extra)."""
    try:
        from mavest.evaluation.peers import run_vqf

        q = run_vqf(data.t, data.gyro, data.accel)
    except ImportError:
        return None
    return rmse_deg(q, data.q_true, settled)["inclination"]


def _euler(q: np.ndarray) -> np.ndarray:
    from mavest import so3

    return so3.euler_zyx_from_quats(q)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _wrap_deg(angle: float) -> float:
    return float((angle + 180.0) % 360.0 - 180.0)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values * values)))


def _triple(values: np.ndarray, unit: str) -> str:
    return ", ".join(f"{v:.3f}" for v in values) + f" {unit}"


# --------------------------------------------------------------------------
# estimate (CSV)
# --------------------------------------------------------------------------


def _estimate_csv(args: argparse.Namespace) -> int:
    config = _load_config(args.config)
    path: Path = args.input
    if path.is_dir():
        raise UsageError(f"{path}: is a directory, not a CSV file")
    if not path.is_file():
        raise UsageError(f"{path}: no such file")
    try:
        table = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
    except ValueError as error:
        raise UsageError(f"{path}: not a CSV of numbers ({error})") from None
    if table.shape[1] != 7:
        raise UsageError(
            f"{path}: expected 7 columns t, gx, gy, gz, ax, ay, az; found {table.shape[1]}"
        )
    out = estimate(table[:, 0], table[:, 1:4], table[:, 4:7], config=config)
    euler = np.degrees(out.euler)
    sigma = np.degrees(np.sqrt(np.stack([out.cov[:, i, i] for i in range(3)], axis=1)))
    result = np.column_stack([out.t, out.q, euler, np.degrees(out.bias), sigma, out.flags])
    header = (
        "t,qw,qx,qy,qz,roll_deg,pitch_deg,yaw_deg,bias_x_dps,bias_y_dps,bias_z_dps,"
        "sigma_x_deg,sigma_y_deg,sigma_z_deg,flags"
    )
    destination = sys.stdout if args.output is None else args.output
    try:
        np.savetxt(destination, result, delimiter=",", header=header, comments="", fmt="%.9g")
    except OSError as error:
        raise UsageError(f"{args.output}: {error.strerror}") from None
    return 0


# --------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mavest",
        description="Attitude and gyro-bias estimation for MAVLink vehicles: an error-state "
        "Kalman filter on SO(3) × R³ that says how sure it is.",
    )
    parser.add_argument("--version", action="version", version=f"mavest {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    demo = commands.add_parser(
        "demo",
        help="run the estimator on a simulated flight and print its accuracy",
        description="Simulate a flight (attitude, gyro bias, noisy IMU samples), run the "
        "estimator on it and compare with the truth; VQF runs beside it when installed.",
    )
    demo.add_argument("--seconds", type=float, default=120.0, help="flight length (default 120)")
    demo.add_argument("--rate", type=float, default=200.0, help="IMU rate in Hz (default 200)")
    demo.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    demo.add_argument("--config", type=Path, help="TOML file with an [estimator] table")
    demo.set_defaults(handler=_demo)

    csv = commands.add_parser(
        "estimate",
        help="estimate attitude for a CSV of IMU samples",
        description="Read t (s), gyro (rad/s) and specific force (m/s²), body FRD, as CSV "
        "columns t,gx,gy,gz,ax,ay,az; write the quaternion (body → NED), roll/pitch/yaw, "
        "gyro bias, 1σ and flags per sample.",
    )
    csv.add_argument("input", type=Path, help="CSV file ('#' starts a comment line)")
    csv.add_argument("-o", "--output", type=Path, help="output CSV (default: standard output)")
    csv.add_argument("--config", type=Path, help="TOML file with an [estimator] table")
    csv.set_defaults(handler=_estimate_csv)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "seconds", 1.0) <= 0 or getattr(args, "rate", 1.0) <= 0:
        print("mavest: --seconds and --rate must be positive", file=sys.stderr)
        return 2
    try:
        return args.handler(args)
    except UsageError as error:
        print(f"mavest: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
