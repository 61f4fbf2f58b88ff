"""The ``mavest`` command line.

``run`` serves a live MAVLink link, ``replay`` runs a log (a telemetry log, or an
autopilot's onboard log: ArduPilot .bin, PX4 .ulg) through the same pipeline,
``fleet`` replays many logs on Dask into one table (:mod:`mavest.fleet`), ``sim``
is a simulated vehicle (JSBSim) that streams like a flight controller or writes a
tlog with its true attitude, ``demo`` flies that vehicle through the whole
pipeline and scores it, ``estimate`` reads a CSV.

Exit codes, the same for every command:

- 0: done (``run`` stopped by Ctrl-C or SIGTERM is done);
- 1: the input held no IMU stream to estimate from (``run`` and ``replay`` alike);
- 2: a mistake in what was asked, an unusable input, or an output that cannot be
  written (standard output included): one line, never a traceback;
- 130: interrupted before the end (``replay``, ``fleet``, ``sim --tlog``, ``demo``,
  ``estimate``);
  what was written so far is valid.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import io
import itertools
import logging
import math
import os
import stat
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn, Protocol

import numpy as np
from numba.core import event as numba_event

from mavest import __version__
from mavest.estimator import AccelUnitWarning, ConfigError, EstimatorConfig, StepFlags, estimate
from mavest.estimator.config import MAX_ANGULAR_RATE
from mavest.mavlink.links import LinkError
from mavest.mavlink.messages import IMU_MESSAGES
from mavest.mavlink.signing import KEY_ENVIRONMENT_VARIABLE, Signing
from mavest.mavlink.tlog import TlogError
from mavest.onboard import OnboardLogError
from mavest.paths import InputFiles, OutputPathError, check_outputs, write_atomically
from mavest.service.config import ServiceConfig
from mavest.service.estimates_table import EstimatesTableError, csv_rows, table_format
from mavest.service.log_repeats import UNLIMITED, RepeatLimiter
from mavest.service.runners import Outputs, RunReport, replay, run_live
from mavest.service.signals import sigterm_interrupts, stop_on_signals
from mavest.viz.viewer import VIEWER_MODES, ViewerError

log = logging.getLogger("mavest")

EXAMPLES = """examples:
  mavest demo                                    simulated flight → replay → .rrd, scored
  mavest run udpin:0.0.0.0:14550                 listen where a flight controller sends
  mavest run tcp:127.0.0.1:5760 --out udpout:127.0.0.1:14551 --rrd flight.rrd
  mavest run /dev/ttyACM0 --baud 921600 --config configs/ardupilot.toml
  mavest replay flight.tlog --out-tlog ours.tlog --rrd ours.rrd
  mavest replay 00000042.BIN --rrd ours.rrd      an ArduPilot onboard log (or a PX4 .ulg)
  mavest fleet logs/ --out fleet.parquet         every log in logs/ on Dask: one table
  mavest sim udpout:127.0.0.1:14550 --rate 500   a simulated vehicle for `mavest run udpin:…`
"""


EXIT_NO_IMU = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """A mistake in what the user asked for; printed as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse's parser, but a mistake is one line: what is wrong and where to look
    (argparse's own prints the whole usage first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _number(
    low: float, high: float = math.inf, *, whole: bool = False, above: bool = False
) -> Callable[[str], float]:
    """An option's type: a finite number in [low, high] (``above``: > low; ``whole``: an
    integer), so that --baud -5, --speed nan or --instance -1 are refused by name."""
    if whole:
        described = f"a whole number from {low:.0f}" + (
            f" to {high:.0f}" if high < math.inf else " up"
        )
    else:
        described = f"a number {'above' if above else 'from'} {low:g}" + (
            f" to {high:g}" if high < math.inf else ""
        )

    def parse(text: str) -> float:
        try:
            value: float = int(text) if whole else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {described}") from None
        if not math.isfinite(value) or value < low or value > high or (above and value == low):
            raise argparse.ArgumentTypeError(f"{text} is not {described}")
        return value

    return parse


def _table_path(text: str) -> Path:
    """--estimates: a .csv or a .parquet file (Parquet only with pyarrow installed)."""
    try:
        table_format(text)
    except EstimatesTableError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return Path(text)


_POSITIVE = _number(0.0, above=True)
_NON_NEGATIVE = _number(0.0)
_ID = _number(1, 255, whole=True)
_PORT = _number(1, 65535, whole=True)
_SEED = _number(0, 2**32 - 1, whole=True)
# A simulated flight written to a file: a day of it at 2 kHz is about 20 GB of tlog,
# beyond which a length is a typing slip that would fill the disk.
MAX_FLIGHT_SECONDS = 86_400.0
_FLIGHT_SECONDS = _number(0.0, MAX_FLIGHT_SECONDS, above=True)


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


