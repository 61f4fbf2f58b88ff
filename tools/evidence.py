"""Accuracy in one run: every filter on every data set, one table (and the plots).

    .venv/bin/python tools/evidence.py [--quick] [--offline] [--markdown] [--detail]
                                       [--plots [DIR]]
                                       [--results [FILE]]
                                       [--parts broad logs flights] [--trials 02 07 ...]
                                       [--seeds 1 2 3 4] [--seconds 120]

One process, one run, the same samples for every filter: mavest (default and its
variants), VQF, x-io Fusion and the ``ahrs`` package's Madgwick and Mahony (with
--offline also the estimates that see the whole recording: mavest smoothed,
``mavest.smooth``, and offline VQF, ``vqf.offlineVQF``), on

* BROAD ($MAVEST_DATA/broad, trials with optical truth), scored as the dataset
  does (RMSE over the movement phases, mean over trials): 6-D inclination, and with
  the magnetometer 9-D total and heading. mavest's defaults were chosen on 22 of its
  trials (mavest.datasets.broad.TUNED_ON): the means, and the per-trial counts against
  VQF, are given apart for those and for the trials held out from it, and --detail
  marks the former with *. A trial with nothing to score (no movement sample with
  truth) is left out with a line; a filter that leaves a scored sample without an
  estimate scores n/a on that trial, with a line (mavest.evaluation.metrics.rmse_deg);
* three autopilot logs ($MAVEST_DATA/dataflash, ulog) whose phases are known:
  6-D from the logged IMU, slerped
  onto the autopilot's own attitude (ArduPilot ATT and AHR2 with the AHRS trim added
  back, EKF1 in --detail: it equals ATT from 10 s on; PX4 vehicle_attitude) and, for
  the PX4 simulator log, onto its true attitude; and onto a reference no estimator
  wrote, the accelerometer's gravity direction in the still seconds of stretches the
  vehicle lies in (log171 before take-off and upside down after its crash, the PX4
  log at rest). Against the truth and the accelerometer the autopilot is a column
  too; inclination RMSE per segment. Each file is checked to be the recording its
  phases were written for (its first IMU sample's time and values): another log under
  its name is refused with a line, a shortened one is scored up to its end with a
  line naming the phases it lacks, and the other logs in those folders are named in
  a line, not scored;
* JSBSim flights as ``make demo`` makes them (Cessna 172, ArduPilot RAW_IMU at 400 Hz
  with noise, bias and quantisation; one per seed): every filter fed the same IMU
  samples read back from the tlog (6-D), tilt RMSE against the flight model's truth
  after the first 10 s; and, labelled apart, mavest as the service runs it (replayed
  with configs/ardupilot.toml: GPS-aided, with the magnetometer), scored by the
  service's own comparison with SIMSTATE.

Rows are data, columns filters, RMSE in degrees; the best of the filters fed the same
samples is in bold (the autopilot, mavest as served and the offline estimates are not
candidates: an offline estimate uses samples after the one it estimates). Per trial,
per segment and per flight with --detail; --plots writes the PNGs (error over time,
mavest against VQF) to DIR (default docs/). Madgwick and Mahony run as pure Python:
they took 1205 s of a 1549 s full run (two shared cores); --quick leaves them out
(~6 min). --results writes the printed tables (as Markdown) as the Accuracy section of
docs/results.md (or FILE). Exits 2, with one line, when data or a package a part needs
is missing.
"""

from __future__ import annotations

import asyncio
import importlib
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mavest.datasets import DATA_ENV_VAR, require_data
from mavest.datasets.autopilot_logs import (
    DATAFLASH_LOG171,
    ULOG_REAL,
    ULOG_SIMULATOR,
    AutopilotLog,
    load_dataflash,
    load_ulog,
    log_path,
)
from mavest.datasets.broad import BroadTrial, list_trials, load_trials, tuned_on
from mavest.evaluation import report
from mavest.evaluation.accuracy import MAVEST_VARIANTS, mavest_adapter
from mavest.evaluation.logs import Score, Segment, gravity_at_rest, score_segments, slerp_onto
from mavest.evaluation.metrics import (
    attitude_errors,
    missing_rows,
    rmse_deg,
    trial_parity,
)
from mavest.evaluation.peers import PEERS, PeerAdapter
from mavest.so3 import euler_zyx_from_quats, quats_from_euler_zyx

if TYPE_CHECKING:
    from matplotlib.figure import Figure

PROJECT = Path(__file__).resolve().parents[1]
ARDUPILOT_CONFIG = PROJECT / "configs" / "ardupilot.toml"
PARTS = ("broad", "logs", "flights")
SLOW_PEERS = ("Madgwick", "Mahony")  # pure Python: left out by --quick
PLOTTED = ("mavest", "VQF")  # the two filters drawn over time
SMOOTHED = "mavest smoothed"
OFFLINE_VQF = "offline VQF"
OFFLINE = (SMOOTHED, OFFLINE_VQF)  # see the whole recording: shown, never bold
AUTOPILOT = "autopilot"  # its own estimate, against a simulator's truth
SERVED = "mavest as served"  # the service on the flight's tlog, GPS-aided, 9-D
FLIGHT_RATE = 400.0  # Hz, as `make demo`
ALL = Segment("all", 0.0, np.inf)
# mavest's default parameters were chosen on 22 BROAD trials (tuned_on): figures on
# those are not held out, and every mean says which kind of trial it is over.
TUNED = " (mavest tuned on these trials)"
HELD_OUT = " (held out: mavest not tuned on these trials)"
KINDS = {"tuned on": TUNED, "held out": HELD_OUT}  # a kind of trial → its main-table words
TUNED_MARK = " *"  # --detail: after the name of a trial mavest was tuned on


