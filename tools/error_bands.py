"""Where each filter's tilt error lies in frequency, on BROAD.

    .venv/bin/python tools/error_bands.py [--delay MS] [--quick] [--results [FILE]]

Each filter (mavest's filter and smoother with the defaults, VQF and offline VQF; 6-D)
is run once per trial. Its tilt error against the optical truth (the two horizontal
components of the world-frame error, :func:`mavest.evaluation.calibration.tilt_heading_errors`)
is split into frequency bands by zero-phase Butterworth filters of order 4
(:func:`scipy.signal.sosfiltfilt`) over the whole trial, the samples without a truth
bridged by linear interpolation; each band's RMS is taken over the scored movement
samples, as the inclination RMSE is, and averaged over the trials. The bands overlap
at their edges, so their squares do not quite add up to the whole's.

Slow bands hold what a filter's references leave (bias, the level it holds at rest);
the middle ones what linear acceleration pulls it by; the fast ones what the gyro and
the timing give it. A filter behind another in one band only is behind it for one
cause. The attitudes are carried forward by 0 and by ``--delay`` (default 2.5 ms,
where every filter's error is least over all the trials: docs/results.md#imu-delay),
as ``tools/imu_delay.py`` carries them; with the lag the data's own taken out, the
bands show what each filter estimates. Then, per band, mavest against the peer of its
kind, paired per trial. No parameter is chosen here; the delay was chosen on these
trials, so the figures describe them, they are not held-out results.

Any folder of BROAD-format trials will do (``MAVEST_DATA``): a file that is not a
readable trial, a second copy of a recording, or a trial with nothing to score is left
out with one line; fewer than two trials left, or no BROAD folder, is one line and
exit 2. ``--results`` writes the tables as the Error bands section of docs/results.md
(or FILE).
"""

from __future__ import annotations

import functools
import itertools
import math
import statistics
import sys
import time
from collections.abc import Sequence

import numpy as np
from scipy import signal

from mavest.datasets.broad import BroadTrial, trials_to_split
from mavest.evaluation import report
from mavest.evaluation.accuracy import carried_runs
from mavest.evaluation.calibration import tilt_heading_errors

TITLE = "Error bands"
#: Band edges (Hz); the last band is everything above its lower edge.
EDGES: tuple[float, ...] = (0.0, 0.03, 0.1, 0.3, 1.0, math.inf)
ORDER = 4
DELAY = 2.5  # ms
QUICK_TRIALS = 4
PAIRS = (("mavest", "VQF"), ("mavest.smooth", "offline VQF"))


def band_label(lo: float, hi: float) -> str:
    if lo == 0.0:
        return f"< {hi:g} Hz"
    if math.isinf(hi):
        return f"> {lo:g} Hz"
    return f"{lo:g}–{hi:g} Hz"


BANDS = tuple(band_label(lo, hi) for lo, hi in itertools.pairwise(EDGES))


def band_rms(
    error: np.ndarray, scored: np.ndarray, rate: float, truth: np.ndarray | None = None
) -> list[float]:
    """The RMS (in the units of ``error``) over the ``scored`` samples of the error (N,
    k), whole and in each band of :data:`EDGES` (the whole last). The rows without a
    truth (``truth`` False; by default the rows whose error is not finite) are bridged by
    linear interpolation before filtering and never scored; an error that is not finite
    where there is a truth (a filter's failed estimate) makes every figure NaN, as
    :func:`mavest.evaluation.metrics.rmse_deg` does."""
    error = np.asarray(error, dtype=np.float64).reshape(error.shape[0], -1)
    known = np.all(np.isfinite(error), axis=1)
    nothing = [math.nan] * (len(BANDS) + 1)
    if truth is not None and np.any(truth & ~known):
        return nothing
    scored = scored & known
    if not scored.any():
        return nothing
    index = np.arange(error.shape[0])
    bridged = np.column_stack([np.interp(index, index[known], column[known]) for column in error.T])
    out = []
    for lo, hi in itertools.pairwise(EDGES):
        if lo == 0.0:
            sos = signal.butter(ORDER, hi, "lowpass", fs=rate, output="sos")
        elif math.isinf(hi):
            sos = signal.butter(ORDER, lo, "highpass", fs=rate, output="sos")
        else:
            sos = signal.butter(ORDER, [lo, hi], "bandpass", fs=rate, output="sos")
        part = signal.sosfiltfilt(sos, bridged, axis=0)
        out.append(math.sqrt(float(np.mean(np.sum(part[scored] ** 2, axis=1)))))
    out.append(math.sqrt(float(np.mean(np.sum(bridged[scored] ** 2, axis=1)))))
    return out


