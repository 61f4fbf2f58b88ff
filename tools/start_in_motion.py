"""The filter started while the vehicle moves: how far its alignment lands, how long to recover.

    .venv/bin/python tools/start_in_motion.py [--scenario NAME ...] [--seeds 0 1 2 3]
                                              [--starts 0 10 20 30 40 50] [--results [FILE]]

On the flights of the Monte Carlo's scenarios (mavest.evaluation.consistency; one per
distinct flight, ``distinct_flights``) it runs ``mavest.estimate``
from each ``--starts`` time on, as a service started while the vehicle flies (or a
log begun then), and scores its tilt against the truth: the error at its first
estimate and the σ per axis it claims there (the filter aligns on one accelerometer
sample), whether that error is over :data:`OFF` (a bad start), and the time until the
error first comes under :data:`RECOVERED` ("never": not before the flight ends).
The scenarios' velocity model makes the linear acceleration tens of m/s² from one
sample to the next, far whiter than a real vehicle's: the figures say what a start
in such motion costs, not how often real starts are bad. --results writes the tables
as the Start in motion section of docs/results.md (or FILE).
"""

from __future__ import annotations

import math
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavest import EstimatorConfig, StepFlags, estimate
from mavest.evaluation import report
from mavest.evaluation.consistency import (
    SCENARIOS,
    Scenario,
    distinct_flights,
    simulate_scenario,
)
from mavest.evaluation.metrics import attitude_errors

OFF = math.radians(15.0)  # a first estimate this far off in tilt is a bad start
RECOVERED = math.radians(5.0)  # tilt error under which a start has recovered


@dataclass(frozen=True)
class Start:
    scenario: str
    seed: int
    start: float  # s into the flight
    error: float  # rad, tilt error at the first estimate
    sigma: float  # rad per axis, claimed there
    recovery: float  # s from the first estimate until the error first comes under RECOVERED


def starts_of(scenario: Scenario, seed: int, starts: Sequence[float]) -> list[Start]:
    """The default filter started at each of ``starts`` (s) on this scenario's flight;
    starts past the flight's end, or that never estimate, are left out."""
    config = EstimatorConfig()
    flight = simulate_scenario(scenario, config, seed)
    out = []
    for start in starts:
        k = int(np.searchsorted(flight.t - flight.t[0], start))
        if k >= flight.t.shape[0] - 1:
            continue
        mag = flight.mag[k:] if scenario.magnetometer else None
        series = estimate(flight.t[k:], flight.gyro[k:], flight.accel[k:], mag, config)
        estimated = np.flatnonzero((series.flags & StepFlags.NOT_INITIALISED) == 0)
        if not estimated.shape[0]:
            continue
        first = int(estimated[0])
        tilt = attitude_errors(series.q, flight.q_true[k:]).inclination
        under = np.flatnonzero(tilt[first:] < RECOVERED)
        t = series.t
        recovery = float(t[first + under[0]] - t[first]) if under.shape[0] else math.inf
        sigma = math.sqrt(0.5 * (series.cov[first, 0, 0] + series.cov[first, 1, 1]))
        out.append(Start(scenario.name, seed, start, float(tilt[first]), sigma, recovery))
    return out


def _deg(value: float) -> str:
    return f"{math.degrees(value):.1f}°"


def _seconds(value: float) -> str:
    return "never" if math.isinf(value) else f"{value:.1f} s"


def summary_table(results: list[Start]) -> str:
    rows = [
        "| scenario | starts | over 15° off | first error, median / max | σ claimed | "
        "time to under 5°, median / max (bad starts) | never (bad starts) |",
        "|---|---|---|---|---|---|---|",
    ]
    groups = [(name, [r for r in results if r.scenario == name]) for name in _names(results)]
    for name, group in [*groups, ("all", results)]:
        bad = [r for r in group if r.error > OFF]
        finite = [r.recovery for r in bad if not math.isinf(r.recovery)]
        recovery = (
            f"{_seconds(statistics.median(finite))} / {_seconds(max(finite))}" if finite else "—"
        )
        never = sum(math.isinf(r.recovery) for r in bad)
        errors = [r.error for r in group]
        sigma = statistics.median(r.sigma for r in group)
        rows.append(
            f"| {name} | {len(group)} | {len(bad)} | "
            f"{_deg(statistics.median(errors))} / {_deg(max(errors))} | {_deg(sigma)} | "
            f"{recovery} | {never} |"
        )
    return "\n".join(rows)


def detail_table(results: list[Start]) -> str:
    rows = [
        "| scenario | seed | start | first tilt error | σ claimed | time to under 5° |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        rows.append(
            f"| {r.scenario} | {r.seed} | {r.start:g} s | {_deg(r.error)} | {_deg(r.sigma)} | "
            f"{_seconds(r.recovery)} |"
        )
    return "\n".join(rows)


def _names(results: list[Start]) -> list[str]:
    return list(dict.fromkeys(r.scenario for r in results))


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument("--scenario", action="append", choices=[s.name for s in SCENARIOS])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument(
        "--starts", type=float, nargs="+", default=[0.0, 10.0, 20.0, 30.0, 40.0, 50.0]
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    results = [
        start
        for scenario in distinct_flights(args.scenario)
        for seed in args.seeds
        for start in starts_of(scenario, seed, args.starts)
    ]
    if not results:
        print("start_in_motion: no start inside the flights", file=sys.stderr)
        return 2
    with report.results_section(args.results, "Start in motion", __file__, argv, __doc__):
        print(
            f"mavest.estimate started {', '.join(f'{s:g}' for s in args.starts)} s into the "
            f"Monte Carlo's flights (seeds {', '.join(map(str, args.seeds))}); tilt error "
            "against the truth\n"
        )
        print(summary_table(results))
        print()
        print(detail_table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