def _say(text: str, end: str = "\n") -> None:
    """Write to standard output now: one that cannot be written (a full disk) is a
    :class:`UsageError`; a reader gone away (``| head``) is left to :func:`main`."""
    try:
        print(text, end=end, flush=True)
    except BrokenPipeError:
        raise
    except OSError as error:
        _silence_stdout()  # what is still buffered would fail again at the exit
        raise UsageError(f"cannot write to standard output: {error.strerror or error}") from None


def _tolerant_stdout() -> None:
    """Standard output escapes what its encoding cannot write, as standard error does: a
    file name that is no text in it (a Linux name is bytes; ``caf\xe9.tlog`` under a
    UTF-8 locale) prints as ``caf\udce9.tlog`` instead of ending the run in a traceback
    at its last line."""
    if isinstance(sys.stdout, io.TextIOWrapper) and sys.stdout.errors == "strict":
        sys.stdout.reconfigure(errors="backslashreplace")


def _silence_stdout() -> None:
    """Point standard output at the null device: the interpreter's last flush of what
    could not be written then succeeds instead of printing a traceback."""
    with contextlib.suppress(OSError, ValueError, io.UnsupportedOperation):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _setup_logging(args: argparse.Namespace) -> None:
    level = logging.INFO
    if getattr(args, "quiet", False):
        level = logging.WARNING
    if getattr(args, "verbose", False):
        level = logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("mavest: %(message)s"))
    REPEATS.reset()
    handler.addFilter(REPEATS)
    root = logging.getLogger("mavest")
    root.handlers[:] = [handler]
    root.setLevel(level)
    # The service says this itself, one line a stream (pipeline.report_accel_unit);
    # Python's own warning would add a second with a source line in it.
    warnings.simplefilter("ignore", AccelUnitWarning)
    root.propagate = False


