"""The ``mavest`` command line.

``run`` serves a live MAVLink link, ``replay`` runs a telemetry log through the
same pipeline, ``sim`` is a simulated vehicle (JSBSim) that streams like a
flight controller or writes a tlog with its true attitude, ``demo`` flies that
vehicle through the whole pipeline and scores it, ``estimate`` reads a CSV.
A user's mistake ends with a one-line message and exit code 2, never a
traceback.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from mavest import __version__
from mavest._jit import cache_is_warm
from mavest.estimator import ConfigError, estimate
from mavest.mavlink.links import LinkError
from mavest.mavlink.messages import IMU_MESSAGES
from mavest.mavlink.signing import KEY_ENVIRONMENT_VARIABLE, Signing
from mavest.mavlink.tlog import TlogError
from mavest.service.config import ServiceConfig
from mavest.service.runners import Outputs, replay, run_live
from mavest.service.signals import stop_on_signals
from mavest.viz.viewer import VIEWER_MODES, ViewerError

log = logging.getLogger("mavest")

EXAMPLES = """examples:
  mavest demo                                    simulated flight → replay → .rrd, scored
  mavest run udpin:0.0.0.0:14550                 listen where a flight controller sends
  mavest run tcp:127.0.0.1:5760 --out udpout:127.0.0.1:14551 --rrd flight.rrd
  mavest run /dev/ttyACM0 --baud 921600 --config configs/ardupilot.toml
  mavest replay flight.tlog --out-tlog ours.tlog --rrd ours.rrd
  mavest sim udpout:127.0.0.1:14550 --rate 500   a simulated vehicle for `mavest run udpin:…`