@dataclass(frozen=True)
class KnownLog:
    """A log whose phases are known, and how to tell it is that recording: the time
    (s since boot) and specific force (m/s², FRD) of its first IMU sample, which a
    shortened copy keeps, and the span of its IMU samples (s)."""

    label: str
    segments: list[Segment]  # none: the log is shown whole
    shown_references: tuple[str, ...]  # further references shown in the main table
    boot_time: float
    first_accel: tuple[float, float, float]
    duration: float

    def mismatch(self, log: AutopilotLog) -> str | None:
        """Why ``log`` is not this recording (None: it is, perhaps shortened)."""
        if abs(log.boot_time - self.boot_time) > 1e-3 or not np.allclose(
            log.accel[0], self.first_accel, atol=1e-4
        ):
            return (
                f"its first IMU sample ({log.boot_time:.3f} s since boot) is not "
                f"{self.label}'s ({self.boot_time:.3f} s)"
            )
        if log.duration > self.duration + 1.0:
            return f"it spans {log.duration:.0f} s, {self.label} {self.duration:.0f} s"
        return None

    def shortened(self, log: AutopilotLog) -> bool:
        """Whether ``log`` ends before this recording does (a cut copy)."""
        return log.duration < self.duration - 1.0


#: Log file → what is known of it. The log171 segments follow the data README (at rest,
#: flying, crash and flip); the pyulog_sample log is moved by hand for its first 10 s,
#: then rests. Identities measured on the shared copies.
LOGS: dict[str, KnownLog] = {
    DATAFLASH_LOG171: KnownLog(
        "ArduCopter log171",
        [
            Segment("rest", 0.0, 60.0),
            Segment("flight", 60.0, 200.0),
            Segment("crash", 200.0, np.inf),
        ],
        ("AHR2",),
        11.46,
        (-0.07167864, -0.62707001, -9.58753395),
        242.601,
    ),
    ULOG_REAL: KnownLog(
        "PX4 pyulog_sample",
        [Segment("moved by hand", 0.0, 10.0), Segment("rest", 10.0, np.inf)],
        (),
        112.614307,
        (1.10714173, -0.48647752, -9.63039494),
        68.879,
    ),
    ULOG_SIMULATOR: KnownLog(
        "PX4 simulator", [], (), 0.284, (0.05289749, 0.01440491, -9.90560532), 10.768
    ),
}
#: The suffixes of the logs looked for beside them (case-insensitive).
LOG_SUFFIXES = (".bin", ".ulg")

#: A reference no estimator wrote (:func:`~mavest.evaluation.logs.gravity_at_rest`):
#: the accelerometer's gravity direction in 1 s windows where the vehicle lies still,
#: within stretches it is known to lie in. Every filter and the autopilot's own
#: attitude are scored against it.
RESTING = "accelerometer at rest"
#: A rate above this is violent motion: log171 lies still only after its last one.
VIOLENT_RATE = np.radians(100.0)


def still_spans(relative: str, log: AutopilotLog, whole: bool = True) -> list[Segment]:
    """The stretches of this log whose vehicle is known to lie still (none: no reference).

    log171: before take-off (the data README), and upside down after the flip, from
    its last rate above VIOLENT_RATE; a shortened copy (not ``whole``) lacks the end it
    lies upside down in. pyulog_sample: resting after the first 10 s.
    """
    if relative == DATAFLASH_LOG171:
        if not whole:
            return [Segment("rest", 0.0, 60.0)]
        violent = np.flatnonzero(np.linalg.norm(log.gyro, axis=1) > VIOLENT_RATE)
        after = float(log.t[violent[-1]]) if violent.size else log.duration
        return [Segment("rest", 0.0, 60.0), Segment("upside down", after, np.inf)]
    if relative == ULOG_REAL:
        return [Segment("rest", 10.0, np.inf)]
    return []


def _warn(text: str) -> None:
    """One line on a problem with an input; the run goes on."""
    report.progress("evidence", text)


class MissingInputError(Exception):
    """Data or a package that a requested part needs is absent: one line for the user."""


# --------------------------------------------------------------------------
# Filters, timed
# --------------------------------------------------------------------------


