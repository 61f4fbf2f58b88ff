"""Whether mavest's σ is calibrated and informative: its covariance scored against truth.

    .venv/bin/python tools/covariance.py [--parts broad sim] [--trials 02 07 ...]
                                         [--split odd|even|all] [--seeds 0 1 2 3]
                                         [--scenario NAME ...] [--estimator NAME ...]
                                         [--config FILE ...] [--quick] [--results [FILE]]

Each estimator (mavest with its defaults, with configs/adaptive.toml and with
configs/handheld.toml, and mavest.smooth with each when the package has it; with
--config FILE also both with that configuration, keys not given taking the defaults)
runs on every BROAD
trial ($MAVEST_DATA/broad; 6-D, and 9-D with the magnetometer) and on simulated flights
of the Monte Carlo's scenarios (mavest.evaluation.consistency; one per distinct flight
model and seed). Per recording and quantity — tilt, and in 9-D heading — it prints
(mavest.evaluation.calibration): the RMS error |e|; σ per axis, sqrt(tr P / dof) (mean,
1st–95th percentile); the calibration ratio sqrt(mean |e|² / mean tr P) (1: honest;
below 1: σ too large); the share of samples inside the 95 % region of P; and Spearman's
ρ between RMS error and RMS σ over 1 s windows (positive: σ is large where the error
is). BROAD is scored over its movement phases, a flight after its first 5 s. In 9-D on
BROAD the optical frame's north is not the magnetic field's: a constant heading
offset, fitted over the scored samples and shown, is removed before scoring (tilt is
unaffected by it).

mavest's defaults were chosen on 22 BROAD trials (mavest.datasets.broad.TUNED_ON):
figures on those are in-sample. Each BROAD row and table is over one kind of trial,
those the defaults were tuned on or those held out from them, and says which; a
line after the summary counts them. A trial with nothing to score (no movement
sample with truth) is left out, with a line. --split odd|even keeps the odd- or
even-numbered trials (the number a trial's name starts with; a trial without one is
left out, with a line); --quick scores three BROAD trials (unless --trials names
them) and one short flight per scenario. --results writes the printed tables as the
"Covariance on real data" section of docs/results.md (or FILE). Exits 2, with one
line, when BROAD or h5py is missing.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

import mavest
from mavest import ConfigError, EstimatorConfig
from mavest.datasets import DATA_ENV_VAR
from mavest.datasets.broad import list_trials, load_trials, tuned_on
from mavest.evaluation import report
from mavest.evaluation.calibration import Calibration, rank_correlation, score_attitude
from mavest.evaluation.consistency import SCENARIOS, distinct_flights, simulate_scenario
from mavest.evaluation.metrics import scored_rows, trial_parity

PARTS = ("broad", "sim")
SPLITS = ("all", "odd", "even")
SETTLE = 5.0  # s: a simulated flight is scored after the filter's alignment
QUICK_TRIALS = 3  # BROAD trials --quick scores, spread over the selection
QUICK_SECONDS = 30.0  # s: a simulated flight's length with --quick
CALIBRATED = (0.6, 1.6)  # the ratio band counted as calibrated
INFORMATIVE = 0.3  # ρ from which σ counts as informative
TUNED = "defaults tuned on these"
HELD_OUT = "held out: defaults not tuned on these"


class MissingInputError(Exception):
    """BROAD or a package it needs is absent: one line for the user."""


@dataclass(frozen=True)
class Recording:
    """Samples (FRD, SI), the truth (body → NED) and which samples are scored."""

    source: str  # "BROAD" or "simulated"
    name: str
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    mag: np.ndarray | None  # None: 6-D
    truth_q: np.ndarray
    scored: np.ndarray  # (N,) bool
    # the truth's north is not the field's (BROAD's optical frame): fit and remove a
    # constant heading offset before scoring heading
    foreign_north: bool = False
    # BROAD: mavest's defaults were chosen on this trial (its figures are in-sample)
    tuned: bool = False

    @property
    def mode(self) -> str:
        return "6-D" if self.mag is None else "9-D"


Run = Callable[[Recording], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class NamedEstimator:
    """An estimator scored by the tool: recording → q (N, 4) and cov (N, 6, 6), whose
    attitude error is ``error`` ("left": world frame, "right": body frame)."""

    name: str
    run: Run
    error: Literal["left", "right"]


def _running(function: Callable[..., mavest.EstimateSeries], config: EstimatorConfig | None) -> Run:
    """``function`` (mavest.estimate or mavest.smooth) with ``config`` (None: the defaults)
    as a recording's estimator."""

    def run(recording: Recording) -> tuple[np.ndarray, np.ndarray]:
        series = function(recording.t, recording.gyro, recording.accel, recording.mag, config)
        return series.q, series.cov

    return run