class _CompileWatch(numba_event.Listener):
    """Says, once, when numba starts compiling (a first run on a machine, or after an
    upgrade), whichever path gets there first; and adds up the time it takes, which
    the summary leaves out of the throughput. Kernels loaded from the cache raise no
    compile event."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._depth = 0
        self._started = 0.0
        self._said = False

    def on_start(self, event: numba_event.Event) -> None:
        if self._depth == 0:
            self._started = time.perf_counter()
            if not self._said:
                self._said = True
                log.info(
                    "compiling the filter (first run, about a minute; later runs start at once)"
                )
        self._depth += 1

    def on_end(self, event: numba_event.Event) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._started


# log lines that repeat one event, held back past a few (counted, and told at the end)
REPEATS = RepeatLimiter()
COMPILING = _CompileWatch()
numba_event.register("numba:compile", COMPILING)


def _refuse_overlaps(
    inputs: dict[str, str | Path | None] | InputFiles, outputs: dict[str, str | Path | None]
) -> None:
    try:
        check_outputs(inputs, outputs)
    except OutputPathError as error:
        raise UsageError(str(error)) from None


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
        estimates=args.estimates,
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


def _output_paths(args: argparse.Namespace) -> dict[str, str | Path | None]:
    return {"--out-tlog": args.out_tlog, "--rrd": args.rrd, "--estimates": args.estimates}


def _finish(report: RunReport, compiled_before: float) -> int:
    """Print the summary; the exit code of a run or replay (see the module's docstring).
    ``compiled_before``: COMPILING's seconds when the run began (what was compiled
    before it, as a demo's simulator, is not the run's time)."""
    report.compile_seconds = COMPILING.seconds - compiled_before
    REPEATS.report(log)
    _say(report.summary())
    if report.interrupted:
        return EXIT_INTERRUPTED
    return 0 if report.pipeline.streams else EXIT_NO_IMU


def _run(args: argparse.Namespace) -> int:
    config = _load_config(args)
    if args.out_only:
        if not args.out:
            raise UsageError("--out-only needs an --out link to send the estimates to")
        config = config.replace(output={"reply_on_input": False})
    signing = _signing(args, config)
    device = args.connection if args.connection.startswith("/") else None
    _refuse_overlaps(
        {
            "the --config file": args.config,
            "the signing key": args.signing_key or config.signing.key_file or None,
            "the serial device": device.split(",")[0] if device else None,
        },
        _output_paths(args),
    )
    outputs = _outputs(args)
    compiled_before = COMPILING.seconds
    try:
        report = asyncio.run(
            run_live(
                args.connection, config, tuple(args.out), outputs, baud=args.baud, signing=signing
            )
        )
    except (LinkError, TlogError, ViewerError, OutputPathError) as error:
        raise UsageError(str(error)) from None
    # stopped by Ctrl-C or SIGTERM: the way a service ends, not an interruption
    report.interrupted = False
    return _finish(report, compiled_before)


def _replay(args: argparse.Namespace) -> int:
    config = _load_config(args)
    _refuse_overlaps(
        {"the log being replayed": args.tlog, "the --config file": args.config}, _output_paths(args)
    )
    outputs = _outputs(args)
    compiled_before = COMPILING.seconds

    async def main() -> RunReport:
        with stop_on_signals() as stop:

            async def serve_on(report: RunReport) -> None:
                # the served web viewer holds the recording: it goes when mavest does
                report.compile_seconds = COMPILING.seconds - compiled_before
                REPEATS.report(log)
                _say(report.summary())
                log.info("replay done; the web viewer serves the recording until Ctrl-C")
                await stop.wait()

            return await replay(
                args.tlog,
                config,
                outputs,
                speed=args.speed,
                stop=stop,
                fast=not args.one_by_one,
                linger=serve_on,
                smooth=args.smooth,
            )

    try:
        report = asyncio.run(main())
    except (TlogError, OnboardLogError, ViewerError, OutputPathError) as error:
        raise UsageError(str(error)) from None
    if report.lingered:  # the summary was printed before serving; Ctrl-C ended the serving
        return 0 if report.pipeline.streams else EXIT_NO_IMU
    return _finish(report, compiled_before)


# --------------------------------------------------------------------------
# fleet
# --------------------------------------------------------------------------


# The failed logs a fleet run names on standard error, each once (the table has all).
_FAILED_LOGS_SAID = 20


def _fleet(args: argparse.Namespace) -> int:
    try:
        from mavest.fleet.cluster import FleetError, run_fleet
    except ImportError:
        raise UsageError("mavest fleet needs Dask: pip install 'mavest[fleet]'") from None
    from mavest.fleet.inputs import FleetInputError, expand, local_paths, output_names
    from mavest.fleet.rows import LogTask
    from mavest.fleet.table import write_table

    if args.scheduler is not None and args.workers is not None:
        raise UsageError("--workers sizes the local cluster; --scheduler's has its own workers")
    config = _load_config(args)
    try:
        logs, empty = expand(args.logs)
    except FleetInputError as error:
        raise UsageError(str(error)) from None
    for line in empty:
        log.warning("%s", line)
    if not logs:
        raise UsageError("no log to replay")
    inputs: dict[str, str | Path | None] = {"the --config file": args.config}
    inputs.update((f"the log {path}", path) for path in local_paths(logs))
    tasks = [LogTask.of(name, config) for name in logs]
    if args.out_dir is not None:  # (first: it makes the folder --out may be in)
        tasks = _with_outputs(tasks, args.out_dir, args.out, inputs, output_names(logs))
    _refuse_overlaps(inputs, {"--out": args.out})
    workers = args.workers or len(os.sched_getaffinity(0))
    try:
        result = run_fleet(tasks, args.scheduler, workers, verbose=args.verbose)
    except FleetError as error:
        raise UsageError(str(error)) from None
    try:
        write_table(args.out, result.rows)
    except OSError as error:
        raise UsageError(f"cannot write {args.out}: {error.strerror or error}") from None
    failed = [row for row in result.rows if row["status"] == "error"]
    for row in failed[:_FAILED_LOGS_SAID]:
        message = row["error"]
        line = message if row["path"] in message else f"{row['path']}: {message}"
        log.warning("%s", line, extra={UNLIMITED: True})
    if len(failed) > _FAILED_LOGS_SAID:
        more = len(failed) - _FAILED_LOGS_SAID
        log.warning("and %d more with an error: the table's error column says why", more)
    REPEATS.report(log)
    if result.interrupted:
        print(
            f"mavest: interrupted: wrote the {result.done} of {result.total} logs that "
            f"finished to {args.out}",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    failed_logs = len({row["path"] for row in failed})
    _say(
        f"{result.total} log{'s' if result.total != 1 else ''} replayed: "
        f"{result.total - failed_logs} ok, {failed_logs} with an error (the table's error "
        f"column); wrote {args.out}"
    )
    return 0


def _with_outputs(
    tasks: list[Any],
    out_dir: Path,
    table: Path,
    inputs: dict[str, str | Path | None],
    names: list[str],
) -> list[Any]:
    """The tasks with each log's recording and estimates table in ``out_dir`` (made if
    missing, and removed again if the outputs are refused), named after the log; refused
    if one is an input or the table (through a link too)."""
    missing = [folder for folder in (out_dir, *out_dir.parents) if not folder.exists()]
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot create {out_dir}: {error.strerror}") from None
    read = InputFiles({**inputs, "the --out table": table})
    planned = []
    try:
        for task, name in zip(tasks, names, strict=True):
            rrd = out_dir.absolute() / f"{name}.rrd"
            estimates = out_dir.absolute() / f"{name}.estimates{table.suffix.lower()}"
            _refuse_overlaps(read, {"--out-dir's recording": rrd, "--out-dir's table": estimates})
            planned.append(dataclasses.replace(task, rrd=str(rrd), estimates=str(estimates)))
    except UsageError:
        for folder in missing:  # (the deepest first; empty: nothing was written)
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    return planned


# --------------------------------------------------------------------------
# sim / demo
# --------------------------------------------------------------------------


def _sim(args: argparse.Namespace) -> int:
    # (the simulator is loaded only by the commands that fly it: replay starts sooner)
    from mavest.sim.flight import SimulatorMissingError

    try:
        return _simulate(args)
    except (SimulatorMissingError, TlogError) as error:  # (TlogError: --tlog not writable)
        raise UsageError(str(error)) from None


def _simulate(args: argparse.Namespace) -> int:
    from mavest.sim.vehicle import AUTOPILOTS, stream_flight, write_flight_tlog

    _refuse_overlaps({}, {"--tlog": args.tlog, "--report": args.report})
    autopilot = AUTOPILOTS[args.autopilot]
    if args.tlog is not None:
        if args.seconds is None:
            raise UsageError("--tlog needs --seconds (how long a flight to write)")
        if args.seconds > MAX_FLIGHT_SECONDS:  # (a file's flight: bounded as demo's)
            raise UsageError(f"--tlog takes --seconds up to {MAX_FLIGHT_SECONDS:g}")
        summary = write_flight_tlog(args.tlog, args.seconds, args.rate, autopilot, args.seed)
        _say(summary)
        return 0
    try:
        report = asyncio.run(
            stream_flight(args.connection, args.rate, autopilot, args.seed, seconds=args.seconds)
        )
    except LinkError as error:
        raise UsageError(str(error)) from None
    _say(report.describe())
    if args.report is not None:
        write_atomically(args.report, report.to_json().encode())
    return 0


def _demo(args: argparse.Namespace) -> int:
    from mavest.sim.flight import SimulatorMissingError
    from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

    config = _load_config(args)  # (a mistake in it is said before the flight is flown)
    output_dir: Path = args.output_dir
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot create {output_dir}: {error.strerror}") from None
    flight = output_dir / "flight.tlog"
    outputs = Outputs(tlog=output_dir / "mavest.tlog", rrd=output_dir / "mavest.rrd")
    _refuse_overlaps(
        {"the --config file": args.config},
        {"flight.tlog": flight, "mavest.tlog": outputs.tlog, "mavest.rrd": outputs.rrd},
    )
    _say(
        f"mavest {__version__} demo: a {args.seconds:g} s Cessna 172 flight from JSBSim, turning "
        f"under its autopilot,\nstreaming ArduPilot RAW_IMU at {args.rate:g} Hz with noise, "
        "bias and quantisation, replayed through mavest.\n"
    )
    start = time.perf_counter()
    try:
        autopilot = AUTOPILOTS["ardupilot"]
        made = write_flight_tlog(flight, args.seconds, args.rate, autopilot, args.seed)
    except (SimulatorMissingError, TlogError) as error:
        raise UsageError(str(error)) from None
    _say(made)
    _say(f"  ({time.perf_counter() - start:.1f} s)\n")
    compiled_before = COMPILING.seconds  # (the simulator's kernels: not the replay's time)
    try:
        report = asyncio.run(replay(flight, config, outputs, progress=False))
    except (TlogError, ViewerError, OutputPathError) as error:
        raise UsageError(str(error)) from None
    report.compile_seconds = COMPILING.seconds - compiled_before
    REPEATS.report(log)
    _say(report.summary())
    _say(
        "\nThe truth is the flight model's attitude (SIMSTATE in the tlog). Open the recording "
        f"with `rerun {outputs.rrd}`;\nplot ours against the truth in any tlog tool from "
        f"{outputs.tlog}."
    )
    return 0


# --------------------------------------------------------------------------
# estimate (CSV)
# --------------------------------------------------------------------------


CSV_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")


def _read_imu_csv(path: Path) -> np.ndarray:
    """The CSV's samples as columns t, gx, gy, gz, ax, ay, az. A first line that is not
    numbers is a header: these seven names in any order, saying which column is which.
    A row that is not seven numbers (a file cut off while written, a damaged line) is
    left out and said in one line; a file of which most rows are not is refused."""
    try:
        mode = path.stat().st_mode
    except OSError:
        mode = 0  # (said by the read below)
    if stat.S_ISDIR(mode):
        raise UsageError(f"{path}: is a directory, not a CSV file")
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):  # (/dev/zero would be read without end)
        raise UsageError(f"{path}: is a device: a CSV is read from a file or a pipe")
    try:
        text = path.read_text(encoding="utf-8-sig")  # (a spreadsheet's byte-order mark)
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise UsageError(f"{path}: not a text file (a CSV of numbers is expected)") from None
    except OSError as error:
        raise UsageError(f"cannot read {path}: {error.strerror}") from None
    rows = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.startswith("#")
    ]
    order = list(range(len(CSV_COLUMNS)))
    if rows and not _is_number(rows[0][1].split(",")[0]):
        order = _header_order(path, rows.pop(0)[1])
    if not rows:
        raise UsageError(f"{path}: no samples (expected rows of {', '.join(CSV_COLUMNS)})")
    lines = [line for _, line in rows]
    try:
        table = np.loadtxt(lines, delimiter=",", ndmin=2)
    except ValueError as error:
        # not every row is numbers of one count: keep the rows that are a sample
        sample = [_is_sample_row(line) for line in lines]
        bad = [row for row, good in zip(rows, sample, strict=True) if not good]
        if not bad:  # numbers Python reads and NumPy does not ("1_000")
            raise UsageError(f"{path}: not a CSV of numbers ({error})") from None
        number, line = bad[0]
        if 2 * len(bad) > len(rows):  # not a damaged file of samples: another format
            raise UsageError(
                f"{path}: not a CSV of numbers: {len(bad)} of {len(rows)} rows are not the "
                f"{len(CSV_COLUMNS)} numbers {', '.join(CSV_COLUMNS)} (the first at line "
                f"{number}: {line[:60]!r})"
            ) from None
        log.warning(
            "%s: %d of %d rows left out, not %d numbers (the first at line %d: %r)",
            path,
            len(bad),
            len(rows),
            len(CSV_COLUMNS),
            number,
            line[:60],
        )
        table = np.loadtxt(list(itertools.compress(lines, sample)), delimiter=",", ndmin=2)
    if table.shape[1] != len(CSV_COLUMNS):
        raise UsageError(
            f"{path}: expected 7 columns {', '.join(CSV_COLUMNS)}; found {table.shape[1]}"
        )
    return table[:, order]


def _is_sample_row(line: str) -> bool:
    """Whether a CSV line is one sample: :data:`CSV_COLUMNS`' count of numbers (a ``#``
    and what follows it are a comment, as ``np.loadtxt`` takes them)."""
    fields = line.split("#", 1)[0].split(",")
    return len(fields) == len(CSV_COLUMNS) and all(_is_number(field) for field in fields)


def _header_order(path: Path, line: str) -> list[int]:
    """Where each of :data:`CSV_COLUMNS` is, from a header line that names each once.
    Any other header is refused: guessing would read one sensor's columns as another's."""
    names = [name.strip().lower() for name in line.split(",")]
    if sorted(names) == sorted(CSV_COLUMNS):
        return [names.index(column) for column in CSV_COLUMNS]
    understood = [name for name in names if name in CSV_COLUMNS]
    unknown = [repr(name) for name in names if name not in CSV_COLUMNS]
    wrong = [f"not understood: {', '.join(unknown)}"] if unknown else []
    twice = sorted({name for name in understood if understood.count(name) > 1})
    if twice:
        wrong.append(f"named twice: {', '.join(twice)}")
    missing = [column for column in CSV_COLUMNS if column not in names]
    if missing:
        wrong.append(f"missing: {', '.join(missing)}")
    raise UsageError(
        f"{path}: the first line is neither numbers nor a header of the columns "
        f"{', '.join(CSV_COLUMNS)} (in any order): "
        + "; ".join(wrong)
        + f"; understood: {', '.join(understood) or 'none'}"
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _estimate_csv(args: argparse.Namespace) -> int:
    with sigterm_interrupts():  # SIGTERM as Ctrl-C: -o is then written whole or not at all
        return _estimate_table(args)


# The columns `estimate` writes, in order.
ESTIMATE_COLUMNS = (
    *("t", "qw", "qx", "qy", "qz", "roll_deg", "pitch_deg", "yaw_deg"),
    *("bias_x_dps", "bias_y_dps", "bias_z_dps", "sigma_x_deg", "sigma_y_deg", "sigma_z_deg"),
    "flags",
)


def _estimate_table(args: argparse.Namespace) -> int:
    config = _load_config(args).estimator
    _refuse_overlaps(
        {"the CSV being read": args.input, "the --config file": args.config}, {"-o": args.output}
    )
    # -o's suffix names the format: .parquet is Parquet (checked before any work), any
    # other name CSV
    parquet = args.output is not None and args.output.suffix.lower() == ".parquet"
    if parquet:
        try:
            table_format(args.output)
        except EstimatesTableError as error:
            raise UsageError(str(error)) from None
    table = _read_imu_csv(args.input)
    try:
        out = estimate(table[:, 0], table[:, 1:4], table[:, 4:7], config=config)
    except ValueError as error:  # samples that cannot be estimated from (a wrong unit)
        raise UsageError(f"{args.input}: {error}") from None
    euler = np.degrees(out.euler)
    sigma = np.degrees(np.sqrt(np.stack([out.cov[:, i, i] for i in range(3)], axis=1)))
    # (flags as the estimates table's: 64-bit integers)
    flags = out.flags.astype(np.int64)
    columns = [out.t, *out.q.T, *euler.T, *np.degrees(out.bias).T, *sigma.T, flags]
    if args.output is None:
        for piece in _csv_pieces(columns):
            _say(piece.decode(), end="")
    else:
        try:
            write_atomically(
                args.output, _parquet_bytes(columns) if parquet else _csv_pieces(columns)
            )
        except OSError as error:
            raise UsageError(f"cannot write {args.output}: {error.strerror}") from None
    for line in _flag_summary(out.flags, table[:, 0], table[:, 1:4], config):
        log.warning("%s: %s", args.input, line)
    return 0


def _csv_pieces(columns: list[np.ndarray]) -> Iterator[bytes]:
    """`estimate`'s table as CSV, made as it is written, a piece at a time (as the
    estimates table's)."""
    yield (",".join(ESTIMATE_COLUMNS) + "\n").encode()
    for data, _ in csv_rows(columns):
        yield data