@dataclass
class Filters:
    """The filters fed the same samples, by column name, with the time each has taken."""

    adapters: dict[str, PeerAdapter]
    seconds: dict[str, float] = field(default_factory=dict)

    @classmethod
    def chosen(cls, quick: bool, offline: bool = False) -> Filters:
        adapters = {"mavest": mavest_adapter()}
        adapters |= {name: mavest_adapter(config) for name, config in MAVEST_VARIANTS.items()}
        for name in PEERS:
            if not (quick and name in SLOW_PEERS) and name not in OFFLINE:
                adapters[name] = PEERS[name]
        if offline:
            adapters[SMOOTHED] = mavest_adapter(smoothed=True)
            adapters[OFFLINE_VQF] = PEERS[OFFLINE_VQF]
        return cls(adapters)

    @property
    def online(self) -> set[str]:
        """The filters that estimate each sample from the samples up to it: the candidates
        for bold."""
        return set(self.adapters) - set(OFFLINE)

    @property
    def names(self) -> list[str]:
        return list(self.adapters)

    def run_all(
        self,
        t: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        mag: np.ndarray | None,
        rate: float,
    ) -> dict[str, np.ndarray]:
        """Every filter on the same samples: name → (N, 4) quaternions, body → NED."""
        estimates = {}
        for name, run in self.adapters.items():
            start = time.perf_counter()
            estimates[name] = run(t, gyro, accel, mag, rate)
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start
        return estimates


def _progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------
# BROAD
# --------------------------------------------------------------------------


@dataclass
class BroadResult:
    """Per-trial RMSE (°) of every filter, and the plotted filters' errors over time."""

    trials: list[BroadTrial]
    inclination_6d: dict[str, list[float]]
    total_9d: dict[str, list[float]]
    heading_9d: dict[str, list[float]]
    # trial name → filter → per-sample error (rad): 6-D inclination, 9-D heading
    inclination_curves: dict[str, dict[str, np.ndarray]]
    heading_curves: dict[str, dict[str, np.ndarray]]
    # the scored samples a filter left without an estimate, making its figure n/a
    notes: list[str] = field(default_factory=list)

    def kinds(self) -> list[tuple[str, list[int]]]:
        """The trials mavest was tuned on and those held out from it: ("tuned on" or
        "held out", trial indices), each kind that is present."""
        tuned = [i for i, trial in enumerate(self.trials) if tuned_on(trial.name)]
        held_out = [i for i in range(len(self.trials)) if i not in tuned]
        return [
            (kind, part) for kind, part in (("tuned on", tuned), ("held out", held_out)) if part
        ]


def load_broad(prefixes: Sequence[str] | None) -> list[BroadTrial]:
    """The BROAD trials (those whose names start with one of ``prefixes``, if given) that
    have something to score; one without (no movement sample with truth) is left out
    of every mean and count, with a line."""
    try:
        paths = list_trials(prefixes=prefixes)
    except FileNotFoundError as error:
        raise MissingInputError(str(error)) from None
    if not paths:
        wanted = f" matching --trials {' '.join(prefixes)}" if prefixes else ""
        raise MissingInputError(f"no BROAD .hdf5 trial{wanted} in {DATA_ENV_VAR}'s broad/")
    # (a bad file, a copy of a trial, one with nothing to score: left out with a line)
    trials = list(load_trials(paths, _warn, scored_only=True))
    if not trials:
        raise MissingInputError("no BROAD trial here has a movement sample with truth to score")
    return trials


def run_broad(trials: list[BroadTrial], filters: Filters) -> BroadResult:
    """Every filter on every trial (each with something to score: :func:`load_broad`)."""
    result = BroadResult(trials, {}, {}, {}, {}, {})
    for index, trial in enumerate(trials, 1):
        _progress(f"BROAD {trial.name} ({index}/{len(trials)})")
        scored = int(np.count_nonzero(trial.scored))
        for mag in (None, trial.mag):
            estimates = filters.run_all(trial.t, trial.gyro, trial.accel, mag, trial.rate)
            for name, q in estimates.items():
                rmse = rmse_deg(q, trial.truth_q, trial.movement)
                if missing := missing_rows(q, trial.truth_q, trial.movement):
                    result.notes.append(
                        f"{name} left {missing} of the {scored} scored samples of "
                        f"{trial.name} ({'6-D' if mag is None else '9-D'}) without an "
                        "estimate: n/a there and in its means"
                    )
                if mag is None:
                    result.inclination_6d.setdefault(name, []).append(rmse["inclination"])
                else:
                    result.total_9d.setdefault(name, []).append(rmse["total"])
                    result.heading_9d.setdefault(name, []).append(rmse["heading"])
                if name in PLOTTED:
                    errors = attitude_errors(q, trial.truth_q)
                    curves = result.inclination_curves if mag is None else result.heading_curves
                    kept = errors.inclination if mag is None else errors.heading
                    curves.setdefault(trial.name, {})[name] = kept.astype(np.float32)
    return result


# --------------------------------------------------------------------------
# Autopilot logs
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class LogScores:
    """Every candidate against one reference of one log over one segment."""

    log: str
    against: str
    segment: str
    main_table: bool
    scores: dict[str, Score]


@dataclass
class LogsResult:
    scores: list[LogScores]
    notes: list[str]
    # the log171 estimates of the plotted filters, for its figure
    log171: AutopilotLog | None = None
    log171_estimates: dict[str, np.ndarray] = field(default_factory=dict)


