"""Is the predicted uncertainty honest on real data? The covariance scored against truth.

The Monte Carlo (:mod:`mavest.evaluation.consistency`) asks whether the covariance is
right when the world is the filter's own model; here the world is whatever the truth
of a recording says. Per recording and per quantity — tilt (2 dof) and heading (1 dof)
— with e the error and P its predicted covariance, over the scored samples:

* **calibration ratio** sqrt(mean |e|² / mean tr P): the actual RMS error over the
  predicted one; 1 is honest, below 1 the filter claims to be worse than it is;
* **share inside the 95 % region**: the fraction of samples with eᵀP⁻¹e ≤ χ²₀.₉₅(dof)
  (5.991 for 2 dof, 3.841 for 1), 0.95 for a Gaussian error of covariance P — the
  per-sample normalised estimation error squared (NEES; Bar-Shalom, Li & Kirubarajan,
  *Estimation with Applications to Tracking and Navigation*, 2001) turned into a coverage;
* **σ–error rank correlation**: Spearman's ρ between the RMS error and the RMS σ of
  windows (1 s) of the recording's own clock; positive when σ is large where the error
  is, the information a calibrated-on-average but constant σ lacks;
* σ per axis, sqrt(tr P / dof) per sample: its mean and its 1st and 95th percentiles
  (the ratio compares |e| with sqrt(tr P), σ·sqrt(dof): both sides count every axis).

The error is split as the default chart splits it (:mod:`mavest.estimator.charts`,
left / heading-tilt): R_true R̂ᵀ = Rz(ψ) Exp([τx, τy, 0]), τ the tilt and ψ the heading
error, both in the world (NED) frame. To first order τ and ψ are the x, y and z
components of Log(R_true R̂ᵀ); unlike those, τ is exact whatever the heading error (a
6-D estimate's heading is arbitrary) and |τ| is BROAD's inclination error. The
covariance must be of the world-frame error: :func:`world_attitude_covariance` turns a
right (body-frame) error's covariance into it.

Quaternions are (w, x, y, z), Hamilton, body → world, as everywhere in mavest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, spearmanr

from mavest.evaluation.metrics import heading_offset, quat_conjugate, quat_multiply

__all__ = [
    "Calibration",
    "TiltHeading",
    "calibration",
    "rank_correlation",
    "rotate_about_vertical",
    "score_attitude",
    "tilt_heading_errors",
    "window_rms",
    "world_attitude_covariance",
]

#: The probability of the ellipse (ellipsoid) the share of samples inside is counted for.
LEVEL = 0.95
#: Length (s) of the windows the rank correlation compares.
WINDOW = 1.0
#: A window counts when it holds at least this share of the samples its length
#: allows: the few samples at the edge of a scored phase give a noisy RMS.
MIN_WINDOW_FILL = 0.5


@dataclass(frozen=True)
class TiltHeading:
    """Per-sample world-frame errors (rad) of an estimate against the truth."""

    tilt: np.ndarray  # (N, 2) τ: R_true R̂ᵀ = Rz(ψ) Exp([τx, τy, 0]); NaN where truth is NaN
    heading: np.ndarray  # (N,) ψ in (−π, π]


def tilt_heading_errors(q_est: np.ndarray, q_true: np.ndarray) -> TiltHeading:
    """The tilt τ and heading ψ of the error rotation R_true R̂ᵀ = Rz(ψ) Exp([τx, τy, 0]).

    These are the coordinates of the left heading-tilt chart (the default filter's), so
    the covariance of a world-frame error describes them directly. With
    e = q_true ⊗ q̂⁻¹ = qz(ψ) ⊗ (c, a, b, 0): ψ/2 = atan2(e_z, e_w), (a, b) is (e_x, e_y)
    turned back by ψ/2, and τ is the rotation vector of the swing (c, a, b, 0).
    """
    e = quat_multiply(np.asarray(q_true, np.float64), quat_conjugate(q_est))
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    e = np.where(e[..., :1] < 0.0, -e, e)  # q and −q: the same rotation, take w ≥ 0
    w, x, y, z = np.moveaxis(e, -1, 0)
    half = np.arctan2(z, w)  # in [−π/2, π/2] as w ≥ 0
    cz, sz = np.cos(half), np.sin(half)
    a, b = cz * x + sz * y, -sz * x + cz * y
    sine, cosine = np.hypot(a, b), np.hypot(w, z)
    angle = 2.0 * np.arctan2(sine, cosine)
    with np.errstate(invalid="ignore", divide="ignore"):
        # angle / sin(angle/2) → 2 as the swing vanishes
        scale = np.where(sine > 1e-12, angle / np.where(sine > 0.0, sine, 1.0), 2.0)
    psi = 2.0 * half
    psi = np.where(psi <= -math.pi, psi + 2.0 * math.pi, psi)
    return TiltHeading(np.stack([scale * a, scale * b], axis=-1), psi)


def world_attitude_covariance(
    q_est: np.ndarray, cov: np.ndarray, error: Literal["left", "right"] = "left"
) -> np.ndarray:
    """(N, 3, 3) covariance of the world-frame attitude error from an estimate's covariance.

    ``cov`` is (N, k, k), k ≥ 3, its first three rows the attitude error. A left error
    (``"left"``, R = Exp(δθ) R̂) is in the world frame already. A right error (R = R̂ Exp(δθ),
    body frame) is the world error turned into the body, Exp(δθ_w) R̂ = R̂ Exp(R̂ᵀ δθ_w), so
    P_world = R̂ P_body R̂ᵀ.
    """
    attitude = np.asarray(cov, np.float64)[..., :3, :3]
    if error == "left":
        return attitude.copy()
    if error != "right":
        raise ValueError(f"error must be 'left' or 'right', not {error!r}")
    q = np.asarray(q_est, np.float64)
    rotation = Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()  # wxyz → scipy's xyzw
    return rotation @ attitude @ np.swapaxes(rotation, -1, -2)


def rotate_about_vertical(
    q_est: np.ndarray, cov_world: np.ndarray, delta: float
) -> tuple[np.ndarray, np.ndarray]:
    """The estimate turned by ``delta`` (rad) about the world vertical, q_z(δ) ⊗ q̂, and its
    world-frame attitude covariance Rz(δ) P Rz(δ)ᵀ (the world axes turn with it).

    This is how an estimate is compared with a truth whose north is another one (a
    constant heading offset between the two world frames).
    """
    turn = np.array([math.cos(0.5 * delta), 0.0, 0.0, math.sin(0.5 * delta)])
    c, s = math.cos(delta), math.sin(delta)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return quat_multiply(turn, q_est), rz @ np.asarray(cov_world, np.float64) @ rz.T


def _columns(values: np.ndarray) -> np.ndarray:
    """(N, k) from (N, k) or (N,)."""
    values = np.asarray(values, np.float64)
    return values[:, None] if values.ndim == 1 else values


def window_rms(t: np.ndarray, values: np.ndarray, window: float = WINDOW) -> np.ndarray:
    """(W, k) RMS of the rows of ``values`` (N, k) in consecutive windows of ``window``
    seconds of the clock ``t`` (from its first sample); windows holding fewer than
    :data:`MIN_WINDOW_FILL` of the samples their length allows are left out."""
    t = np.asarray(t, np.float64)
    values = _columns(values)
    if len(t) < 2:
        return np.empty((0, values.shape[1]))
    step = float(np.median(np.diff(t)))
    index = np.floor((t - t[0]) / window).astype(np.int64)
    counts = np.bincount(index)
    sums = np.stack([np.bincount(index, v * v, len(counts)) for v in values.T], axis=-1)
    full = counts >= MIN_WINDOW_FILL * window / step if step > 0.0 else counts > 0
    return np.sqrt(sums[full] / counts[full, None])


def rank_correlation(sigma: np.ndarray, error: np.ndarray) -> float:
    """Spearman's ρ of σ against the error (window RMS values); NaN with fewer than three
    pairs or when either side is constant (no ranking)."""
    sigma, error = np.asarray(sigma, np.float64), np.asarray(error, np.float64)
    if len(sigma) < 3 or np.ptp(sigma) == 0.0 or np.ptp(error) == 0.0:
        return math.nan
    return float(spearmanr(sigma, error).statistic)


@dataclass(frozen=True)
class Calibration:
    """How the predicted uncertainty of one quantity compares with its actual error.

    Angles in rad; NaN where there is nothing to compute (no sample, or fewer than three
    windows, or a constant window RMS, for ρ).
    """

    samples: int
    dof: int
    rmse: float  # sqrt(mean |e|²)
    sigma_rms: float  # sqrt(mean tr P), the RMS error predicted
    ratio: float  # rmse / sigma_rms
    inside: float  # share of samples with eᵀP⁻¹e ≤ χ²_LEVEL(dof)
    rank_correlation: float  # Spearman ρ of window RMS σ against window RMS error
    windows: int
    sigma_mean: float  # mean of σ per axis, sqrt(tr P / dof)
    sigma_p1: float  # 1st percentile of σ per axis
    sigma_p95: float  # 95th percentile of σ per axis
    # per window: RMS |e| and RMS σ per axis (what ρ ranks; recordings can be pooled)
    window_error: np.ndarray = field(default_factory=lambda: np.empty(0), compare=False)
    window_sigma: np.ndarray = field(default_factory=lambda: np.empty(0), compare=False)

    @property
    def threshold(self) -> float:
        """χ²_LEVEL(dof): the bound of the region the share inside is counted for."""
        return float(chi2.ppf(LEVEL, self.dof))


def calibration(
    t: np.ndarray, errors: np.ndarray, cov: np.ndarray, window: float = WINDOW
) -> Calibration:
    """Score errors (N, d) — or (N,) for d = 1 — against their predicted covariance
    (N, d, d) — or (N,) variances — over samples at times ``t`` (N,).

    Samples whose error or covariance is not finite (lost truth) are left out; the caller
    selects the scored samples (BROAD: its movement phases) before.
    """
    t = np.asarray(t, np.float64)
    errors = _columns(errors)
    d = errors.shape[1]
    cov = np.asarray(cov, np.float64)
    cov = cov[:, None, None] if cov.ndim == 1 else cov
    keep = np.all(np.isfinite(errors), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
    t, errors, cov = t[keep], errors[keep], cov[keep]
    n = len(t)
    if n == 0:
        nan = math.nan
        return Calibration(0, d, nan, nan, nan, nan, nan, 0, nan, nan, nan)
    squared = np.einsum("ni,ni->n", errors, errors)
    variance = np.trace(cov, axis1=1, axis2=2)
    nees = np.einsum("ni,ni->n", errors, np.linalg.solve(cov, errors[..., None])[..., 0])
    sigma = np.sqrt(variance / d)  # per axis: the σ a user reads off each angle
    rmse = math.sqrt(float(np.mean(squared)))
    sigma_rms = math.sqrt(float(np.mean(variance)))
    # the windows: RMS |e| and RMS σ side by side, from the same samples
    windows = window_rms(t, np.stack([np.sqrt(squared), sigma], axis=-1), window)
    # (ρ is a rank statistic: σ per axis or sqrt(tr P) gives the same)
    rho = rank_correlation(windows[:, 1], windows[:, 0])
    return Calibration(
        samples=n,
        dof=d,
        rmse=rmse,
        sigma_rms=sigma_rms,
        ratio=rmse / sigma_rms if sigma_rms > 0.0 else math.nan,
        inside=float(np.mean(nees <= chi2.ppf(LEVEL, d))),
        rank_correlation=rho,
        windows=len(windows),
        sigma_mean=float(np.mean(sigma)),
        sigma_p1=float(np.percentile(sigma, 1.0)),
        sigma_p95=float(np.percentile(sigma, 95.0)),
        window_error=windows[:, 0],
        window_sigma=windows[:, 1],
    )


def score_attitude(
    t: np.ndarray,
    q: np.ndarray,
    cov: np.ndarray,
    truth_q: np.ndarray,
    scored: np.ndarray,
    error: Literal["left", "right"] = "left",
    heading: bool = False,
    foreign_north: bool = False,
) -> tuple[Calibration, Calibration | None, float]:
    """Tilt and (``heading``) heading calibration of an estimate (q (N, 4), its error's
    cov (N, 6, 6)) over the ``scored`` samples, and the heading offset removed first:
    with ``foreign_north`` (BROAD's optical frame has its own north) a constant offset
    is fitted (:func:`~mavest.evaluation.metrics.heading_offset`) and turned off the
    estimate and its covariance; 0 otherwise."""
    cov_world = world_attitude_covariance(q, cov, error)
    offset = 0.0
    if heading and foreign_north:
        offset = heading_offset(q, truth_q, scored)
        q, cov_world = rotate_about_vertical(q, cov_world, offset)
    errors = tilt_heading_errors(q, truth_q)
    times = t[scored]
    tilt = calibration(times, errors.tilt[scored], cov_world[scored][:, :2, :2])
    heading_score = None
    if heading:
        heading_score = calibration(times, errors.heading[scored], cov_world[scored][:, 2, 2])
    return tilt, heading_score, offset