CONFIGS = Path(__file__).resolve().parents[1] / "configs"
ADAPTIVE = EstimatorConfig.from_toml(CONFIGS / "adaptive.toml")
HANDHELD = EstimatorConfig.from_toml(CONFIGS / "handheld.toml")


def estimators(configs: Sequence[Path] = ()) -> list[NamedEstimator]:
    """mavest's filter with its defaults, with the motion level measured
    (configs/adaptive.toml) and with the hand-held profile (configs/handheld.toml), then,
    when the package has one, its smoother with each; then the filter and the smoother
    with each of ``configs`` (TOML files, as the service reads them), named after the
    file. Adding an estimator is one entry here."""
    functions = [("mavest", mavest.estimate)]
    if hasattr(mavest, "smooth"):
        functions.append(("mavest.smooth", mavest.smooth))
    builtin: list[tuple[str, EstimatorConfig | None]] = [
        ("", None),
        (" adaptive", ADAPTIVE),
        (" handheld", HANDHELD),
    ]
    entries = [
        NamedEstimator(f"{name}{suffix}", _running(function, config), _error(config))
        for name, function in functions
        for suffix, config in builtin
    ]
    for path in configs:
        config = EstimatorConfig.from_toml(path)
        entries += [
            NamedEstimator(f"{name} ({path.name})", _running(function, config), config.error)
            for name, function in functions
        ]
    return entries


def _error(config: EstimatorConfig | None) -> Literal["left", "right"]:
    return (config or EstimatorConfig()).error


# --------------------------------------------------------------------------
# Recordings
# --------------------------------------------------------------------------


def broad_recordings(prefixes: Sequence[str] | None, split: str, quick: bool) -> list[Recording]:
    """BROAD trials, each as a 6-D and a 9-D recording, scored over its movement phases."""
    try:
        importlib.import_module("h5py")
    except ImportError:
        raise MissingInputError("the package h5py (dev extra) is needed to read BROAD") from None
    try:
        paths = list_trials(prefixes=prefixes)
    except FileNotFoundError as error:
        raise MissingInputError(str(error)) from None
    if split != "all":
        for path in paths:
            if trial_parity(path.stem) is None:
                _warn(f"--split {split}: {path.stem} has no trial number: left out")
        paths = [p for p in paths if trial_parity(p.stem) == (split == "odd")]
    if quick and not prefixes and len(paths) > QUICK_TRIALS:
        picks = np.linspace(0, len(paths) - 1, QUICK_TRIALS).round().astype(int)
        paths = [paths[i] for i in picks]
    if not paths:
        wanted = f" matching --trials {' '.join(prefixes)}" if prefixes else ""
        raise MissingInputError(f"no BROAD .hdf5 trial{wanted} in {DATA_ENV_VAR}'s broad/")
    recordings = []
    # (a bad file, a copy of a trial, one with nothing to score: left out with a line)
    for trial in load_trials(paths, _warn, scored_only=True):
        for mag in (None, trial.mag):
            recordings.append(
                Recording(
                    "BROAD",
                    trial.name,
                    trial.t,
                    trial.gyro,
                    trial.accel,
                    mag,
                    trial.truth_q,
                    trial.movement,
                    foreign_north=True,
                    tuned=tuned_on(trial.name),
                )
            )
    if not recordings:
        raise MissingInputError("no BROAD trial here has a movement sample with truth to score")
    return recordings


def _warn(text: str) -> None:
    """One line on an input left out; the run goes on."""
    report.progress("covariance", text)


def simulated_recordings(
    names: Sequence[str] | None, seeds: Sequence[int], quick: bool
) -> list[Recording]:
    """A flight per distinct scenario and seed, with the noise and motion the default
    configuration claims (bursts on top), scored after :data:`SETTLE`."""
    config = EstimatorConfig()
    recordings = []
    for scenario in distinct_flights(names):
        if quick:
            scenario = dataclasses.replace(scenario, duration=QUICK_SECONDS)
        for seed in seeds:
            flight = simulate_scenario(scenario, config, seed)
            recordings.append(
                Recording(
                    "simulated",
                    f"{scenario.name} seed {seed}",
                    flight.t,
                    flight.gyro,
                    flight.accel,
                    flight.mag if scenario.magnetometer else None,
                    flight.q_true,
                    flight.t - flight.t[0] >= SETTLE,
                )
            )
    return recordings


# --------------------------------------------------------------------------
# Scoring
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Scored:
    """One estimator on one recording: tilt and (9-D) heading, and the offset removed."""

    estimator: str
    recording: Recording
    tilt: Calibration
    heading: Calibration | None
    north_offset: float  # rad, turned off the estimate before scoring


