"""Choose the filter's noise parameters on one half of BROAD, report on the other.

    .venv/bin/python tools/tune.py [--quick] [--results [FILE]]

Figures measured on the trials the parameters were chosen on flatter a filter: chosen on
the 22 shared BROAD trials, mavest looked 17 % better than VQF there and was 3 % worse
on trials outside them. So the 22 shared trials are split in two halves (alternate
trials of the sorted list: each half holds every kind of motion and disturbance), the
parameters are chosen on one half by the rule below and every figure is reported on
the other, both ways round; then the rule is applied to all 22, which gives
configs/adaptive.toml (figures on the trials a choice was made on are not reported as
results).

6-D (gyroscope and accelerometer), over the grid :data:`GRID_6D` of
``gyro_noise_density`` (white rate noise), ``gyro_scale_noise_density`` (rate noise
∝ |ω|: scale and alignment errors) and ``velocity_adapt_time`` (0: the velocity
model's σ fixed at ``velocity_sigma``; else measured from the data over that time):
among the combinations whose mean inclination RMSE on the tuning half is within
:data:`ACCURACY_SLACK` of the best, the one with the most trials whose tilt
calibration ratio (RMS error / RMS σ, :mod:`mavest.evaluation.calibration`) lies in
:data:`CALIBRATED`; ties go to the higher median σ–error rank correlation. Accuracy
first, then honesty.

9-D, with the 6-D choice: ``mag_heading_noise_density`` over :data:`GRID_MAG`, the one
with the lowest mean total RMSE on the tuning half.

Held-out, per direction: mavest (its choice), mavest's previous defaults and VQF on
the same trials; the paired per-trial differences (how many trials mavest is better
on, the median difference); tilt calibration (trials in the band, median ρ); 9-D total
RMSE likewise. ``--results`` writes the tables as the Cross-validation section of
docs/results.md (or FILE).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

import mavest
from mavest import EstimatorConfig
from mavest.datasets.broad import BroadTrial, halves, list_trials, load_trial
from mavest.evaluation import report
from mavest.evaluation.calibration import score_attitude
from mavest.evaluation.metrics import rmse_deg
from mavest.evaluation.peers import PEERS

#: (gyro_noise_density, gyro_scale_noise_density, velocity_adapt_time). The white rate
#: noise stays at 0.005 rad/s/√Hz, five times a MEMS gyro's: it is also how fast a
#: confidently wrong attitude becomes uncertain enough to be corrected, and at 0.002 a
#: tilt 30° off with σ 0.06° is still 25° off after a minute at rest
#: (tests/test_health.py asks for it within the minute).
#: The level is averaged over 1 or 3 s: over 10 s it lags a drop in the motion, and the
#: Monte Carlo whose level falls from 3 to 0.5 m/s ends conservative (last 10 s' ANEES
#: 4.3 of 6 over 30 runs, against 5.5 with 1 s; tools/consistency.py, changing_motion).
GRID_6D: tuple[tuple[float, float, float], ...] = tuple(
    itertools.product((0.005,), (0.0, 0.0007, 0.0015, 0.003, 0.006), (0.0, 1.0, 3.0))
)
GRID_MAG: tuple[float, ...] = (0.02, 0.04, 0.08, 0.16)
ACCURACY_SLACK = 0.03  # a combination this much less accurate than the best still competes
CALIBRATED = (0.6, 1.6)
#: mavest's defaults before the velocity's level was measured and the rate noise split
PREVIOUS = EstimatorConfig(
    gyro_noise_density=0.005,
    gyro_scale_noise_density=0.0,
    velocity_adapt_time=0.0,
    mag_heading_noise_density=0.08,
)
QUICK_GRID_6D = ((0.005, 0.0, 0.0), (0.002, 0.0015, 10.0))
QUICK_TRIALS = 4


@dataclass(frozen=True)
class TrialScore:
    inclination: float  # RMSE °, 6-D
    ratio: float  # tilt calibration ratio, 6-D
    rho: float  # σ–error rank correlation over 1 s windows, 6-D


def config_6d(values: tuple[float, float, float]) -> EstimatorConfig:
    gyro, scale, adapt = values
    return EstimatorConfig(
        gyro_noise_density=gyro, gyro_scale_noise_density=scale, velocity_adapt_time=adapt
    )


def score_6d(trial: BroadTrial, config: EstimatorConfig) -> TrialScore:
    series = mavest.estimate(trial.t, trial.gyro, trial.accel, None, config)
    tilt, _, _ = score_attitude(
        trial.t, series.q, series.cov, trial.truth_q, trial.movement, config.error
    )
    inclination = rmse_deg(series.q, trial.truth_q, trial.movement)["inclination"]
    return TrialScore(inclination, tilt.ratio, tilt.rank_correlation)


def total_9d(trial: BroadTrial, config: EstimatorConfig) -> float:
    series = mavest.estimate(trial.t, trial.gyro, trial.accel, trial.mag, config)
    return rmse_deg(series.q, trial.truth_q, trial.movement)["total"]


def _calibrated(scores: Sequence[TrialScore]) -> int:
    lo, hi = CALIBRATED
    return sum(lo <= s.ratio <= hi for s in scores)


def _median_rho(scores: Sequence[TrialScore]) -> float:
    finite = [s.rho for s in scores if np.isfinite(s.rho)]
    return statistics.median(finite) if finite else float("nan")


def choose_6d(
    table: dict[tuple[float, float, float], list[TrialScore]], subset: Sequence[int]
) -> tuple[float, float, float]:
    """The rule: accuracy within the slack of the best, then calibration, then ρ."""
    mean = {k: float(np.mean([v[i].inclination for i in subset])) for k, v in table.items()}
    best = min(mean.values())
    competing = [k for k in table if mean[k] <= best * (1.0 + ACCURACY_SLACK)]

    def merit(k: tuple[float, float, float]) -> tuple[int, float, float]:
        picked = [table[k][i] for i in subset]
        return (_calibrated(picked), _median_rho(picked), -mean[k])

    return max(competing, key=merit)


def choose_mag(table: dict[float, list[float]], subset: Sequence[int]) -> float:
    return min(table, key=lambda k: float(np.mean([table[k][i] for i in subset])))


@dataclass(frozen=True)
class Direction:
    tuned_on: str
    held_out: str
    subset: list[int]  # the held-out trials
    choice_6d: tuple[float, float, float]
    choice_mag: float


def held_out_table(
    trials: Sequence[BroadTrial],
    directions: Sequence[Direction],
    table_6d: dict[tuple[float, float, float], list[TrialScore]],
    table_mag: dict[tuple[tuple[float, float, float], float], list[float]],
    previous: list[TrialScore],
    previous_9d: list[float],
    vqf: list[float],
    vqf_9d: list[float],
) -> str:
    lines = [
        "| tuned on → reported on | chosen | 6-D inclination RMSE: mavest / previous / VQF "
        "| mavest − VQF, paired | tilt σ calibrated (ratio in [0.6, 1.6]) | median ρ "
        "| 9-D total RMSE: mavest / previous / VQF | 9-D mavest − VQF, paired |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for d in directions:
        ours = [table_6d[d.choice_6d][i] for i in d.subset]
        before = [previous[i] for i in d.subset]
        incl = np.array([s.inclination for s in ours])
        incl_vqf = np.array([vqf[i] for i in d.subset])
        total = np.array([table_mag[(d.choice_6d, d.choice_mag)][i] for i in d.subset])
        total_vqf = np.array([vqf_9d[i] for i in d.subset])
        gyro, scale, adapt = d.choice_6d
        chosen = f"gyro {gyro:g}, scale {scale:g}, adapt {adapt:g} s, mag {d.choice_mag:g}"
        lines.append(
            f"| {d.tuned_on} → {d.held_out} | {chosen} "
            f"| {incl.mean():.3f}° / {np.mean([s.inclination for s in before]):.3f}° / "
            f"{incl_vqf.mean():.3f}° ({incl.mean() / incl_vqf.mean():.2f}×) "
            f"| {report.paired(incl, incl_vqf)} "
            f"| {_calibrated(ours)} of {len(ours)} (previous {_calibrated(before)}) "
            f"| {_median_rho(ours):+.2f} (previous {_median_rho(before):+.2f}) "
            f"| {total.mean():.3f}° / {np.mean([previous_9d[i] for i in d.subset]):.3f}° / "
            f"{total_vqf.mean():.3f}° ({total.mean() / total_vqf.mean():.2f}×) "
            f"| {report.paired(total, total_vqf)} |"
        )
    return "\n".join(lines)


def per_trial_table(
    trials: Sequence[BroadTrial],
    directions: Sequence[Direction],
    table_6d: dict[tuple[float, float, float], list[TrialScore]],
    vqf: list[float],
) -> str:
    lines = [
        "| trial | held out in | inclination: mavest / VQF | tilt ratio | ρ |",
        "|---|---|---|---|---|",
    ]
    for d in directions:
        for i in d.subset:
            s = table_6d[d.choice_6d][i]
            lines.append(
                f"| {trials[i].name} | {d.held_out} | {s.inclination:.3f}° / {vqf[i]:.3f}° "
                f"| {s.ratio:.2f} | {s.rho:+.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="two combinations, four trials")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    paths = list_trials()
    if args.quick:
        paths = paths[:QUICK_TRIALS]
    trials = [load_trial(p) for p in paths]
    grid = QUICK_GRID_6D if args.quick else GRID_6D
    vqf = [rmse_deg(_peer(t, False), t.truth_q, t.movement)["inclination"] for t in trials]
    vqf_9d = [rmse_deg(_peer(t, True), t.truth_q, t.movement)["total"] for t in trials]
    previous = [score_6d(t, PREVIOUS) for t in trials]
    previous_9d = [total_9d(t, PREVIOUS) for t in trials]
    table_6d = {}
    for values in grid:
        table_6d[values] = [score_6d(t, config_6d(values)) for t in trials]
        print(
            f"6-D {values}: {np.mean([s.inclination for s in table_6d[values]]):.3f}°",
            file=sys.stderr,
            flush=True,
        )
    a, b = halves(trials)
    everything = list(range(len(trials)))
    choices = {name: choose_6d(table_6d, subset) for name, subset in (("A", a), ("B", b))}
    choices["all"] = choose_6d(table_6d, everything)
    table_mag: dict[tuple[tuple[float, float, float], float], list[float]] = {}
    for values in set(choices.values()):
        for density in GRID_MAG:
            config = dataclasses.replace(config_6d(values), mag_heading_noise_density=density)
            table_mag[(values, density)] = [total_9d(t, config) for t in trials]

    def mag_for(values: tuple[float, float, float], subset: Sequence[int]) -> float:
        per = {k[1]: v for k, v in table_mag.items() if k[0] == values}
        return choose_mag(per, subset)

    directions = [
        Direction("A", "B", b, choices["A"], mag_for(choices["A"], a)),
        Direction("B", "A", a, choices["B"], mag_for(choices["B"], b)),
    ]
    overall = (choices["all"], mag_for(choices["all"], everything))
    body = "\n\n".join(
        [
            f"Halves of the {len(trials)} shared BROAD trials: A = "
            + ", ".join(trials[i].name[:2] for i in a)
            + "; B = "
            + ", ".join(trials[i].name[:2] for i in b)
            + ". Every figure below is on the half the parameters were **not** chosen on.",
            held_out_table(
                trials, directions, table_6d, table_mag, previous, previous_9d, vqf, vqf_9d
            ),
            per_trial_table(trials, directions, table_6d, vqf),
            "The rule applied to all 22 trials (what configs/adaptive.toml sets; the "
            "defaults keep the velocity's level fixed): gyro_noise_density "
            f"{overall[0][0]:g}, gyro_scale_noise_density {overall[0][1]:g}, "
            f"velocity_adapt_time {overall[0][2]:g} s, mag_heading_noise_density "
            f"{overall[1]:g}. (In the A → B and B → A rows the halves chose "
            + "; ".join(
                f"{d.tuned_on}: {d.choice_6d[0]:g}/{d.choice_6d[1]:g}/{d.choice_6d[2]:g}/"
                f"{d.choice_mag:g}"
                for d in directions
            )
            + ".)",
        ]
    )
    print(body)
    print(f"\n({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    if args.results is not None:
        report.write_section(
            args.results,
            "Cross-validation",
            body,
            "tools/tune.py" + (" --quick" if args.quick else ""),
        )
    return 0


def _peer(trial: BroadTrial, mag: bool) -> np.ndarray:
    return PEERS["VQF"](trial.t, trial.gyro, trial.accel, trial.mag if mag else None, trial.rate)


if __name__ == "__main__":
    sys.exit(main())
