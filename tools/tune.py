"""Choose the filter's noise parameters on one half of BROAD, report on the other.

    .venv/bin/python tools/tune.py [--profile adaptive|handheld] [--quick] [--results [FILE]]

Figures measured on the trials the parameters were chosen on flatter a filter: chosen on
the 22 shared BROAD trials, mavest looked 17 % better than VQF there and was 3 % worse
on trials outside them. So the 22 shared trials are split in two halves (alternate
trials of the sorted list: each half holds every kind of motion and disturbance), the
parameters are chosen on one half by the rule below and every figure is reported on
the other, both ways round; then the rule is applied to all 22, which gives the
profile's configuration file (figures on the trials a choice was made on are not
reported as results).

6-D (gyroscope and accelerometer), over the profile's grid of ``gyro_noise_density``
(white rate noise), ``gyro_scale_noise_density`` (rate noise ∝ |ω|: scale and
alignment errors), ``velocity_adapt_time`` (0: the velocity model's σ fixed at
``velocity_sigma``; else measured from the data over that time) and ``velocity_time``
(how long the vehicle's velocity stays correlated: a prior on the vehicle, which the
IMU cannot measure, docs/design.md#motion-level-from-the-data) and
``accel_alignment_sigma`` (the accelerometer's alignment, added to the tilt σ: one
filter run serves every value of it, :data:`ALIGNMENTS`): among the
combinations whose mean inclination RMSE on the tuning half is within
:data:`ACCURACY_SLACK` of the best, the one with the most trials whose tilt
calibration ratio (RMS error / RMS σ, :mod:`mavest.evaluation.calibration`) lies in
:data:`CALIBRATED`; ties go to the higher median σ–error rank correlation. Accuracy
first, then honesty. The profiles (:data:`PROFILES`):

* ``adaptive`` (configs/adaptive.toml): for any vehicle; the velocity's correlation
  time stays the default's 1 s, and the white rate noise at 0.005.
* ``handheld`` (configs/handheld.toml): for motion that goes back and forth within
  reach, as BROAD's hand-held trials do; the correlation time, the white rate noise and
  the accelerometer's alignment are chosen too.

9-D, with the 6-D choice: ``mag_heading_noise_density`` over :data:`GRID_MAG`, the one
with the lowest mean total RMSE on the tuning half.

Held-out, per direction: mavest (its choice), mavest's defaults and VQF on the same
trials; the paired per-trial differences (how many trials mavest is better on, the
median difference); tilt calibration (trials in the band, median ρ); 9-D total RMSE
likewise. mavest's defaults were chosen on the 22 shared trials
(:data:`mavest.datasets.broad.TUNED_ON`), so their figures are held out only on trials
outside those: the tables say on how many of each half, and of which trial, they were.
The closing line is this run's choice on all its trials, compared with what the
profile's file sets. ``--results`` writes the tables as the profile's Cross-validation
section of docs/results.md (or FILE).

Any folder of BROAD-format trials will do (``MAVEST_DATA``): a file that is not a
readable trial, a second copy of a recording, or a trial with nothing to score is left
out with one line; fewer than two trials left, or no BROAD folder, is one line and
exit 2.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import mavest
from mavest import EstimatorConfig
from mavest.datasets.broad import (
    TUNED_ON,
    BroadTrial,
    halves,
    halves_named,
    lowest_mean,
    trials_to_split,
    tuned_on,
)
from mavest.estimator.config import ConfigError
from mavest.estimator.frames import add_alignment
from mavest.evaluation import report
from mavest.evaluation.calibration import score_attitude
from mavest.evaluation.metrics import rmse_deg
from mavest.evaluation.peers import PEERS

#: (gyro_noise_density, gyro_scale_noise_density, velocity_adapt_time, velocity_time,
#: accel_alignment_sigma)
Values = tuple[float, float, float, float, float]


@dataclass(frozen=True)
class Profile:
    """A kind of use, the grid its parameters are chosen from and its configuration file."""

    name: str
    title: str  # of its section in docs/results.md
    config_file: str
    grid: tuple[Values, ...]
    quick_grid: tuple[Values, ...]

    def filter_runs(self, grid: Sequence[Values]) -> dict[Values, list[Values]]:
        """The grid's points by the filter run they share: the accelerometer's alignment
        changes only the covariance reported, added to one run's (:func:`score_6d`)."""
        runs: dict[Values, list[Values]] = {}
        for values in grid:
            runs.setdefault((*values[:4], 0.0), []).append(values)
        return runs


