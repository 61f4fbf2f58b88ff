"""What the IMU cannot see: the low-pass's actual error against the velocity model's.

    .venv/bin/python tools/motion_prior.py [--trials 02 10 ...] [--results [FILE]]

The tilt's σ is set by the linear acceleration at the low frequencies the filter's
accelerometer low-pass lets through, where the accelerometer cannot tell it from
gravity; the velocity model (Gauss–Markov, correlation time ``velocity_time``)
extrapolates it from the faster motion the data do show. This tool checks that
extrapolation against BROAD's optical truth. Per trial, over its movement phases,
with the truth turning the specific force into the world frame (NED):

* σ_v: the velocity's level as mavest measures it (docs/design.md, "Motion level from
  the data"): the horizontal specific force's departure from its low-pass,
  integrated with a 1 s leak; its mean square, times the share a Gauss–Markov
  velocity of 1 s keeps through that, per axis;
* r: the same integrated with a 0.2 s leak, its variance over the 1 s one's; for a
  Gauss–Markov velocity r depends on its correlation time alone, and the time it
  gives is printed beside (">" at the grid's end);
* the low-pass's actual error, per horizontal axis, as tilt: the world-frame linear
  acceleration (specific force plus gravity, its mean over the trial removed, which
  is a sensor bias or the frames' misalignment, printed apart) through the low-pass,
  over g;
* the error the Gauss–Markov velocity predicts at that σ_v, with a 1 s and a 0.1 s
  correlation time.

The low-pass is mavest's (second order, ω = √2/τ, ζ = 1/√2, τ = the default
``accel_lowpass_time``), here discretised by scipy (bilinear), and the predictions
are its frequency response integrated against the model's spectrum. ``--results``
writes the table as the Motion prior section of docs/results.md (or FILE). A file that
is not a readable trial, a second copy of a recording, or a trial with nothing to score
(no movement sample with known truth) is left out with one line; exits 2, with one
line, when BROAD or h5py is missing or no trial is left.
"""

from __future__ import annotations

import functools
import importlib
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation

from mavest import EstimatorConfig
from mavest.datasets import DATA_ENV_VAR
from mavest.datasets.broad import BroadTrial, list_trials, load_trials
from mavest.evaluation import report

G = 9.80665
LONG, SHORT = 1.0, 0.2  # s: the two leaks the fast velocity is integrated with
MODEL_TIMES = (1.0, 0.1)  # s: correlation times whose predictions are printed
# (rad/s) where the spectra are integrated: far past every corner here
_W = np.linspace(1e-4, 400.0, 400_001)


def lowpass_response(w: np.ndarray, tau: float) -> np.ndarray:
    """mavest's second-order low-pass at angular frequencies ``w``."""
    omega = math.sqrt(2.0) / tau
    s = 1j * w
    return omega**2 / (s**2 + math.sqrt(2.0) * omega * s + omega**2)


def gauss_markov_velocity(w: np.ndarray, time: float) -> np.ndarray:
    """One-sided spectrum of a unit-variance Gauss–Markov velocity, per rad/s."""
    return 2.0 * time / (1.0 + (w * time) ** 2) / math.pi


def fast_share(time: float, leak: float, tau: float) -> float:
    """The share of a Gauss–Markov velocity's variance that its acceleration's departure
    from the low-pass, integrated with ``leak``, keeps."""
    s = 1j * _W
    gain = np.abs(s * (1.0 - lowpass_response(_W, tau)) / (s + 1.0 / leak)) ** 2
    return float(np.trapezoid(gain * gauss_markov_velocity(_W, time), _W))


def predicted_error(sigma_v: float, time: float, tau: float) -> float:
    """RMS of the low-passed acceleration per axis (m/s²) of that velocity."""
    gain = np.abs(1j * _W * lowpass_response(_W, tau)) ** 2
    return sigma_v * math.sqrt(float(np.trapezoid(gain * gauss_markov_velocity(_W, time), _W)))


def ratio_to_time(ratio: float, tau: float) -> str:
    """The Gauss–Markov correlation time whose SHORT/LONG variance ratio is ``ratio``."""
    times = np.geomspace(0.01, 10.0, 61)
    ratios = np.array([fast_share(t, SHORT, tau) / fast_share(t, LONG, tau) for t in times])
    # (the ratio falls as the time grows)
    if ratio >= ratios[0]:
        return f"< {times[0]:g}"
    if ratio <= ratios[-1]:
        return f"> {times[-1]:g}"
    return f"{np.exp(np.interp(ratio, ratios[::-1], np.log(times[::-1]))):.2f}"


