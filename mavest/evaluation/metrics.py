"""Attitude error metrics: the BROAD dataset's scoring, reimplemented.

BROAD (Laidig et al. 2021, example code ``broad_utils.py``) scores an estimate by the
error quaternion expressed in the *world* frame,

    q_err = q_est ⊗ q_true⁻¹        (normalised),

which is the rotation that carries the true attitude onto the estimated one, applied
on the world side. With q_err = (w, x, y, z):

* total error        2·acos(|w|)                  — the angle of q_err;
* heading error      2·atan(|z / w|)              — its twist about the world vertical;
* inclination error  2·acos(√(w² + z²))           — the remaining swing about a
  horizontal world axis.

These are an exact swing–twist split: q_err = q_twist ⊗ q_swing with q_twist about
world z and q_swing about a horizontal axis. The world z axis is vertical in both ENU
(the dataset) and NED (mavest), so the formulas hold unchanged for FRD → NED
quaternions. The score of a trial is the RMSE over the ``movement`` samples whose truth
is finite (:func:`scored_rows`; lost optical tracking is skipped). An estimate must
cover every one of those rows: one it left non-finite makes the score NaN
(:func:`rmse_deg`, :func:`missing_rows`), since skipping it would reward a filter for
giving up where it is worst.

A 6-D filter (no magnetometer) has no heading reference: compare its inclination only,
or first apply :func:`remove_heading_offset`.

Quaternions are (w, x, y, z), Hamilton, body → world, float64, shape (N, 4) or (4,).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

__all__ = [
    "AttitudeErrors",
    "attitude_errors",
    "error_quaternion",
    "heading_offset",
    "missing_rows",
    "quat_conjugate",
    "quat_multiply",
    "remove_heading_offset",
    "rmse_deg",
    "scored_rows",
    "signed_heading_error",
    "trial_parity",
]


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Row-wise Hamilton product p ⊗ q of (w, x, y, z) quaternions; broadcasts (4,) rows.

    Vectorised over arrays (the numba kernels in ``mavest.so3`` work on one quaternion at
    a time); NaN rows propagate as NaN.
    """
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse, for unit quaternions) of (w, x, y, z) quaternions."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _normalized(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def error_quaternion(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """World-frame error q_est ⊗ q_true⁻¹, both inputs normalised first, result normalised."""
    err = quat_multiply(_normalized(q_est), quat_conjugate(_normalized(q_true)))
    return _normalized(err)


@dataclass(frozen=True)
class AttitudeErrors:
    """Per-sample attitude errors in radians, each in [0, π]; NaN where truth is NaN."""

    total: np.ndarray
    heading: np.ndarray
    inclination: np.ndarray


def attitude_errors(q_est: np.ndarray, q_true: np.ndarray) -> AttitudeErrors:
    """Total, heading and inclination error of ``q_est`` against ``q_true`` (rad).

    The dataset writes the heading as 2·atan(|z/w|); 2·atan2(|z|, |w|) is the same value
    and stays defined (π) when w = 0. Total and inclination, 2·acos(|w|) and
    2·acos(√(w² + z²)) in the dataset, are written as the equal atan2 forms: acos
    loses half the digits near zero (a 1e-7 rad error came out 1.5 % wrong).
    """
    e = error_quaternion(q_est, q_true)
    w = np.abs(e[..., 0])
    x, y, z = e[..., 1], e[..., 2], np.abs(e[..., 3])
    total = 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), w)
    heading = 2.0 * np.arctan2(z, w)
    inclination = 2.0 * np.arctan2(np.sqrt(x * x + y * y), np.sqrt(w * w + z * z))
    return AttitudeErrors(total=total, heading=heading, inclination=inclination)


def _boolean(mask: np.ndarray) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.dtype != bool:
        raise TypeError("mask must be a boolean array (e.g. BroadTrial.movement)")
    return mask


def _select(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    return values if mask is None else values[_boolean(mask)]


def _rms(values: np.ndarray) -> float:
    """sqrt(mean(values²)) of the finite values; NaN (not a warning) when none is left."""
    finite = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(finite * finite))) if finite.size else float("nan")


def _valid(q: np.ndarray) -> np.ndarray:
    """(N,) bool: the rows of ``q`` that are a rotation (finite, not all zero)."""
    q = np.asarray(q, dtype=np.float64)
    return np.all(np.isfinite(q), axis=-1) & np.any(q != 0.0, axis=-1)


def scored_rows(q_true: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the rows a score counts, those inside ``mask`` (every row when None;
    BROAD: ``movement``) whose truth is a rotation (not NaN: tracking was not lost).

    A recording with none of them has nothing to score.
    """
    rows = _valid(q_true)
    return rows if mask is None else rows & _boolean(mask)