#: The white rate noise of ``adaptive`` stays at 0.005 rad/s/√Hz, five times a MEMS
#: gyro's: it is also how fast a confidently wrong attitude becomes uncertain enough to
#: be corrected without reopening it, and at 0.002 a tilt 30° off with σ 0.06° is still
#: 25° off after a minute at rest (tests/test_health.py asks the defaults for it within
#: the minute; with reopening, as configured, the accelerometer takes over after
#: ``accel_max_disturbance_time``). ``handheld`` may choose less.
#: The level is averaged over 1 or 3 s: over 10 s it lags a drop in the motion, and the
#: Monte Carlo whose level falls from 3 to 0.5 m/s ends conservative (last 10 s' ANEES
#: 4.3 of 6 over 30 runs, against 5.5 with 1 s; tools/consistency.py, changing_motion).
#: The velocity's correlation time is a prior on the vehicle: the accelerometer cannot
#: tell linear acceleration from gravity below the low-pass's corner, so the data cannot
#: measure it; ``adaptive`` keeps the default's 1 s (a vehicle's accelerations may last
#: seconds), ``handheld`` chooses among shorter ones.
#: The accelerometer's alignment, rad (0.1° to 0.3°): the tilt its averaged reading shows
#: against BROAD's optical truth over the trials' rests is 0.05–0.33° (docs/design.md#the-
#: accelerometers-alignment). ``adaptive`` keeps none: its σ is too large on BROAD as it is.
ALIGNMENTS = tuple(math.radians(a) for a in (0.0, 0.1, 0.15, 0.2, 0.25, 0.3))
PROFILES = {
    "adaptive": Profile(
        "adaptive",
        "Cross-validation",
        "configs/adaptive.toml",
        tuple(
            itertools.product(
                (0.005,), (0.0, 0.0007, 0.0015, 0.003, 0.006), (0.0, 1.0, 3.0), (1.0,), (0.0,)
            )
        ),
        ((0.005, 0.0, 0.0, 1.0, 0.0), (0.005, 0.0015, 3.0, 1.0, 0.0)),
    ),
    "handheld": Profile(
        "handheld",
        "Cross-validation, hand-held motion",
        "configs/handheld.toml",
        tuple(
            itertools.product(
                (0.005, 0.002, 0.001),
                (0.0, 0.0007, 0.0015, 0.003),
                (1.0, 3.0),
                (1.0, 0.3, 0.1),
                ALIGNMENTS,
            )
        ),
        ((0.005, 0.0, 1.0, 1.0, 0.0), (0.001, 0.0015, 3.0, 0.1, ALIGNMENTS[-1])),
    ),
}
GRID_MAG: tuple[float, ...] = (0.02, 0.04, 0.08, 0.16)
ACCURACY_SLACK = 0.03  # a combination this much less accurate than the best still competes
CALIBRATED = (0.6, 1.6)
#: mavest's defaults: the velocity's level fixed, no rate noise
DEFAULT = EstimatorConfig()
QUICK_TRIALS = 4
ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class TrialScore:
    inclination: float  # RMSE °, 6-D
    ratio: float  # tilt calibration ratio, 6-D
    rho: float  # σ–error rank correlation over 1 s windows, 6-D


def config_6d(values: Values) -> EstimatorConfig:
    gyro, scale, adapt, velocity_time, alignment = values
    return EstimatorConfig(
        gyro_noise_density=gyro,
        gyro_scale_noise_density=scale,
        velocity_adapt_time=adapt,
        velocity_time=velocity_time,
        accel_alignment_sigma=alignment,
    )