def load_logs() -> list[tuple[str, AutopilotLog]]:
    """The logs of :data:`LOGS` that are there and are the recordings their phases were
    written for; each other one is named in a line and left out, and so, in one line,
    are the logs beside them that this part does not score. MissingInputError when
    pyulog is absent or none of :data:`LOGS` can be scored."""
    try:
        importlib.import_module("pyulog")
    except ImportError:
        raise MissingInputError("pyulog (dev extra) is needed to read the PX4 logs") from None
    logs, refused = [], []
    for relative, known in LOGS.items():
        try:
            path = log_path(relative)
            log = load_dataflash(path) if relative.endswith(".bin") else load_ulog(path)
        except (FileNotFoundError, ValueError) as error:
            refused.append(f"{relative}: {error}")
            continue
        if reason := known.mismatch(log):
            refused.append(f"{relative} is not the log its phases belong to: {reason}")
            continue
        logs.append((relative, log))
    if not logs:
        raise MissingInputError(
            f"no autopilot log to score ({refused[0]}; set {DATA_ENV_VAR} to the folder with "
            "dataflash/ and ulog/, or leave logs out of --parts)"
        )
    for reason in refused:
        _warn(f"{reason}: not scored")
    if others := unscored_logs():
        _warn(f"other logs, not scored (their phases are not known): {', '.join(others)}")
    return logs


def unscored_logs() -> list[str]:
    """The logs in the folders of :data:`LOGS` (relative to the data root) that are not
    among them."""
    found = []
    for folder in sorted({relative.partition("/")[0] for relative in LOGS}):
        try:
            paths = sorted(require_data(folder).iterdir())
        except (FileNotFoundError, NotADirectoryError):
            continue
        found += [
            f"{folder}/{path.name}"
            for path in paths
            if path.suffix.lower() in LOG_SUFFIXES and f"{folder}/{path.name}" not in LOGS
        ]
    return found


def _short_source(source: str) -> str:
    """``"ATT + AHRS_TRIM"`` → ``"ATT"`` (the trim is said once, in the notes)."""
    return source.split(" + ")[0]


def run_logs(logs: list[tuple[str, AutopilotLog]], filters: Filters) -> LogsResult:
    result = LogsResult([], [])
    for relative, log in logs:
        known = LOGS[relative]
        label, shown_references = known.label, known.shown_references
        whole = not known.shortened(log)
        # a shortened copy is scored up to its end: the phases it does not reach are left
        # out, with a line
        segments = [segment for segment in known.segments if segment.start < log.duration]
        spans = [span for span in still_spans(relative, log, whole) if span.start < log.duration]
        if not whole:
            lacked = [s.describe(known.duration) for s in known.segments if s not in segments]
            lacked += [
                f"{s.label} ({RESTING})"
                for s in still_spans(relative, log)
                if s.label not in {span.label for span in spans}
            ]
            _warn(
                f"{label} ({relative}) ends at {log.duration:.0f} s, not "
                f"{known.duration:.0f} s: scored up to its end"
                + (f", without {', '.join(lacked)}" if lacked else "")
            )
        _progress(f"log {label}")
        estimates = filters.run_all(log.t, log.gyro, log.accel, None, log.rate)
        candidates = {name: (log.t, q) for name, q in estimates.items()}
        references = [(log.reference_source, log.reference_t, log.reference_q, True)]
        references += [
            (r.source, r.t, r.q, _short_source(r.source) in shown_references)
            for r in log.other_references
        ]
        if relative == DATAFLASH_LOG171:
            result.log171 = log
            result.log171_estimates = {name: estimates[name] for name in PLOTTED}
        everywhere = [*segments, ALL]
        comparisons = [
            (source, t, q, shown, candidates, everywhere) for source, t, q, shown in references
        ]
        # Against a reference no estimator wrote the autopilot is one more estimate,
        # interpolated like ours.
        with_autopilot = candidates | {AUTOPILOT: (log.reference_t, log.reference_q)}
        if log.truth_t is not None and log.truth_q is not None:
            comparisons.append(
                ("ground truth", log.truth_t, log.truth_q, True, with_autopilot, everywhere)
            )
        if spans:
            still_t, still_q = gravity_at_rest(log.t, log.gyro, log.accel, spans)
            comparisons.append((RESTING, still_t, still_q, True, with_autopilot, spans))
        shown_segments = [*segments, *spans] or [ALL]
        for source, ref_t, ref_q, shown, compared, scored in comparisons:
            by_segment = score_segments(compared, ref_t, ref_q, scored)
            for segment in scored:
                result.scores.append(
                    LogScores(
                        label,
                        _short_source(source),
                        segment.describe(log.duration),
                        shown and segment in shown_segments,
                        by_segment[segment.label],
                    )
                )
        notes = list(log.notes)
        if spans:
            notes.append(
                f"{RESTING}: {len(still_t)} still 1 s windows in "
                + ", ".join(segment.describe(log.duration) for segment in spans)
            )
        result.notes.append(f"{label} = {log.name}: " + "; ".join(notes))
    return result


# --------------------------------------------------------------------------
# JSBSim flights
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightSamples:
    """A simulated flight as its tlog holds it: the IMU in SI (FRD) and the truth."""

    t: np.ndarray  # (N,) s from the first sample
    gyro: np.ndarray  # (N, 3) rad/s
    accel: np.ndarray  # (N, 3) m/s²
    truth_q: np.ndarray  # (N, 4) (w, x, y, z), body → NED, SIMSTATE's angles