def _parquet_bytes(columns: list[np.ndarray]) -> bytes:
    """`estimate`'s table as a Parquet file's bytes (the same bytes for the same
    estimates: the file says which pyarrow wrote it, and nothing of when)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table(dict(zip(ESTIMATE_COLUMNS, columns, strict=True)))
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


# The flags `estimate` counts after its run, besides the samples it skipped: each is an
# input the user may not know is wrong (the flags column says it per row, unread).
_TOLD_FLAGS = (
    StepFlags.NOT_INITIALISED,
    StepFlags.ACCEL_INVALID,
    StepFlags.GAP_REALIGNED,
    StepFlags.TIME_RESTARTED,
    StepFlags.GYRO_CLIPPED,
    StepFlags.UNHEALTHY_RESET,
    StepFlags.DIVERGED,
)


def _time_unit(step: float, max_dt: float) -> str | None:
    """The unit a recording's time seems to be in, from its median step: None where that
    is a sampling interval in seconds (at most ``max_dt``), else the first of
    milliseconds, microseconds and nanoseconds in which it would be one."""
    if step <= max_dt:
        return None
    for unit, per_second in (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9)):
        if step / per_second <= max_dt:
            return unit
    return None


def _flag_summary(
    flags: np.ndarray, t: np.ndarray, gyro: np.ndarray, config: EstimatorConfig
) -> list[str]:
    """A line per kind of problem the samples' flags tell of, named as
    :meth:`StepFlags.describe` names the flags: the samples skipped, by reason, then a
    count for each of :data:`_TOLD_FLAGS`, with the likely unit mistake where there is one."""

    def count(bit: int) -> int:
        return int(np.count_nonzero(flags & bit))

    def name(bit: int) -> str:
        return StepFlags.describe(bit)[0].lower().replace("_", " ")

    lines = []
    steps = np.diff(t[np.isfinite(t)])
    step = float(np.median(steps[steps > 0.0])) if np.any(steps > 0.0) else 0.0
    # a sampling interval of seconds that is a plausible one in a smaller unit
    time_unit = _time_unit(step, config.max_dt)
    time_hint = f"the median step of t is {step:g}: {time_unit}? t must be in seconds"
    skipped = count(StepFlags.SKIPPED)
    if skipped:
        reasons = [getattr(StepFlags, reason) for reason in StepFlags.describe(StepFlags.SKIPPED)]
        # a finite rate beyond any gyro's: read in °/s, most likely
        too_fast = np.isfinite(gyro).all(axis=1) & (np.abs(gyro) > MAX_ANGULAR_RATE).any(axis=1)
        unit = (
            f"; beyond {MAX_ANGULAR_RATE:g} rad/s: °/s? the gyro must be in rad/s"
            if too_fast.any()
            else ""
        )
        if time_unit is not None and count(StepFlags.TIME_OFF_TIMELINE):
            unit += f"; {time_hint}"
        lines.append(
            f"{skipped} sample{'s' if skipped != 1 else ''} skipped: "
            + ", ".join(f"{name(bit)} ({count(bit)})" for bit in reasons if count(bit))
            + unit
        )
    hints = {
        StepFlags.GAP_REALIGNED: (
            f" ({time_hint})"
            if time_unit is not None
            else f" (more than max_dt = {config.max_dt:g} s after the sample before)"
        ),
        StepFlags.GYRO_CLIPPED: (
            f" (beyond gyro_clip = {config.gyro_clip:.4g}: °/s? the gyro must be in rad/s)"
        ),
    }
    for bit in _TOLD_FLAGS:
        if n := count(bit):
            lines.append(f"{name(bit)}: {n} sample{'s' if n != 1 else ''}{hints.get(bit, '')}")
    return lines


# --------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML with [estimator], [input], [output]"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="say more")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


class _Options(Protocol):
    """A parser or one of its argument groups."""

    def add_argument(self, *args: Any, **kwargs: Any) -> Any: ...


def _add_stream_selection(group: _Options) -> None:
    """Which IMU streams are estimated: the same options wherever logs or links are read."""
    group.add_argument(
        "--imu",
        choices=("auto", "all", *IMU_MESSAGES),
        help="IMU message to estimate from (default auto: the best one each vehicle sends)",
    )
    group.add_argument(
        "--instance",
        type=_number(0, 255, whole=True),
        metavar="N",
        help="IMU instance (default: lowest)",
    )
    group.add_argument(
        "--system", type=_ID, metavar="ID", help="follow this vehicle only (default: all)"
    )


def _add_settle(parser: _Options) -> None:
    parser.add_argument(
        "--settle",
        type=_NON_NEGATIVE,
        metavar="S",
        help="seconds before accuracy is scored (default 10)",
    )


def _add_stream_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("streams and output (override the config file)")
    _add_stream_selection(group)
    group.add_argument(
        "--sysid", type=_ID, metavar="ID", help="mavest's system id (default: the vehicle's)"
    )
    group.add_argument(
        "--compid", type=_ID, metavar="ID", help="mavest's component id (default 191)"
    )
    group.add_argument(
        "--attitude-rate",
        type=_NON_NEGATIVE,
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
        "--rerun-port",
        type=_PORT,
        default=9876,
        metavar="PORT",
        help="its gRPC port (default 9876)",
    )
    group.add_argument(
        "--rerun-web-port",
        type=_PORT,
        default=9090,
        metavar="PORT",
        help="the served web viewer's HTTP port (default 9090)",
    )
    group.add_argument(
        "--out-tlog",
        type=Path,
        metavar="PATH",
        help="write a tlog of every input message and everything mavest sends (ATTITUDE, "
        "ATTITUDE_QUATERNION, HEARTBEAT; live also its requests to the vehicle and answers "
        "to ground stations), in the MAVLink version of the vehicle",
    )
    group.add_argument(
        "--estimates",
        type=_table_path,
        metavar="FILE.csv|FILE.parquet",
        help="write the estimates as a table, a row per IMU sample estimated: system, "
        "component, message, instance, time_s (the vehicle's boot clock), qw qx qy qz "
        "(body → NED), roll/pitch/yaw_deg and their 1σ (sigma_roll_deg, ...), "
        "bias_x/y/z_dps, nis, accel_used, flags. Parquet needs pyarrow "
        "(pip install 'mavest[parquet]')",
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
    parser = _Parser(
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
        "Runs until Ctrl-C or SIGTERM, then flushes its files and exits 0 (1 if it heard "
        "no IMU stream).",
        epilog="CONNECTION: udpin:HOST:PORT (listen; replies go to the sender; udp:HOST:PORT "
        "and a bare HOST:PORT are the same), udpout:HOST:PORT, udpbcast:ADDRESS:PORT, "
        "tcp:HOST:PORT (reconnects), tcpin:HOST:PORT, or a serial device (/dev/ttyUSB0 with "
        "--baud, or /dev/ttyUSB0,57600).",
    )
    run.add_argument("connection", metavar="CONNECTION", help="where the IMU data comes from")
    run.add_argument(
        "--out",
        action="append",
        default=[],
        metavar="CONNECTION",
        help="also send estimates here (repeatable)",
    )
    run.add_argument(
        "--out-only",
        action="store_true",
        help="send estimates and HEARTBEAT only to the --out links, not back on CONNECTION "
        "(which still carries the message-interval request and answers to requests)",
    )
    run.add_argument(
        "--baud",
        type=_number(1, 20_000_000, whole=True),
        default=115200,
        help="serial baud rate (default 115200)",
    )
    run.add_argument(
        "--request-rate",
        type=_number(0, 4000),
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
        help="run a log (.tlog, ArduPilot .bin, PX4 .ulg) through the estimator",
        description="Replay a log through the same pipeline as `run`: as fast as possible, "
        "or paced with --speed. Prints a summary: samples, rate, gaps, rejected samples, and "
        "accuracy against the log's own ATTITUDE (and SIMSTATE, a simulator's truth). "
        "The log is a telemetry log (.tlog) or an autopilot's onboard log, told apart by "
        "content: an ArduPilot DataFlash log (.bin) or a PX4 ULog (.ulg), whose samples are "
        "replayed as the MAVLink a vehicle would send with them: every IMU as HIGHRES_IMU "
        "(--instance picks one), the autopilot's attitude as ATTITUDE, a simulator's truth "
        "as SIMSTATE, GPS velocity, airspeed and COMPASS_DEC where the log has them. With "
        "--out-tlog that MAVLink is written too, beside mavest's answers: a tlog of the "
        "onboard log that any MAVLink tool reads.",
    )
    rep.add_argument("tlog", type=Path, metavar="LOG", help="a .tlog, .bin or .ulg file")
    rep.add_argument(
        "--speed", type=_POSITIVE, help="pace the replay (1 = real time; default: fast)"
    )
    rep.add_argument(
        "--one-by-one",
        action="store_true",
        help="take every record singly, as the live service does (the same result, in "
        "several times the time; without it, clean stretches of the log go through a "
        "compiled path, unless --speed paces the replay)",
    )
    rep.add_argument(
        "--smooth",
        action="store_true",
        help="after the replay, smooth each stream (every sample's attitude given the whole "
        "log) and put it beside the online estimate: in the summary (against the autopilot "
        "and the truth), the --rrd recording and the --estimates table (smoothed_* columns)",
    )
    _add_settle(rep)
    _add_stream_options(rep)
    _add_common(rep)
    rep.set_defaults(handler=_replay)

    fleet = commands.add_parser(
        "fleet",
        help="replay many logs on Dask (here or on a cluster): one table, a row per log",
        description="Replay every log given, as `mavest replay` does, on Dask: a local "
        "cluster of worker processes, or an existing cluster (--scheduler). One table, a row "
        "per log and IMU stream: status and error, vehicle, samples, duration, rate, gaps, "
        "rejected samples, filter health events, tilt and heading RMS against the log's "
        "ATTITUDE (and a simulator's truth), the filter's mean 1σ. A log that cannot be "
        "replayed is a row with its error, never the end of the run; Ctrl-C writes the "
        "table of the logs that finished.",
    )
    fleet.add_argument(
        "logs",
        nargs="+",
        metavar="LOG",
        help="a log, a folder (its .tlog, .bin and .ulg files, in sub-folders too), a glob "
        "(expanded by mavest, sorted), or an fsspec URL of any of these (s3://bucket/logs/, "
        "gs://…, file://…; the backend, e.g. s3fs, installed)",
    )
    fleet.add_argument(
        "--out",
        type=_table_path,
        required=True,
        metavar="TABLE.parquet|TABLE.csv",
        help="the table (Parquet needs pyarrow)",
    )
    fleet.add_argument(
        "--out-dir",
        type=Path,
        metavar="DIR",
        help="also write each log's Rerun recording and estimates table here: NAME.rrd and "
        "NAME.estimates.parquet (or .csv, as --out), NAME the log's (NAME-2 … for a name "
        "taken already)",
    )
    fleet.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="an existing Dask cluster's scheduler, tcp://HOST:PORT, or tls://HOST:PORT "
        "with Dask's TLS settings (default: a local cluster on this machine)",
    )
    fleet.add_argument(
        "--workers",
        type=_number(1, 4096, whole=True),
        metavar="N",
        help="worker processes of the local cluster (default: this machine's cores)",
    )
    stream = fleet.add_argument_group("streams (override the config file)")
    _add_stream_selection(stream)
    _add_settle(stream)
    _add_common(fleet)
    fleet.set_defaults(handler=_fleet)

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
    sim.add_argument(
        "--rate", type=_number(1, 2000), default=200.0, help="IMU rate in Hz (1–2000, default 200)"
    )
    sim.add_argument(
        "--autopilot", choices=("ardupilot", "px4"), default="ardupilot", help="message flavour"
    )
    sim.add_argument(
        "--seconds",
        type=_POSITIVE,
        help="stop after this long (default: until Ctrl-C; with --tlog up to 86400)",
    )
    sim.add_argument("--seed", type=_SEED, default=1, help="flight and noise seed (default 1)")
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
    demo.add_argument(
        "--seconds",
        type=_FLIGHT_SECONDS,
        default=120.0,
        help="flight length (up to 86400, default 120)",
    )
    demo.add_argument(
        "--rate", type=_number(1, 2000), default=400.0, help="IMU rate in Hz (default 400)"
    )
    demo.add_argument("--seed", type=_SEED, default=1, help="random seed (default 1)")
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
    csv.add_argument(
        "-o",
        "--output",
        type=Path,
        help="the estimates: FILE.parquet as Parquet (with pyarrow), any other name as CSV "
        "(default: CSV on standard output)",
    )
    _add_common(csv)
    csv.set_defaults(handler=_estimate_csv)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as done:  # --help, --version, or a mistake argparse found (said)
        return int(done.code or 0)
    _setup_logging(args)
    _tolerant_stdout()
    try:
        return int(args.handler(args))
    except UsageError as error:
        print(f"mavest: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # (a command whose summary says so has returned 130 itself)
        with contextlib.suppress(OSError):
            print("mavest: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader of our output went away (`mavest … | head`)
        _silence_stdout()
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