def describe(values: Values, mag: float) -> str:
    gyro, scale, adapt, velocity_time, alignment = values
    return (
        f"gyro {gyro:g}, scale {scale:g}, adapt {adapt:g} s, velocity time "
        f"{velocity_time:g} s, alignment {math.degrees(alignment):g}°, mag {mag:g}"
    )


def score_6d(
    trial: BroadTrial, config: EstimatorConfig, alignments: Sequence[float] | None = None
) -> list[TrialScore]:
    """The trial's scores with ``config``, for each of these accelerometer alignments
    (rad) in its place (None: the config's own): one filter run, the alignment added to
    its covariance as the filter adds it (:func:`mavest.estimator.frames.add_alignment`)."""
    if alignments is None:
        alignments = (config.accel_alignment_sigma,)
    base = config.replace(accel_alignment_sigma=0.0)
    series = mavest.estimate(trial.t, trial.gyro, trial.accel, None, base)
    inclination = rmse_deg(series.q, trial.truth_q, trial.movement)["inclination"]
    scores = []
    for alignment in alignments:
        cov = series.cov.copy()
        add_alignment(series.q, alignment**2, config.error == "right", cov)
        tilt, _, _ = score_attitude(
            trial.t, series.q, cov, trial.truth_q, trial.movement, config.error
        )
        scores.append(TrialScore(inclination, tilt.ratio, tilt.rank_correlation))
    return scores


def total_9d(trial: BroadTrial, config: EstimatorConfig) -> float:
    series = mavest.estimate(trial.t, trial.gyro, trial.accel, trial.mag, config)
    return rmse_deg(series.q, trial.truth_q, trial.movement)["total"]


def _calibrated(scores: Sequence[TrialScore]) -> int:
    lo, hi = CALIBRATED
    return sum(lo <= s.ratio <= hi for s in scores)


def _median_rho(scores: Sequence[TrialScore]) -> float:
    finite = [s.rho for s in scores if np.isfinite(s.rho)]
    return statistics.median(finite) if finite else float("nan")


def choose_6d(table: dict[Values, list[TrialScore]], subset: Sequence[int]) -> Values:
    """The rule: accuracy within the slack of the best, then calibration, then ρ."""
    mean = {k: float(np.mean([v[i].inclination for i in subset])) for k, v in table.items()}
    best = min(mean.values())
    competing = [k for k in table if mean[k] <= best * (1.0 + ACCURACY_SLACK)]

    def merit(k: Values) -> tuple[int, float, float]:
        picked = [table[k][i] for i in subset]
        return (_calibrated(picked), _median_rho(picked), -mean[k])

    return max(competing, key=merit)


@dataclass(frozen=True)
class Direction:
    tuned_on: str
    held_out: str
    subset: list[int]  # the held-out trials
    choice_6d: Values
    choice_mag: float