def read_flight_tlog(path: Path) -> FlightSamples:
    """RAW_IMU (decoded as the service decodes it) and the SIMSTATE sent after each."""
    from mavest.mavlink.messages import decode_imu
    from mavest.mavlink.tlog import TlogReader, message_ids

    times, gyro, accel, euler = [], [], [], []
    for record in TlogReader.open(path, message_ids(["RAW_IMU", "SIMSTATE"])):
        message = record.message
        if message is None:
            continue
        if message.get_type() == "SIMSTATE":
            euler.append((message.roll, message.pitch, message.yaw))
        elif (sample := decode_imu(message)) is not None:
            times.append(sample.ticks * sample.tick)
            gyro.append(sample.gyro)
            accel.append(sample.accel)
    if len(euler) != len(times):
        raise ValueError(f"{path.name}: {len(times)} RAW_IMU but {len(euler)} SIMSTATE")
    t = np.array(times)
    return FlightSamples(
        t - t[0], np.array(gyro), np.array(accel), quats_from_euler_zyx(np.array(euler))
    )


@dataclass
class FlightsResult:
    seeds: list[int]
    seconds: float
    settle_time: float
    tilt: dict[str, list[float]]  # column → per seed, RMSE ° after the settle time
    served_detail: list[tuple[float, float, float]]  # per seed: roll, pitch, tilt RMS °
    samples: list[FlightSamples]
    curves: list[dict[str, np.ndarray]]  # per seed: filter → tilt error (rad) per sample


def run_flights(seeds: Sequence[int], seconds: float, filters: Filters) -> FlightsResult:
    from mavest.service.config import ServiceConfig
    from mavest.service.runners import replay
    from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

    config = ServiceConfig.from_toml(ARDUPILOT_CONFIG)
    settle = config.input.settle_time
    result = FlightsResult(list(seeds), seconds, settle, {}, [], [], [])
    with tempfile.TemporaryDirectory() as folder:
        for seed in seeds:
            _progress(f"JSBSim flight, seed {seed}")
            path = Path(folder) / f"flight{seed}.tlog"
            write_flight_tlog(path, seconds, FLIGHT_RATE, AUTOPILOTS["ardupilot"], seed=seed)
            flight = read_flight_tlog(path)
            scored = flight.t >= settle
            estimates = filters.run_all(flight.t, flight.gyro, flight.accel, None, FLIGHT_RATE)
            curves = {}
            for name, q in estimates.items():
                tilt = attitude_errors(q, flight.truth_q).inclination
                result.tilt.setdefault(name, []).append(_rms_deg(tilt[scored]))
                if name in PLOTTED:
                    curves[name] = tilt
            start = time.perf_counter()
            (stream,) = asyncio.run(replay(path, config)).streams
            filters.seconds[SERVED] = filters.seconds.get(SERVED, 0.0) + (
                time.perf_counter() - start
            )
            served = stream.vs_truth.result()
            result.tilt.setdefault(SERVED, []).append(served.inclination_rms)
            result.served_detail.append((served.roll_rms, served.pitch_rms, served.inclination_rms))
            result.samples.append(flight)
            result.curves.append(curves)
    return result


def _rms_deg(radians: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(np.square(radians)))))


# --------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    """One row of a table: a label and a value (° RMSE) per column that has one."""

    label: str
    values: dict[str, float]
    digits: int = 2
    bold_lowest: bool = True  # False for rows where lower is not better (counts)


def _cell(value: float | None, digits: int, best: bool) -> str:
    if value is None:
        return ""
    text = f"{value:.{digits}f}" if np.isfinite(value) else "n/a"
    return f"**{text}**" if best else text


