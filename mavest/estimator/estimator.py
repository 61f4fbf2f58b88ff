"""The public estimator: :class:`Estimator` (online) and :func:`estimate` (batch).

Inputs are in the body frame (right-handed; FRD for MAVLink data) with the
world frame NED: ``t`` in seconds, ``gyro`` in rad/s, ``accel`` the specific
force in m/s² (≈ (0, 0, −g) at rest). Outputs: ``q`` (w, x, y, z) body → NED,
``bias`` (rad/s), ``cov`` the 6×6 covariance of the error [δθ, δb], δθ in the
world frame (left error) or body frame (right error).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from mavest import so3
from mavest._jit import kernel
from mavest.estimator.config import EstimatorConfig
from mavest.estimator.layout import N_ERROR, StepFlags, make_coefficients, new_state
from mavest.estimator.recursion import step


@kernel
def _step_scalars(
    state: np.ndarray,
    coefficients: np.ndarray,
    t: float,
    gx: float,
    gy: float,
    gz: float,
    ax: float,
    ay: float,
    az: float,
) -> tuple[float, float, bool, int, int, bool]:
    """One step; the sample comes as scalars, which cross into numba far faster than arrays."""
    s = state[0]
    s.w_sample[0] = gx
    s.w_sample[1] = gy
    s.w_sample[2] = gz
    s.w_sample[3] = ax
    s.w_sample[4] = ay
    s.w_sample[5] = az
    step(s, coefficients[0], t, s.w_sample[:3], s.w_sample[3:])
    return s.t, s.nis, s.accel_used != 0, s.flags, s.iterations, s.at_rest != 0


def _compiled_step(state: np.ndarray, coefficients: np.ndarray) -> Callable[..., tuple]:
    """The compiled step for these record types, without numba's per-call type dispatch.

    Resolving a structured array's numba type on every call costs more than the
    filter step itself; the state and coefficients keep their dtypes for life, so
    it is resolved once here. Falls back to the dispatcher if numba's layout
    differs (it is not a documented interface).
    """
    _step_scalars(state.copy(), coefficients, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8)  # compiles
    try:
        signature = next(iter(_step_scalars.overloads))
        return _step_scalars.overloads[signature].entry_point
    except (AttributeError, StopIteration):  # pragma: no cover - numba internals moved
        return _step_scalars


@kernel
def _run_batch(
    state: np.ndarray,
    coefficients: np.ndarray,
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    out_q: np.ndarray,
    out_bias: np.ndarray,
    out_cov: np.ndarray,
    out_innovation: np.ndarray,
    out_nis: np.ndarray,
    out_accel_used: np.ndarray,
    out_flags: np.ndarray,
    out_iterations: np.ndarray,
    out_at_rest: np.ndarray,
) -> None:
    s = state[0]
    c = coefficients[0]
    for i in range(t.shape[0]):
        step(s, c, t[i], gyro[i], accel[i])
        out_q[i] = s.q
        out_bias[i] = s.b
        out_cov[i] = s.P[:N_ERROR, :N_ERROR]
        out_innovation[i] = s.innovation
        out_nis[i] = s.nis
        out_accel_used[i] = s.accel_used != 0
        out_flags[i] = s.flags
        out_iterations[i] = s.iterations
        out_at_rest[i] = s.at_rest != 0


class Estimate(NamedTuple):
    """The estimate after one sample, with what the step did.

    A named tuple rather than a dataclass: the live service makes one per IMU
    sample, and a frozen dataclass costs several µs to build.
    """

    t: float
    q: np.ndarray  # (4,) w, x, y, z; body → NED
    bias: np.ndarray  # (3,) rad/s
    cov: np.ndarray  # (6, 6)
    innovation: np.ndarray  # (2,) gravity residual before the update, rad
    nis: float  # normalised innovation squared (χ², 2 dof); NaN if no measurement
    accel_used: bool
    flags: int  # StepFlags bits
    iterations: int
    at_rest: bool  # rest detected: the bias got a zero-rate update

    @property
    def euler(self) -> np.ndarray:
        """(roll, pitch, yaw) in rad, ZYX as MAVLink's ATTITUDE."""
        return so3.euler_zyx_from_quat(self.q)

    @property
    def status(self) -> list[str]:
        """Names of the flags set, e.g. ``["ACCEL_DISTURBED"]``."""
        return StepFlags.describe(self.flags)