def held_out_table(
    trials: Sequence[BroadTrial],
    directions: Sequence[Direction],
    table_6d: dict[Values, list[TrialScore]],
    table_mag: dict[tuple[Values, float], list[float]],
    default: list[TrialScore],
    default_9d: list[float],
    vqf: list[float],
    vqf_9d: list[float],
) -> str:
    lines = [
        "| tuned on → reported on | chosen | 6-D inclination RMSE: mavest / default / VQF "
        "| mavest − VQF, paired | tilt σ calibrated (ratio in [0.6, 1.6]) | median ρ "
        "| 9-D total RMSE: mavest / default / VQF | 9-D mavest − VQF, paired "
        "| defaults chosen on these trials |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in directions:
        ours = [table_6d[d.choice_6d][i] for i in d.subset]
        defaults = [default[i] for i in d.subset]
        incl = np.array([s.inclination for s in ours])
        incl_vqf = np.array([vqf[i] for i in d.subset])
        total = np.array([table_mag[(d.choice_6d, d.choice_mag)][i] for i in d.subset])
        total_vqf = np.array([vqf_9d[i] for i in d.subset])
        lines.append(
            f"| {d.tuned_on} → {d.held_out} | {describe(d.choice_6d, d.choice_mag)} "
            f"| {incl.mean():.3f}° / {np.mean([s.inclination for s in defaults]):.3f}° / "
            f"{incl_vqf.mean():.3f}° ({incl.mean() / incl_vqf.mean():.2f}×) "
            f"| {report.paired(incl, incl_vqf)} "
            f"| {_calibrated(ours)} of {len(ours)} (default {_calibrated(defaults)}) "
            f"| {_median_rho(ours):+.2f} (default {_median_rho(defaults):+.2f}) "
            f"| {total.mean():.3f}° / {np.mean([default_9d[i] for i in d.subset]):.3f}° / "
            f"{total_vqf.mean():.3f}° ({total.mean() / total_vqf.mean():.2f}×) "
            f"| {report.paired(total, total_vqf)} "
            f"| {sum(tuned_on(trials[i].name) for i in d.subset)} of {len(d.subset)} |"
        )
    return "\n".join(lines)


def per_trial_table(
    trials: Sequence[BroadTrial],
    directions: Sequence[Direction],
    table_6d: dict[Values, list[TrialScore]],
    vqf: list[float],
) -> str:
    lines = [
        "| trial | held out in | inclination: mavest / VQF | tilt ratio | ρ "
        "| defaults chosen on it |",
        "|---|---|---|---|---|---|",
    ]
    for d in directions:
        for i in d.subset:
            s = table_6d[d.choice_6d][i]
            lines.append(
                f"| {trials[i].name} | {d.held_out} | {s.inclination:.3f}° / {vqf[i]:.3f}° "
                f"| {s.ratio:.2f} | {s.rho:+.2f} "
                f"| {'yes' if tuned_on(trials[i].name) else 'no'} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument(
        "--profile", choices=list(PROFILES), default="adaptive", help="which (default: adaptive)"
    )
    parser.add_argument("--quick", action="store_true", help="two combinations, four trials")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    profile = PROFILES[args.profile]
    start = time.perf_counter()
    trials = _load(args.quick)
    if trials is None:
        return 2
    grid = profile.quick_grid if args.quick else profile.grid
    vqf = [rmse_deg(_peer(t, False), t.truth_q, t.movement)["inclination"] for t in trials]
    vqf_9d = [rmse_deg(_peer(t, True), t.truth_q, t.movement)["total"] for t in trials]
    default = [score_6d(t, DEFAULT)[0] for t in trials]
    default_9d = [total_9d(t, DEFAULT) for t in trials]
    table_6d: dict[Values, list[TrialScore]] = {}
    for run, points in profile.filter_runs(grid).items():
        per_trial = [score_6d(t, config_6d(run), [v[4] for v in points]) for t in trials]
        for k, values in enumerate(points):
            table_6d[values] = [scores[k] for scores in per_trial]
        print(
            f"6-D {run[:4]}: {np.mean([s[0].inclination for s in per_trial]):.3f}°",
            file=sys.stderr,
            flush=True,
        )
    a, b = halves(trials)
    everything = list(range(len(trials)))
    choices = {name: choose_6d(table_6d, subset) for name, subset in (("A", a), ("B", b))}
    choices["all"] = choose_6d(table_6d, everything)
    table_mag: dict[tuple[Values, float], list[float]] = {}
    for values in sorted(set(choices.values())):
        for density in GRID_MAG:
            config = dataclasses.replace(config_6d(values), mag_heading_noise_density=density)
            table_mag[(values, density)] = [total_9d(t, config) for t in trials]

    def mag_for(values: Values, subset: Sequence[int]) -> float:
        per = {k[1]: v for k, v in table_mag.items() if k[0] == values}
        return lowest_mean(per, subset)

    directions = [
        Direction("A", "B", b, choices["A"], mag_for(choices["A"], a)),
        Direction("B", "A", a, choices["B"], mag_for(choices["B"], b)),
    ]
    overall = (choices["all"], mag_for(choices["all"], everything))
    gyro, scale, adapt, velocity_time, alignment = overall[0]
    in_sample = sum(tuned_on(t.name) for t in trials)
    with report.results_section(args.results, profile.title, __file__, argv, __doc__):
        print(
            f"Profile {profile.name} ({profile.config_file}). Halves of the {len(trials)} "
            f"BROAD trials ({in_sample} of them among the {len(TUNED_ON)} mavest's defaults "
            "were chosen on): "
            + halves_named([t.name for t in trials], a, b)
            + ". Every figure below is on the half the parameters were **not** chosen on, "
            "except the defaults': mavest's defaults were chosen on the "
            f"{len(TUNED_ON)} trials of mavest.datasets.broad.TUNED_ON, so on those "
            "(columns 'defaults chosen on') their figures are in-sample."
        )
        print()
        print(
            held_out_table(
                trials, directions, table_6d, table_mag, default, default_9d, vqf, vqf_9d
            )
        )
        print()
        print(per_trial_table(trials, directions, table_6d, vqf))
        print()
        print(
            f"The rule applied to all {len(trials)} trials, this run's choice (the defaults "
            "keep the velocity's level fixed): gyro_noise_density "
            f"{gyro:g}, gyro_scale_noise_density {scale:g}, velocity_adapt_time {adapt:g} s, "
            f"velocity_time {velocity_time:g} s, accel_alignment_sigma "
            f"{math.degrees(alignment):g}° ({alignment:.6g} rad), "
            f"mag_heading_noise_density {overall[1]:g}. "
            + against_file(profile, overall)
            + " (In the A → B and B → A rows the halves chose "
            + "; ".join(f"{d.tuned_on}: {describe(d.choice_6d, d.choice_mag)}" for d in directions)
            + ".)"
        )
    print(f"\n({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


def _load(quick: bool) -> list[BroadTrial] | None:
    """The trials to tune on (the first :data:`QUICK_TRIALS` usable ones with
    ``quick``), or None after one line saying why there are too few to split."""

    say = functools.partial(report.progress, "tune")

    return trials_to_split(say, QUICK_TRIALS if quick else None)


#: The keys the closing line reports: :data:`Values`' order, then the magnetometer's.
RULE_KEYS = (
    "gyro_noise_density",
    "gyro_scale_noise_density",
    "velocity_adapt_time",
    "velocity_time",
    "accel_alignment_sigma",
    "mag_heading_noise_density",
)


def against_file(profile: Profile, overall: tuple[Values, float]) -> str:
    """A sentence comparing this run's choice with what the profile's file sets."""
    chosen = dict(zip(RULE_KEYS, (*overall[0], overall[1]), strict=True))
    try:
        config = EstimatorConfig.from_toml(ROOT / profile.config_file)
    except (OSError, ConfigError) as error:
        return f"({profile.config_file} could not be read to compare: {error}.)"

    def show(key: str, value: float) -> str:  # (in the units above)
        if key == "accel_alignment_sigma":
            return f"{math.degrees(value):g}°"
        return f"{value:g} s" if key.endswith("_time") else f"{value:g}"

    differ = [
        f"{key} {show(key, getattr(config, key))} (this run {show(key, value)})"
        for key, value in chosen.items()
        if not math.isclose(getattr(config, key), value, rel_tol=1e-9, abs_tol=0.0)
    ]
    if not differ:
        return f"{profile.config_file} sets the same."
    return f"{profile.config_file} sets otherwise: " + ", ".join(differ) + "."


def _peer(trial: BroadTrial, mag: bool) -> np.ndarray:
    return PEERS["VQF"](trial.t, trial.gyro, trial.accel, trial.mag if mag else None, trial.rate)


if __name__ == "__main__":
    sys.exit(main())