"""


class UsageError(Exception):
    """A mistake in what the user asked for; printed as one line, exit code 2."""


def _load_config(args: argparse.Namespace) -> ServiceConfig:
    """The configuration file, then the command-line options over it."""
    path: Path | None = getattr(args, "config", None)
    try:
        config = ServiceConfig.from_toml(path) if path is not None else ServiceConfig()
        input_changes: dict[str, Any] = {}
        output_changes: dict[str, Any] = {}
        for option, table, key in (
            ("imu", input_changes, "imu"),
            ("instance", input_changes, "imu_instance"),
            ("system", input_changes, "system"),
            ("request_rate", input_changes, "request_rate"),
            ("settle", input_changes, "settle_time"),
            ("sysid", output_changes, "system_id"),
            ("compid", output_changes, "component_id"),
            ("attitude_rate", output_changes, "attitude_rate"),
        ):
            value = getattr(args, option, None)
            if value is not None:
                table[key] = value
        return config.replace(input=input_changes, output=output_changes)
    except ConfigError as error:
        raise UsageError(str(error)) from None


def _setup_logging(args: argparse.Namespace) -> None:
    level = logging.INFO
    if getattr(args, "quiet", False):
        level = logging.WARNING
    if getattr(args, "verbose", False):
        level = logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("mavest: %(message)s"))
    root = logging.getLogger("mavest")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _say_compiling() -> None:
    if not cache_is_warm():
        log.info("first run: compiling the filter (about a minute; later runs start at once)")


# --------------------------------------------------------------------------
# run / replay
# --------------------------------------------------------------------------


def _outputs(args: argparse.Namespace) -> Outputs:
    mode, url = None, None
    if args.rerun is not None:
        mode, _, url = args.rerun.partition("=")
        if mode not in VIEWER_MODES or (url and mode != "connect"):
            raise UsageError(f"--rerun {args.rerun}: use spawn, connect, connect=URL or serve")
    return Outputs(
        tlog=args.out_tlog,
        rrd=args.rrd,
        rerun=mode,
        rerun_url=url or None,
        rerun_bind=args.rerun_bind,
        rerun_port=args.rerun_port,
        rerun_web_port=args.rerun_web_port,
    )


def _signing(args: argparse.Namespace, config: ServiceConfig) -> Signing | None:
    """The signing key and policy: --signing-key, else the environment, else the file."""
    settings = config.signing
    if args.require_signed:
        settings = dataclasses.replace(settings, require_signed=True)
    try:
        return settings.resolve(os.environ, args.signing_key)
    except ConfigError as error:
        raise UsageError(str(error)) from None


def _run(args: argparse.Namespace) -> int:
    config = _load_config(args)
    signing = _signing(args, config)
    _say_compiling()
    outputs = _outputs(args)
    try:
        report = asyncio.run(
            run_live(
                args.connection, config, tuple(args.out), outputs, baud=args.baud, signing=signing
            )
        )
    except (LinkError, TlogError, ViewerError) as error:
        raise UsageError(str(error)) from None
    print(report.summary())
    return 0


def _replay(args: argparse.Namespace) -> int:
    config = _load_config(args)
    if args.speed is not None and args.speed <= 0:
        raise UsageError("--speed must be positive (1 = real time)")
    _say_compiling()
    outputs = _outputs(args)

    async def main() -> Any:
        with stop_on_signals() as stop:
            return await replay(
                args.tlog, config, outputs, speed=args.speed, stop=stop, fast=not args.one_by_one
            )

    try:
        report = asyncio.run(main())
    except (TlogError, ViewerError) as error:
        raise UsageError(str(error)) from None
    print(report.summary())
    if not report.pipeline.streams:
        return 1
    return 0


# --------------------------------------------------------------------------
# sim / demo
# --------------------------------------------------------------------------


def _sim(args: argparse.Namespace) -> int:
    from mavest.sim.vehicle import AUTOPILOTS, stream_flight, write_flight_tlog

    if args.rate < 1 or args.rate > 2000:
        raise UsageError("--rate must be 1–2000 Hz")
    autopilot = AUTOPILOTS[args.autopilot]
    if args.tlog is not None:
        if args.seconds is None:
            raise UsageError("--tlog needs --seconds (how long a flight to write)")
        summary = write_flight_tlog(args.tlog, args.seconds, args.rate, autopilot, args.seed)
        print(summary)
        return 0
    try:
        report = asyncio.run(
            stream_flight(args.connection, args.rate, autopilot, args.seed, seconds=args.seconds)
        )
    except LinkError as error:
        raise UsageError(str(error)) from None
    print(report.describe())
    if args.report is not None:
        args.report.write_text(report.to_json())
    return 0


def _demo(args: argparse.Namespace) -> int:
    from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

    output_dir: Path = args.output_dir
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot create {output_dir}: {error.strerror}") from None
    flight = output_dir / "flight.tlog"
    print(
        f"mavest {__version__} demo: a {args.seconds:g} s Cessna 172 flight from JSBSim, turning "
        f"under its autopilot,\nstreaming ArduPilot RAW_IMU at {args.rate:g} Hz with noise, "
        "bias and quantisation, replayed through mavest.\n"
    )
    start = time.perf_counter()
    print(write_flight_tlog(flight, args.seconds, args.rate, AUTOPILOTS["ardupilot"], args.seed))
    print(f"  ({time.perf_counter() - start:.1f} s)\n")
    config = _load_config(args)
    _say_compiling()
    outputs = Outputs(tlog=output_dir / "mavest.tlog", rrd=output_dir / "mavest.rrd")
    report = asyncio.run(replay(flight, config, outputs, progress=False))
    print(report.summary())
    print(
        "\nThe truth is the flight model's attitude (SIMSTATE in the tlog). Open the recording "
        f"with `rerun {outputs.rrd}`;\nplot ours against the truth in any tlog tool from "
        f"{outputs.tlog}."
    )
    return 0


# --------------------------------------------------------------------------
# estimate (CSV)
# --------------------------------------------------------------------------


def _estimate_csv(args: argparse.Namespace) -> int:
    config = _load_config(args).estimator
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


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML with [estimator], [input], [output]"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="say more")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def _add_stream_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("streams and output (override the config file)")
    group.add_argument(
        "--imu",
        choices=("auto", "all", *IMU_MESSAGES),
        help="IMU message to estimate from (default auto: the best one each vehicle sends)",
    )
    group.add_argument("--instance", type=int, metavar="N", help="IMU instance (default: lowest)")
    group.add_argument(
        "--system", type=int, metavar="ID", help="follow this vehicle only (default: all)"
    )
    group.add_argument(
        "--sysid", type=int, metavar="ID", help="mavest's system id (default: the vehicle's)"
    )
    group.add_argument(
        "--compid", type=int, metavar="ID", help="mavest's component id (default 191)"
    )
    group.add_argument(
        "--attitude-rate",
        type=float,
        metavar="HZ",
        help="ATTITUDE rate (default 0: one per IMU sample)",
    )
    group.add_argument("--rrd", type=Path, metavar="PATH", help="save a Rerun recording (.rrd)")
    group.add_argument(
        "--rerun",
        metavar="MODE",
        help="live Rerun viewer: spawn (a window here), connect[=URL] (a running viewer, "
        "default rerun+http://127.0.0.1:9876/proxy) or serve (a web viewer for a browser)",
    )
    group.add_argument(
        "--rerun-bind",
        default="127.0.0.1",
        metavar="ADDRESS",
        help="address a spawned or served viewer listens on (default 127.0.0.1: this "
        "machine only; 0.0.0.0 exposes it to the network)",
    )
    group.add_argument(
        "--rerun-port", type=int, default=9876, metavar="PORT", help="its gRPC port (default 9876)"
    )
    group.add_argument(
        "--rerun-web-port",
        type=int,
        default=9090,
        metavar="PORT",
        help="the served web viewer's HTTP port (default 9090)",
    )
    group.add_argument(
        "--out-tlog",
        type=Path,
        metavar="PATH",
        help="write a tlog of every input message plus mavest's ATTITUDE",
    )


def _add_signing_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "MAVLink 2 signing",
        "With a key, mavest signs everything it sends and drops signed input whose "
        "signature or timestamp fails (a different key, a replay); unsigned input is "
        "accepted unless --require-signed. Without a key, nothing is signed or checked.",
    )
    group.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE",
        help="the key: a file of 32 raw bytes (as ArduPilot stores it), or 64 hex digits, "
        "or any other text as a passphrase, whose SHA-256 is the key (as MAVProxy's "
        f"`signing setup PASSPHRASE`). Default: ${KEY_ENVIRONMENT_VARIABLE} (hex or "
        "passphrase), else [signing] key_file of the config",
    )
    group.add_argument(
        "--require-signed",
        action="store_true",
        default=None,
        help="drop unsigned input (MAVLink 1 included); needs a key",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mavest",
        description="Attitude and gyro-bias estimation for MAVLink vehicles: an error-state "
        "Kalman filter on SO(3) × R³ that says how sure it is.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mavest {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    run = commands.add_parser(
        "run",
        help="estimate live from a MAVLink link and send ATTITUDE back",
        description="Read IMU messages (RAW_IMU, SCALED_IMU/2/3, HIGHRES_IMU) from a "
        "MAVLink link, estimate attitude and gyro bias per vehicle, and send ATTITUDE and "
        "ATTITUDE_QUATERNION (and a HEARTBEAT at 1 Hz) back on the link and to every --out. "
        "Runs until Ctrl-C or SIGTERM, then flushes its files and exits 0.",
        epilog="CONNECTION: udpin:HOST:PORT (listen; replies go to the sender), "
        "udpout:HOST:PORT, tcp:HOST:PORT (reconnects), tcpin:HOST:PORT, or a serial device "
        "(/dev/ttyUSB0, with --baud).",
    )
    run.add_argument("connection", metavar="CONNECTION", help="where the IMU data comes from")
    run.add_argument(
        "--out",
        action="append",
        default=[],
        metavar="CONNECTION",
        help="also send estimates here (repeatable)",
    )
    run.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    run.add_argument(
        "--request-rate",
        type=float,
        metavar="HZ",
        help="ask the flight controller for the IMU message at this rate "
        "(MAV_CMD_SET_MESSAGE_INTERVAL; default: config, 0 = don't ask)",
    )
    _add_stream_options(run)
    _add_signing_options(run)
    _add_common(run)
    run.set_defaults(handler=_run)

    rep = commands.add_parser(
        "replay",
        help="run a telemetry log (.tlog) through the estimator",
        description="Replay a tlog through the same pipeline as `run`: as fast as possible, "
        "or paced with --speed. Prints a summary: samples, rate, gaps, rejected samples, and "
        "accuracy against the log's own ATTITUDE (and SIMSTATE, a simulator's truth).",
    )
    rep.add_argument("tlog", type=Path, metavar="FILE.tlog")
    rep.add_argument("--speed", type=float, help="pace the replay (1 = real time; default: fast)")
    rep.add_argument(
        "--one-by-one",
        action="store_true",
        help="take every record singly, as the live service does (the same result, in "
        "several times the time; without it, clean stretches of the log go through a "
        "compiled path, unless --speed paces the replay)",
    )
    rep.add_argument(
        "--settle", type=float, metavar="S", help="seconds before accuracy is scored (default 10)"
    )
    _add_stream_options(rep)
    _add_common(rep)
    rep.set_defaults(handler=_replay)

    sim = commands.add_parser(
        "sim",
        help="a simulated vehicle (JSBSim) streaming IMU like a flight controller",
        description="Fly a Cessna 172 in JSBSim under its autopilot (turns, light turbulence) "
        "and send its IMU as the autopilot would (ArduPilot RAW_IMU or PX4 HIGHRES_IMU, with "
        "noise, bias and quantisation) over MAVLink in real time, with HEARTBEAT and the true "
        "attitude as SIMSTATE; honours SET_MESSAGE_INTERVAL. It scores the ATTITUDE it gets "
        "back. With --tlog, writes the flight to a file instead, as fast as it can.",
    )
    sim.add_argument(
        "connection",
        nargs="?",
        default="udpout:127.0.0.1:14550",
        metavar="CONNECTION",
        help="where to stream (default udpout:127.0.0.1:14550)",
    )
    sim.add_argument("--rate", type=float, default=200.0, help="IMU rate in Hz (default 200)")
    sim.add_argument(
        "--autopilot", choices=("ardupilot", "px4"), default="ardupilot", help="message flavour"
    )
    sim.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    sim.add_argument("--seed", type=int, default=1, help="flight and noise seed (default 1)")
    sim.add_argument("--tlog", type=Path, metavar="PATH", help="write a tlog instead of streaming")
    sim.add_argument("--report", type=Path, metavar="PATH", help="write the score as JSON")
    sim.set_defaults(handler=_sim)

    demo = commands.add_parser(
        "demo",
        help="fly the simulated vehicle through the whole pipeline and score it",
        description="Write a simulated flight to a tlog (with the true attitude), replay it "
        "through mavest into a Rerun recording and an output tlog, and print the accuracy "
        "against the truth.",
    )
    demo.add_argument("--seconds", type=float, default=120.0, help="flight length (default 120)")
    demo.add_argument("--rate", type=float, default=400.0, help="IMU rate in Hz (default 400)")
    demo.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    demo.add_argument(
        "--output-dir",
        type=Path,
        default=Path("demo-output"),
        help="where the tlogs and the .rrd go (default ./demo-output)",
    )
    _add_common(demo)
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
    _add_common(csv)
    csv.set_defaults(handler=_estimate_csv)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "seconds", 1.0) is not None and getattr(args, "seconds", 1.0) <= 0:
        print("mavest: --seconds must be positive", file=sys.stderr)
        return 2
    if getattr(args, "rate", 1.0) <= 0:
        print("mavest: --rate must be positive", file=sys.stderr)
        return 2
    _setup_logging(args)
    try:
        return int(args.handler(args))
    except UsageError as error:
        print(f"mavest: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader of our output went away (`mavest … | head`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