@dataclass(frozen=True)
class TrialPrior:
    name: str
    sigma_v: float  # m/s
    ratio: float  # SHORT over LONG
    actual: float  # rad of tilt per axis
    predicted: tuple[float, ...]  # rad, per MODEL_TIMES
    offset: float  # rad, the constant part removed


def measure(trial: BroadTrial, tau: float) -> TrialPrior:
    known = np.isfinite(trial.truth_q).all(axis=1)
    known &= np.linalg.norm(np.nan_to_num(trial.truth_q), axis=1) > 0.5
    # truth gaps: the last known attitude held (they are not scored)
    held = np.maximum.accumulate(np.where(known, np.arange(known.shape[0]), 0))
    q = np.where(known[held, None], trial.truth_q[held], [1.0, 0.0, 0.0, 0.0])
    world = Rotation.from_quat(q, scalar_first=True).apply(trial.accel)
    linear = world + np.array([0.0, 0.0, G])
    scored = trial.movement & known
    dt = float(np.median(np.diff(trial.t)))
    b, a = signal.bilinear([2.0 / tau**2], [1.0, 2.0 / tau, 2.0 / tau**2], fs=1.0 / dt)
    departure = (linear - signal.lfilter(b, a, linear, axis=0))[:, :2]
    fast = []
    for leak in (LONG, SHORT):
        velocity = signal.lfilter([dt], [1.0, -math.exp(-dt / leak)], departure, axis=0)
        fast.append(float(np.mean(velocity[scored] ** 2)))
    sigma_v = math.sqrt(fast[0] / fast_share(LONG, LONG, tau))
    mean = linear[scored].mean(axis=0)
    lowpassed = signal.lfilter(b, a, linear - mean, axis=0)[scored][:, :2]
    actual = math.sqrt(float(np.mean(lowpassed**2))) / G
    predicted = tuple(predicted_error(sigma_v, time, tau) / G for time in MODEL_TIMES)
    return TrialPrior(
        trial.name, sigma_v, fast[1] / fast[0], actual, predicted, math.hypot(*mean[:2]) / G
    )


def table(priors: Sequence[TrialPrior], tau: float) -> str:
    predicted = " | ".join(f"predicted, {t:g} s" for t in MODEL_TIMES)
    lines = [
        f"| trial | σ_v m/s | r ({SHORT:g} s / {LONG:g} s) | its correlation time s "
        f"| low-pass error °/axis | {predicted} | constant part ° |",
        "|---|---:|---:|---:|---:|" + "---:|" * len(MODEL_TIMES) + "---:|",
    ]
    for p in priors:
        cells = " | ".join(f"{math.degrees(x):.3f}" for x in p.predicted)
        lines.append(
            f"| {p.name} | {p.sigma_v:.2f} | {p.ratio:.3f} | {ratio_to_time(p.ratio, tau)} "
            f"| {math.degrees(p.actual):.3f} | {cells} | {math.degrees(p.offset):.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = report.tool_parser(__doc__)
    parser.add_argument(
        "--trials", nargs="+", metavar="PREFIX", help="only these BROAD trials (name prefixes)"
    )
    report.add_results_option(parser)
    args = parser.parse_args(argv)
    try:
        importlib.import_module("h5py")
        paths = list_trials(prefixes=args.trials)
    except ImportError:
        print("motion_prior: the package h5py (dev extra) is needed to read BROAD", file=sys.stderr)
        return 2
    except FileNotFoundError as error:
        report.progress("motion_prior", str(error))
        return 2
    if not paths:
        report.progress("motion_prior", f"no BROAD trial in {DATA_ENV_VAR}'s broad/")
        return 2
    tau = EstimatorConfig().accel_lowpass_time

    say = functools.partial(report.progress, "motion_prior")

    priors = [measure(trial, tau) for trial in load_trials(paths, say, scored_only=True)]
    if not priors:
        say("no BROAD trial with something to score is left")
        return 2
    shares = ", ".join(
        f"{t:g} s: {fast_share(t, SHORT, tau) / fast_share(t, LONG, tau):.2f}"
        for t in (0.1, 0.3, 1.0, 3.0)
    )
    with report.results_section(args.results, "Motion prior", __file__, argv, __doc__):
        print(
            f"BROAD trials over their movement phases; low-pass τ {tau:g} s. r of a "
            f"Gauss–Markov velocity by its correlation time: {shares}.\n"
        )
        print(table(priors, tau))
    return 0


if __name__ == "__main__":
    sys.exit(main())