def score(
    recording: Recording, q: np.ndarray, cov: np.ndarray, error: Literal["left", "right"]
) -> tuple[Calibration, Calibration | None, float]:
    """Tilt and (9-D) heading calibration of an estimate over the scored samples, and
    the heading offset removed (0 unless the truth's north is foreign)."""
    return score_attitude(
        recording.t,
        q,
        cov,
        recording.truth_q,
        recording.scored,
        error,
        heading=recording.mag is not None,
        foreign_north=recording.foreign_north,
    )


def run_all(recordings: list[Recording], entries: list[NamedEstimator]) -> list[Scored]:
    results = []
    for index, recording in enumerate(recordings, 1):
        print(
            f"{recording.source} {recording.name} {recording.mode} ({index}/{len(recordings)})",
            file=sys.stderr,
            flush=True,
        )
        for entry in entries:
            q, cov = entry.run(recording)
            # the calibration skips samples without an estimate as it does lost truth:
            # say so, so that a filter giving up where it is worst is not taken for honest
            given = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
            rows = scored_rows(recording.truth_q, recording.scored)
            if lacking := int(np.count_nonzero(rows & ~given)):
                _warn(
                    f"{entry.name} left {lacking} of the {np.count_nonzero(rows)} scored samples "
                    f"of {recording.name} {recording.mode} without an estimate and covariance: "
                    "scored on the rest"
                )
            tilt, heading, offset = score(recording, q, cov, entry.error)
            results.append(Scored(entry.name, recording, tilt, heading, offset))
    return results


# --------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------


def _deg(value: float, digits: int = 2) -> str:
    return "—" if not math.isfinite(value) else f"{math.degrees(value):.{digits}f}"


def _number(value: float, digits: int = 2) -> str:
    return "—" if not math.isfinite(value) else f"{value:.{digits}f}"


#: (estimator, source, mode, quantity, kind): kind is, on BROAD, TUNED or HELD_OUT
Key = tuple[str, str, str, str, str]


def _kind(recording: Recording) -> str:
    """Which trials a BROAD recording's rows are pooled with: those mavest's defaults were
    tuned on or those held out (a mean over both would be neither)."""
    if recording.source != "BROAD":
        return ""
    return TUNED if recording.tuned else HELD_OUT


def groups(results: list[Scored]) -> dict[Key, list[tuple[Scored, Calibration]]]:
    """(estimator, source, mode, quantity, kind) → its rows: an estimator's groups
    together, in the order the estimators and recordings were run, the trials it was
    tuned on before those held out."""
    order = list(dict.fromkeys(r.estimator for r in results))
    grouped: dict[Key, list[tuple[Scored, Calibration]]] = {}
    for r in sorted(results, key=lambda r: order.index(r.estimator)):  # stable
        quantities = [("tilt", r.tilt)] + ([("heading", r.heading)] if r.heading else [])
        for quantity, c in quantities:
            key = (r.estimator, r.recording.source, r.recording.mode, quantity, _kind(r.recording))
            grouped.setdefault(key, []).append((r, c))
    first = list(dict.fromkeys(key[:4] for key in grouped))
    kinds = ["", TUNED, HELD_OUT]
    keys = sorted(grouped, key=lambda k: (first.index(k[:4]), kinds.index(k[4])))
    return {key: grouped[key] for key in keys}


def _title(source: str, mode: str, quantity: str, kind: str) -> str:
    return f"{source} {mode} {quantity}" + (f" ({kind})" if kind else "")


def tuned_note(recordings: Sequence[Recording]) -> str | None:
    """How many of the BROAD trials here mavest's defaults were chosen on (None: no
    BROAD trial), in words that are true of this selection."""
    trials = {r.name: r.tuned for r in recordings if r.source == "BROAD"}
    if not trials:
        return None
    n, tuned = len(trials), sum(trials.values())
    if tuned == n:
        these = "this trial" if n == 1 else f"all {n} of these trials"
        return (
            f"BROAD: mavest's defaults were chosen on {these}, so none of its BROAD figures "
            "here is held out."
        )
    if tuned == 0:
        these = "this trial" if n == 1 else f"any of these {n} trials"
        return (
            f"BROAD: mavest's defaults were not chosen on {these}: every BROAD figure here "
            "is held out."
        )
    return (
        f"BROAD: mavest's defaults were chosen on {tuned} of these {n} trials (rows "
        f'"{TUNED}"); the other {n - tuned} {"is" if n - tuned == 1 else "are"} held out '
        f'(rows "{HELD_OUT}").'
    )