def missing_rows(q_est: np.ndarray, q_true: np.ndarray, mask: np.ndarray | None = None) -> int:
    """How many of the :func:`scored_rows` the estimate leaves without a rotation
    (non-finite or zero): each makes :func:`rmse_deg` NaN."""
    return int(np.count_nonzero(scored_rows(q_true, mask) & ~_valid(q_est)))


def rmse_deg(
    q_est: np.ndarray, q_true: np.ndarray, mask: np.ndarray | None = None
) -> dict[str, float]:
    """RMSE in degrees of the total, heading and inclination errors, as BROAD scores them.

    The rows counted are :func:`scored_rows`: inside ``mask`` (BROAD: ``movement``) with
    a finite truth; rows whose truth is NaN are skipped. The estimate is not given that
    grace: if it is non-finite on any counted row (:func:`missing_rows` says how many),
    every figure is NaN, as it is when no row is counted. Returns ``{"total": …,
    "heading": …, "inclination": …}``.
    """
    rows = scored_rows(q_true, mask)
    if not rows.any() or np.any(rows & ~_valid(q_est)):
        return dict.fromkeys(("total", "heading", "inclination"), float("nan"))
    errors = attitude_errors(np.asarray(q_est)[rows], np.asarray(q_true)[rows])
    return {
        "total": float(np.degrees(_rms(errors.total))),
        "heading": float(np.degrees(_rms(errors.heading))),
        "inclination": float(np.degrees(_rms(errors.inclination))),
    }


def trial_parity(name: str) -> int | None:
    """0 or 1, the parity of a BROAD trial's number (the digits its name starts with:
    ``"07_undisturbed_fast_rotation_B"`` → 1); None for a name that starts with none."""
    number = re.match(r"\d+", name)
    return int(number.group()) % 2 if number else None


def signed_heading_error(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """Signed twist angle (rad, in (−π, π]) of the world-frame error about world z.

    Its absolute value is the BROAD heading error.
    """
    e = error_quaternion(q_est, q_true)
    sign = np.where(e[..., 0] < 0.0, -1.0, 1.0)  # q and −q are the same rotation
    return 2.0 * np.arctan2(sign * e[..., 3], np.abs(e[..., 0]))


def wrap_angles(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [−π, π)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def heading_offset(q_est: np.ndarray, q_true: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The constant turn δ about world z (rad) that minimises the heading RMSE of q_z(δ) ⊗ q_est.

    Left-multiplying by a world-vertical rotation changes only the twist of the error
    (q_z(δ) ⊗ q_twist ⊗ q_swing), so each sample's heading error becomes ψᵢ + δ wrapped,
    and the inclination error is untouched. The minimiser of Σ wrap(ψᵢ + δ)² is exact:
    at the optimum the errors ψᵢ + δ lie within one turn, so the ψᵢ, sorted, are cut
    somewhere and the part before the cut taken one turn on; for each of the n cuts the
    best δ is minus the mean and the cost n times the variance of the values so taken
    (running sums: O(n log n)), and the least of them is the global minimum, which a
    search from the circular mean can miss when the errors spread over half a turn.
    """
    psi = _select(signed_heading_error(q_est, q_true), mask)
    psi = np.sort(wrap_angles(psi[np.isfinite(psi)]))
    n = psi.size
    if n == 0:
        return 0.0
    turn = 2.0 * np.pi
    # cut j: psi[j:], then psi[:j] + 2π; their sum and sum of squares for every j
    before = np.concatenate(([0.0], np.cumsum(psi)))  # Σ psi[:j]
    j = np.arange(n)
    total = before[-1] + turn * j
    squares = np.sum(psi**2) + 2.0 * turn * before[:-1] + turn**2 * j
    cost = squares - total**2 / n  # n × the variance
    best = int(np.argmin(cost))
    return float(wrap_angles(-total[best] / n))


def remove_heading_offset(
    q_est: np.ndarray, q_true: np.ndarray, mask: np.ndarray | None = None
) -> np.ndarray:
    """``q_est`` turned about the world vertical by the constant that best matches ``q_true``.

    Returns q_z(δ) ⊗ q_est with δ from :func:`heading_offset` over the ``mask`` samples.
    The inclination error is unchanged sample by sample; the heading RMSE over ``mask``
    does not increase. This is how a 6-D (no magnetometer) estimate, whose heading is
    arbitrary, can be scored on total error.
    """
    delta = heading_offset(q_est, q_true, mask)
    turn = np.array([np.cos(0.5 * delta), 0.0, 0.0, np.sin(0.5 * delta)])
    return quat_multiply(turn, _normalized(q_est))