def format_table(
    title: str, columns: list[str], rows: Iterable[Row], markdown: bool, candidates: set[str]
) -> str:
    """Markdown or aligned text; per row the lowest value (as shown) among ``candidates``
    is bold."""
    header = [title, *columns]
    lines = []
    for row in rows:
        shown = {
            name: round(value, row.digits)
            for name, value in row.values.items()
            if name in candidates and np.isfinite(value)
        }
        lowest = min(shown.values(), default=None) if row.bold_lowest else None
        lines.append(
            [row.label]
            + [
                _cell(row.values.get(name), row.digits, name in shown and shown[name] == lowest)
                for name in columns
            ]
        )
    if markdown:
        out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        out += ["| " + " | ".join(line) + " |" for line in lines]
        return "\n".join(out)
    widths = [max(len(r[i]) for r in [header, *lines]) for i in range(len(header))]
    return "\n".join(
        "  ".join(
            cell.ljust(w) if i == 0 else cell.rjust(w)
            for i, (cell, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in [header, *lines]
    )


def _mean(values: dict[str, list[float]], subset: list[int] | None = None) -> dict[str, float]:
    """Per column the mean of its values (of those at ``subset``, if given); n/a when
    one of them is."""
    return {
        name: float(np.mean(np.asarray(v)[subset] if subset is not None else v))
        for name, v in values.items()
    }


def main_rows(
    broad: BroadResult | None, logs: LogsResult | None, flights: FlightsResult | None
) -> list[Row]:
    rows = []
    if broad is not None:
        # apart for the trials mavest was tuned on and those held out: a mean over both
        # would be neither in-sample nor a check
        for title, values in (
            ("BROAD 6-D inclination", broad.inclination_6d),
            ("BROAD 9-D total", broad.total_9d),
            ("BROAD 9-D heading", broad.heading_9d),
        ):
            rows += [
                Row(f"{title}, mean of {len(subset)}{KINDS[kind]}", _mean(values, subset), 3)
                for kind, subset in broad.kinds()
            ]
    if logs is not None:
        rows += [
            Row(
                f"{s.log} vs {s.against}: {s.segment}",
                {name: score.inclination for name, score in s.scores.items()},
            )
            for s in logs.scores
            if s.main_table
        ]
    if flights is not None:
        rows.append(
            Row(
                f"JSBSim flights ({len(flights.seeds)} × {flights.seconds:g} s), tilt after "
                f"{flights.settle_time:g} s, mean",
                _mean(flights.tilt),
            )
        )
    return rows


def columns_of(
    filters: Filters, logs: LogsResult | None, flights: FlightsResult | None
) -> list[str]:
    columns = filters.names
    if logs is not None and any(AUTOPILOT in s.scores for s in logs.scores):
        columns.append(AUTOPILOT)
    if flights is not None:
        columns.append(SERVED)
    return columns


def detail_tables(
    filters: Filters,
    broad: BroadResult | None,
    logs: LogsResult | None,
    flights: FlightsResult | None,
    markdown: bool,
) -> list[str]:
    """Per trial, per segment, per flight."""
    names = filters.names
    same_imu = filters.online
    tables = []
    if broad is not None:
        kinds = broad.kinds()
        for title, values in (
            ("BROAD 6-D inclination RMSE (°)", broad.inclination_6d),
            ("BROAD 9-D total RMSE (°)", broad.total_9d),
            ("BROAD 9-D heading RMSE (°)", broad.heading_9d),
        ):
            rows = [
                Row(
                    trial.name + (TUNED_MARK if tuned_on(trial.name) else ""),
                    {name: values[name][i] for name in names},
                )
                for i, trial in enumerate(broad.trials)
            ]
            for kind, subset in kinds:
                # with both kinds present, each row says which one it is over
                of = f", {kind}" if len(kinds) > 1 else ""
                # and its halves by trial number: whether a margin holds across the trials
                parity = {i: trial_parity(broad.trials[i].name) for i in subset}
                for label, part in (
                    (f"mean{of}", subset),
                    (f"mean{of}, even", [i for i in subset if parity[i] == 0]),
                    (f"mean{of}, odd", [i for i in subset if parity[i] == 1]),
                ):
                    if part:
                        rows.append(Row(label, _mean(values, part), 3))
            for peer in ("VQF", OFFLINE_VQF):
                if peer not in values:
                    continue
                for kind, subset in kinds:
                    of = f", {kind} (of {len(subset)})" if len(kinds) > 1 else ""
                    reference = np.asarray(values[peer])[subset]
                    below = {n: np.asarray(values[n])[subset] <= reference for n in names}
                    rows.append(
                        Row(
                            f"trials at or below {peer}{of}",
                            {n: float(np.sum(b)) for n, b in below.items()},
                            digits=0,
                            bold_lowest=False,
                        )
                    )
            tables.append(format_table(title, names, rows, markdown, same_imu))
        legend = []
        if any(tuned_on(trial.name) for trial in broad.trials):
            legend.append(
                f"A{TUNED_MARK} after a trial's name: mavest's defaults were chosen on it."
            )
        if unnumbered := [t.name for t in broad.trials if trial_parity(t.name) is None]:
            legend.append(
                f"In neither the even nor the odd mean (no number): {', '.join(unnumbered)}."
            )
        if legend:
            tables.append(" ".join(legend))
    if logs is not None:
        columns = names + ([AUTOPILOT] if any(AUTOPILOT in s.scores for s in logs.scores) else [])
        rows = [
            Row(
                f"{s.log} vs {s.against}: {s.segment} (n {next(iter(s.scores.values())).n})",
                {name: score.inclination for name, score in s.scores.items()},
            )
            for s in logs.scores
        ]
        tables.append(
            format_table("autopilot logs, inclination RMSE (°)", columns, rows, markdown, same_imu)
        )
        tables.append("\n".join(("- " if markdown else "") + note for note in logs.notes))
    if flights is not None:
        rows = [
            Row(f"seed {seed}", {name: v[i] for name, v in flights.tilt.items()})
            for i, seed in enumerate(flights.seeds)
        ]
        tables.append(
            format_table(
                f"JSBSim flights, tilt RMSE after {flights.settle_time:g} s (°)",
                [*names, SERVED],
                rows,
                markdown,
                same_imu,
            )
        )
        tables.append(
            "mavest as served, roll / pitch / tilt RMS (°): "
            + "; ".join(
                f"seed {seed} {r:.2f} / {p:.2f} / {t:.2f}"
                for seed, (r, p, t) in zip(flights.seeds, flights.served_detail, strict=True)
            )
        )
    return tables


# --------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------

COLOURS = {"mavest": "tab:blue", "VQF": "tab:orange"}
BIN_SECONDS = 0.25  # the curves are drawn as the RMS over bins this long
PNG_COLOURS = 64


def _binned_rms(t: np.ndarray, error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres and the RMS (°) of the finite errors in each bin of BIN_SECONDS."""
    index = np.floor((t - t[0]) / BIN_SECONDS).astype(int)
    finite = np.isfinite(error)
    squares = np.bincount(index[finite], np.square(np.degrees(error[finite])), index[-1] + 1)
    counts = np.bincount(index[finite], minlength=index[-1] + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(squares / counts)
    centres = t[0] + (np.arange(len(rms)) + 0.5) * BIN_SECONDS
    return centres, rms


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True runs of a boolean array."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _figure(rows: int, columns: int, width: float, height: float) -> tuple[Figure, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(rows, columns, figsize=(width, height), squeeze=False)


def _save(figure: Figure, path: Path) -> Path:
    """Write the figure as a PNG of at most PNG_COLOURS colours: the noisy error curves
    make a full-colour PNG compress badly (a 22-panel grid: 450 kB, quantised: ~150 kB)."""
    import io

    import matplotlib.pyplot as plt
    from PIL import Image

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=72)
    plt.close(figure)
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=PNG_COLOURS).save(path, optimize=True)
    return path


def plot_broad(broad: BroadResult, which: str, scores: dict[str, list[float]], path: Path) -> Path:
    """A grid of small panels, one per trial: the error over time, movement shaded."""
    curves = broad.inclination_curves if which == "inclination" else broad.heading_curves
    columns = 4
    rows = -(-len(broad.trials) // columns)
    figure, axes = _figure(rows, columns, 16.0, 2.4 * rows + 0.8)
    for i, trial in enumerate(broad.trials):
        axis = axes[i // columns][i % columns]
        for start, end in _runs(trial.movement):
            axis.axvspan(trial.t[start], trial.t[end - 1], color="0.9", lw=0)
        for name in reversed(PLOTTED):  # mavest drawn last, on top
            axis.plot(*_binned_rms(trial.t, curves[trial.name][name]), lw=0.8, color=COLOURS[name])
        title = trial.name.replace("_", " ")
        rmse = ", ".join(f"{name} {scores[name][i]:.2f}°" for name in PLOTTED)
        axis.set_title(f"{title}\n{rmse}", fontsize=8)
        axis.tick_params(labelsize=7)
        axis.set_ylim(bottom=0.0)
        axis.set_xlim(trial.t[0], trial.t[-1])
    for j in range(len(broad.trials), rows * columns):
        axes[j // columns][j % columns].axis("off")
    mode = "6-D inclination" if which == "inclination" else "9-D heading"
    figure.suptitle(
        f"BROAD, {mode} error (°, RMS over {BIN_SECONDS:g} s) over time (s): mavest (blue) and "
        "VQF (orange); scored movement phases shaded; per-trial RMSE in the titles",
        fontsize=11,
    )
    figure.tight_layout(rect=(0, 0, 1, 0.98))
    return _save(figure, path)


def plot_flights(flights: FlightsResult, path: Path) -> Path:
    """Tilt error over time per flight; turns (true bank above 10°) shaded."""
    figure, axes = _figure(len(flights.seeds), 1, 12.0, 2.2 * len(flights.seeds) + 0.6)
    for i, (seed, flight, curves) in enumerate(
        zip(flights.seeds, flights.samples, flights.curves, strict=True)
    ):
        axis = axes[i][0]
        bank = np.abs(np.degrees(euler_zyx_from_quats(flight.truth_q)[:, 0])) > 10.0
        for start, end in _runs(bank):
            axis.axvspan(flight.t[start], flight.t[end - 1], color="0.9", lw=0)
        axis.axvline(flights.settle_time, color="0.5", lw=0.8, ls="--")
        for name in reversed(PLOTTED):
            axis.plot(*_binned_rms(flight.t, curves[name]), lw=0.9, color=COLOURS[name])
        rmse = ", ".join(f"{name} {flights.tilt[name][i]:.2f}°" for name in PLOTTED)
        axis.set_title(
            f"seed {seed}: {rmse} (after {flights.settle_time:g} s); as served "
            f"{flights.tilt[SERVED][i]:.2f}°",
            fontsize=9,
        )
        axis.set_ylim(bottom=0.0)
        axis.set_xlim(flight.t[0], flight.t[-1])
        axis.tick_params(labelsize=8)
    figure.suptitle(
        "JSBSim flights, same RAW_IMU samples: tilt error (°) over time (s), mavest (blue) and "
        "VQF (orange), 6-D; turns (bank > 10°) shaded",
        fontsize=10,
    )
    figure.tight_layout(rect=(0, 0, 1, 0.97))
    return _save(figure, path)


def plot_log171(logs: LogsResult, path: Path) -> Path:
    """log171: ATT's roll and pitch, and mavest's and VQF's tilt error against ATT."""
    log = logs.log171
    assert log is not None
    figure, axes = _figure(2, 1, 12.0, 6.0)
    top, bottom = axes[0][0], axes[1][0]
    euler = np.degrees(euler_zyx_from_quats(log.reference_q))
    top.plot(log.reference_t, euler[:, 0], lw=0.8, color="tab:green", label="roll")
    top.plot(log.reference_t, euler[:, 1], lw=0.8, color="tab:purple", label="pitch")
    top.set_ylabel("ATT (°)")
    top.legend(fontsize=8, loc="upper left")
    for name in PLOTTED:
        inside, q = slerp_onto(log.t, logs.log171_estimates[name], log.reference_t)
        tilt = np.degrees(attitude_errors(q, log.reference_q[inside]).inclination)
        bottom.semilogy(log.reference_t[inside], tilt, lw=0.8, color=COLOURS[name], label=name)
    bottom.set_ylabel("tilt error vs ATT (°)")
    bottom.set_xlabel("time (s from the first IMU sample)")
    bottom.set_ylim(1e-2, 200.0)
    bottom.legend(fontsize=8, loc="upper left")
    for segment in LOGS[DATAFLASH_LOG171].segments:
        if segment.start >= log.duration:  # a shortened copy
            continue
        for axis in (top, bottom):
            axis.axvline(segment.start, color="0.5", lw=0.8, ls="--")
        top.text(segment.start + 1.0, 0.9, segment.label, transform=top.get_xaxis_transform())
    for axis in (top, bottom):
        axis.set_xlim(log.t[0], log.t[-1])
        axis.tick_params(labelsize=8)
    figure.suptitle("ArduCopter log171 (flight and crash): 6-D from the logged IMU", fontsize=10)
    figure.tight_layout()
    return _save(figure, path)


def write_plots(
    folder: Path,
    broad: BroadResult | None,
    logs: LogsResult | None,
    flights: FlightsResult | None,
) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    if broad is not None:
        written.append(
            plot_broad(broad, "inclination", broad.inclination_6d, folder / "broad_inclination.png")
        )
        written.append(plot_broad(broad, "heading", broad.heading_9d, folder / "broad_heading.png"))
    if logs is not None and logs.log171 is not None:
        written.append(plot_log171(logs, folder / "log171.png"))
    if flights is not None:
        written.append(plot_flights(flights, folder / "jsbsim_tilt.png"))
    return written


# --------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------


def _check_packages(parts: Sequence[str], filters: Filters) -> None:
    needed = {
        "VQF": "vqf",
        OFFLINE_VQF: "vqf",
        "Fusion": "imufusion",
        "Madgwick": "ahrs",
        "Mahony": "ahrs",
    }
    modules = {needed[name] for name in filters.names if name in needed}
    if "broad" in parts:
        modules.add("h5py")
    if "flights" in parts:
        modules.add("jsbsim")
    for module in sorted(modules):
        try:
            importlib.import_module(module)
        except ImportError:
            raise MissingInputError(f"the package {module} (dev extra) is not installed") from None


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--quick", action="store_true", help="without Madgwick and Mahony")
    parser.add_argument(
        "--offline", action="store_true", help="also mavest smoothed and offline VQF"
    )
    parser.add_argument("--markdown", action="store_true", help="print Markdown tables")
    report.add_results_option(parser)
    parser.add_argument("--detail", action="store_true", help="per trial, segment and flight")
    parser.add_argument(
        "--plots",
        type=Path,
        nargs="?",
        const=PROJECT / "docs",
        metavar="DIR",
        help="write the PNGs to DIR (default: docs/)",
    )
    parser.add_argument(
        "--parts", nargs="+", choices=PARTS, default=list(PARTS), help="what to run (default: all)"
    )
    parser.add_argument(
        "--trials", nargs="+", metavar="PREFIX", help="only these BROAD trials (name prefixes)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4], help="flights")
    parser.add_argument("--seconds", type=float, default=120.0, help="flight length (s)")
    args = parser.parse_args(argv)
    if args.seconds <= 10.0:
        parser.error("--seconds must be above the 10 s settle time")

    started = time.perf_counter()
    filters = Filters.chosen(args.quick, args.offline)
    try:
        _check_packages(args.parts, filters)
        trials = load_broad(args.trials) if "broad" in args.parts else None
        loaded_logs = load_logs() if "logs" in args.parts else None
    except MissingInputError as error:
        report.progress("evidence", str(error))
        return 2

    # the error curves are NaN where the truth is lost (drawn as gaps); the scoring skips
    # those rows, and a filter's own NaN on a scored row makes its figure n/a, with a line
    np.seterr(all="ignore")
    broad = run_broad(trials, filters) if trials is not None else None
    logs = run_logs(loaded_logs, filters) if loaded_logs is not None else None
    flights = run_flights(args.seeds, args.seconds, filters) if "flights" in args.parts else None

    markdown = args.markdown or args.results is not None
    columns = columns_of(filters, logs, flights)
    with report.results_section(args.results, "Accuracy", __file__, argv, __doc__):
        print(
            format_table(
                "data (RMSE, °)",
                columns,
                main_rows(broad, logs, flights),
                markdown,
                filters.online,
            )
        )
        if broad is not None and broad.notes:
            print("\n" + "\n".join(("- " if markdown else "") + note for note in broad.notes))
        if args.detail:
            for table in detail_tables(filters, broad, logs, flights, markdown):
                print(f"\n{table}")
    sys.stdout.flush()  # the table before the lines on stderr below
    if args.plots is not None:
        for path in write_plots(args.plots, broad, logs, flights):
            _progress(f"wrote {path} ({path.stat().st_size / 1024:.0f} kB)")
    spent = ", ".join(f"{name} {s:.0f} s" for name, s in filters.seconds.items())
    _progress(f"wall time {time.perf_counter() - started:.0f} s; per filter: {spent}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