@dataclass(frozen=True)
class EstimateSeries:
    """Estimates for N samples (the batch form of :class:`Estimate`)."""

    t: np.ndarray  # (N,)
    q: np.ndarray  # (N, 4)
    bias: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 6, 6)
    innovation: np.ndarray  # (N, 2)
    nis: np.ndarray  # (N,)
    accel_used: np.ndarray  # (N,) bool
    flags: np.ndarray  # (N,) int
    iterations: np.ndarray  # (N,) int
    at_rest: np.ndarray  # (N,) bool

    def __len__(self) -> int:
        return self.t.shape[0]

    def __getitem__(self, i: int) -> Estimate:
        return Estimate(
            float(self.t[i]),
            self.q[i],
            self.bias[i],
            self.cov[i],
            self.innovation[i],
            float(self.nis[i]),
            bool(self.accel_used[i]),
            int(self.flags[i]),
            int(self.iterations[i]),
            bool(self.at_rest[i]),
        )

    @property
    def euler(self) -> np.ndarray:
        """(N, 3) roll, pitch, yaw in rad."""
        return so3.euler_zyx_from_quats(self.q)


def _vector3(value: ArrayLike, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {array.shape}")
    return array


def _components3(value: ArrayLike, name: str) -> list[float]:
    """The three components of a vector as Python floats (fast for a (3,) array)."""
    if type(value) is np.ndarray and value.shape == (3,):
        return value.tolist()
    return _vector3(value, name).tolist()


def _series3(value: ArrayLike, n: int, name: str) -> np.ndarray:
    array = np.ascontiguousarray(value, dtype=np.float64)
    if array.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {array.shape}")
    return array


class Estimator:
    """Online attitude and gyro-bias estimator.

    >>> est = Estimator()
    >>> e = est.update(0.01, [0.0, 0.0, 0.0], [0.0, 0.0, -9.81])
    >>> e.q.round(6).tolist()
    [1.0, 0.0, 0.0, 0.0]

    The first usable sample sets tilt from the accelerometer (heading 0 until
    a heading reference exists); every later sample is a predict–update–reset
    step. Samples may arrive at any rate and with gaps.
    """

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config if config is not None else EstimatorConfig()
        self._coefficients = make_coefficients(self.config)
        self._warned_mag = False
        self._bind(new_state(self._coefficients))

    def _bind(self, state: np.ndarray) -> None:
        """Adopt a state record, with views of the fields every update reads."""
        self._state = state
        self._step = _compiled_step(state, self._coefficients)
        self._view_q = state["q"][0]
        self._view_b = state["b"][0]
        self._view_cov = state["P"][0, :N_ERROR, :N_ERROR]
        self._view_innovation = state["innovation"][0]

    def reset(self) -> None:
        """Forget everything; the next usable sample initialises again."""
        self._bind(new_state(self._coefficients))

    def initialise(
        self,
        t: float,
        q: ArrayLike,
        bias: ArrayLike | None = None,
        cov: ArrayLike | None = None,
    ) -> None:
        """Start from a known state instead of aligning on the first sample.

        ``cov`` is the 6×6 covariance of [δθ, δb] with δθ in the *world* frame
        (R_true = Exp(δθ) R); it is converted to the configured error's frame.
        Default: the configured initial covariance. The next sample at a time
        after ``t`` is the first step.
        """
        state = new_state(self._coefficients)
        s = state[0]
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0.0:
            raise ValueError("q must be a finite, non-zero quaternion (w, x, y, z)")
        s["q"] = q / np.linalg.norm(q)
        if bias is not None:
            s["b"] = _vector3(bias, "bias")
        if cov is not None:
            P = np.asarray(cov, dtype=np.float64)
            if P.shape != (6, 6) or not np.all(np.isfinite(P)):
                raise ValueError("cov must be a finite (6, 6) matrix")
            if np.any(np.linalg.eigvalsh(0.5 * (P + P.T)) <= 0.0):
                raise ValueError("cov must be symmetric positive definite")
            s["P"][:N_ERROR, :N_ERROR] = 0.5 * (P + P.T)
        if self.config.error == "right":  # δθ_body = Rᵀ δθ_world
            A = np.eye(N_ERROR)
            A[:3, :3] = so3.matrix_from_quat(s["q"]).T
            s["P"][:N_ERROR, :N_ERROR] = A @ s["P"][:N_ERROR, :N_ERROR] @ A.T
        s["t"] = float(t)
        s["t_accel"] = float(t)
        s["initialised"] = 1
        self._bind(state)

    @property
    def initialised(self) -> bool:
        return bool(self._state["initialised"][0])

    @property
    def q(self) -> np.ndarray:
        return self._state["q"][0].copy()

    @property
    def bias(self) -> np.ndarray:
        return self._state["b"][0].copy()

    @property
    def cov(self) -> np.ndarray:
        return self._state["P"][0, :N_ERROR, :N_ERROR].copy()

    @property
    def samples(self) -> int:
        """Samples taken so far (skipped ones not counted)."""
        return int(self._state["samples"][0])

    @property
    def accel_rejections(self) -> int:
        return int(self._state["accel_rejections"][0])

    def _check_mag(self, mag: Any) -> None:
        if mag is not None and not self._warned_mag:
            self._warned_mag = True
            warnings.warn(
                "magnetometer samples are not fused yet: estimating tilt and a free heading (6-D)",
                stacklevel=3,
            )

    def update(
        self, t: float, gyro: ArrayLike, accel: ArrayLike, mag: ArrayLike | None = None
    ) -> Estimate:
        """Take one sample; return the estimate after it."""
        if mag is not None:
            self._check_mag(mag)
        t_step, nis, accel_used, flags, iterations, at_rest = self._step(
            self._state,
            self._coefficients,
            float(t),
            *_components3(gyro, "gyro"),
            *_components3(accel, "accel"),
        )
        return Estimate(
            t_step,
            self._view_q.copy(),
            self._view_b.copy(),
            self._view_cov.copy(),
            self._view_innovation.copy(),
            nis,
            accel_used,
            flags,
            iterations,
            at_rest,
        )

    def update_batch(
        self,
        t: ArrayLike,
        gyro: ArrayLike,
        accel: ArrayLike,
        mag: ArrayLike | None = None,
    ) -> EstimateSeries:
        """Take N samples in one compiled loop; return the estimate after each."""
        self._check_mag(mag)
        t = np.ascontiguousarray(t, dtype=np.float64)
        if t.ndim != 1:
            raise ValueError(f"t must be one-dimensional, got shape {t.shape}")
        n = t.shape[0]
        gyro = _series3(gyro, n, "gyro")
        accel = _series3(accel, n, "accel")
        out = EstimateSeries(
            t.copy(),
            np.empty((n, 4)),
            np.empty((n, 3)),
            np.empty((n, 6, 6)),
            np.empty((n, 2)),
            np.empty(n),
            np.empty(n, dtype=bool),
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=bool),
        )
        _run_batch(
            self._state,
            self._coefficients,
            t,
            gyro,
            accel,
            out.q,
            out.bias,
            out.cov,
            out.innovation,
            out.nis,
            out.accel_used,
            out.flags,
            out.iterations,
            out.at_rest,
        )
        return out


def estimate(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
) -> EstimateSeries:
    """Estimate attitude and gyro bias for a whole recording (see :class:`Estimator`)."""
    return Estimator(config).update_batch(t, gyro, accel, mag)