def score(
    trials: Sequence[BroadTrial], delays: Sequence[float]
) -> dict[float, dict[str, list[list[float]]]]:
    """Per delay (s), per filter, per trial: the tilt error's RMS (°) per band and whole."""
    table: dict[float, dict[str, list[list[float]]]] = {d: {} for d in delays}
    for trial in trials:
        truth = np.all(np.isfinite(trial.truth_q), axis=1)
        for name, carried in carried_runs(trial).items():
            for delay in delays:
                tilt = tilt_heading_errors(carried(delay), trial.truth_q).tilt
                rms = band_rms(np.degrees(tilt), trial.movement, trial.rate, truth)
                table[delay].setdefault(name, []).append(rms)
        report.progress("error_bands", trial.name)
    return table


def bands_table(per_filter: dict[str, list[list[float]]]) -> str:
    lines = [
        "| filter | " + " | ".join(BANDS) + " | whole |",
        "|---" * (len(BANDS) + 2) + "|",
    ]
    for name, rows in per_filter.items():
        means = np.nanmean(np.array(rows), axis=0)
        lines.append(f"| {name} | " + " | ".join(f"{m:.3f}°" for m in means) + " |")
    return "\n".join(lines)


def paired_table(per_filter: dict[str, list[list[float]]]) -> str:
    lines = ["| band | " + " | ".join(f"{ours} − {peer}" for ours, peer in PAIRS) + " |"]
    lines.append("|---" * (len(PAIRS) + 1) + "|")
    for k, band in enumerate([*BANDS, "whole"]):
        cells = []
        for ours, peer in PAIRS:
            pairs = [
                (a[k], b[k])
                for a, b in zip(per_filter[ours], per_filter[peer], strict=True)
                if math.isfinite(a[k]) and math.isfinite(b[k])
            ]
            mine, theirs = [a for a, _ in pairs], [b for _, b in pairs]
            cells.append(
                f"{statistics.fmean(mine) / statistics.fmean(theirs):.2f}×, "
                + report.paired(mine, theirs)
            )
        lines.append(f"| {band} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument(
        "--delay", type=float, default=DELAY, help="ms the attitudes are carried forward by"
    )
    parser.add_argument("--quick", action="store_true", help="four trials")
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    if not (math.isfinite(args.delay) and 0.0 <= args.delay <= 100.0):
        parser.error(f"--delay must be 0–100 ms, got {args.delay}")
    start = time.perf_counter()

    say = functools.partial(report.progress, "error_bands")

    trials = trials_to_split(say, QUICK_TRIALS if args.quick else None)
    if trials is None:
        return 2
    delays = sorted({0.0, args.delay * 1e-3})
    table = score(trials, delays)
    with report.results_section(args.results, TITLE, __file__, argv, __doc__):
        for delay in delays:
            carried = "as recorded" if delay == 0.0 else f"carried forward by {delay * 1e3:g} ms"
            print(
                f"Mean over the {len(trials)} BROAD trials of the 6-D tilt error's RMS per "
                f"band, the attitudes {carried} (defaults).\n"
            )
            print(bands_table(table[delay]) + "\n")
        last = delays[-1]
        print(
            f"Per band, carried forward by {last * 1e3:g} ms: mavest's mean over the peer's, "
            "and the paired per-trial differences (lower is better).\n"
        )
        print(paired_table(table[last]))
    print(f"({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