def detail_table(key: Key, rows: list[tuple[Scored, Calibration]]) -> str:
    estimator, source, mode, quantity, kind = key
    offset = source == "BROAD" and mode == "9-D"
    lines = [
        f"### {estimator}: {_title(source, mode, quantity, kind)}",
        "",
        "| recording | samples | RMSE ° | σ/axis mean ° | σ/axis p1–p95 ° | ratio | inside 95 % "
        "| ρ (windows) |" + (" north offset ° |" if offset else ""),
        "|---|---|---|---|---|---|---|---|" + ("---|" if offset else ""),
    ]
    for r, c in rows:
        line = (
            f"| {r.recording.name} | {c.samples} | {_deg(c.rmse)} | {_deg(c.sigma_mean)} | "
            f"{_deg(c.sigma_p1)}–{_deg(c.sigma_p95)} | {_number(c.ratio)} | "
            f"{_number(100.0 * c.inside, 1)} % | {_number(c.rank_correlation)} ({c.windows}) |"
        )
        if offset:
            line += f" {_deg(r.north_offset)} |"
        lines.append(line)
    return "\n".join(lines)


def summary_table(grouped: dict[Key, list[tuple[Scored, Calibration]]]) -> str:
    low, high = CALIBRATED
    lines = [
        "| estimator | data | recordings | ratio min–max | ratio in "
        f"[{low}, {high}] | median ρ | ρ ≥ {INFORMATIVE} | ρ, windows pooled | inside 95 %, mean "
        "| σ/axis mean ° |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, rows in grouped.items():
        estimator, source, mode, quantity, kind = key
        ratios = [c.ratio for _, c in rows if math.isfinite(c.ratio)]
        rhos = [c.rank_correlation for _, c in rows if math.isfinite(c.rank_correlation)]
        calibrated = sum(low <= x <= high for x in ratios)
        informative = sum(x >= INFORMATIVE for x in rhos)
        inside = statistics.fmean(c.inside for _, c in rows if math.isfinite(c.inside))
        sigma = statistics.fmean(c.sigma_mean for _, c in rows if math.isfinite(c.sigma_mean))
        pooled = rank_correlation(
            np.concatenate([c.window_sigma for _, c in rows]),
            np.concatenate([c.window_error for _, c in rows]),
        )
        spread = f"{min(ratios):.2f}–{max(ratios):.2f}" if ratios else "—"
        lines.append(
            f"| {estimator} | {_title(source, mode, quantity, kind)} | {len(rows)} | {spread} | "
            f"{calibrated} of {len(rows)} | "
            f"{_number(statistics.median(rhos)) if rhos else '—'} | {informative} of "
            f"{len(rows)} | {_number(pooled)} | {100.0 * inside:.1f} % | {_deg(sigma)} |"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument(
        "--parts", nargs="+", choices=PARTS, default=list(PARTS), help="what to run (default: all)"
    )
    parser.add_argument(
        "--trials", nargs="+", metavar="PREFIX", help="only these BROAD trials (name prefixes)"
    )
    parser.add_argument(
        "--split", choices=SPLITS, default="all", help="BROAD trials by the parity of their number"
    )
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="simulated flights per scenario"
    )
    parser.add_argument(
        "--scenario", action="append", choices=[s.name for s in SCENARIOS], help="only these"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"{QUICK_TRIALS} BROAD trials, one {QUICK_SECONDS:g} s flight per scenario",
    )
    report.add_config_option(parser, "also the filter and the smoother with this configuration")
    parser.add_argument(
        "--estimator", action="append", help="only these (default: every one the package has)"
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    try:
        available = estimators(args.config)
    except ConfigError as error:
        parser.error(f"--config: {error}")
    names = [entry.name for entry in available]
    for name in args.estimator or []:
        if name not in names:
            parser.error(f"--estimator {name!r}: one of {', '.join(map(repr, names))}")

    started = time.perf_counter()
    try:
        recordings = []
        if "broad" in args.parts:
            recordings += broad_recordings(args.trials, args.split, args.quick)
        if "sim" in args.parts:
            seeds = args.seeds[:1] if args.quick else args.seeds
            recordings += simulated_recordings(args.scenario, seeds, args.quick)
    except MissingInputError as error:
        report.progress("covariance", str(error))
        return 2
    entries = [e for e in available if not args.estimator or e.name in args.estimator]
    results = run_all(recordings, entries)
    grouped = groups(results)

    title = "Covariance on real data"
    with report.results_section(args.results, title, __file__, argv, __doc__):
        print(
            f"Calibration of the predicted attitude covariance, {len(recordings)} recordings, "
            f"estimators: {', '.join(e.name for e in entries)}. "
            "Ratio: sqrt(mean |e|² / mean tr P), 1 when honest (the RMS error |e| counts "
            "every axis, σ is per axis); ρ: Spearman, "
            "RMS σ against RMS error over 1 s windows.\n"
        )
        print(summary_table(grouped))
        if note := tuned_note(recordings):
            print(f"\n{note}")
        for key, rows in grouped.items():
            print(f"\n{detail_table(key, rows)}")
    print(f"wall time {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
