"""The public estimator: :class:`Estimator` (online) and :func:`estimate` (batch).

Inputs are in the body frame (right-handed; FRD for MAVLink data) with the
world frame NED: ``t`` in seconds, ``gyro`` in rad/s, ``accel`` the specific
force in m/s² (≈ (0, 0, −g) at rest). Outputs: ``q`` (w, x, y, z) body → NED,
``bias`` (rad/s), ``cov`` the 6×6 covariance of the error [δθ, δb], δθ in the
world frame (left error) or body frame (right error).
"""

from __future__ import annotations

import copy
import math
import operator
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike

from mavest import so3
from mavest._jit import inplace_kernel, without_dispatch
from mavest.estimator import online
from mavest.estimator.config import (
    MAX_ANGULAR_RATE,
    MAX_ATTITUDE_VAR,
    MAX_GYRO_BIAS,
    MAX_SPECIFIC_FORCE,
    EstimatorConfig,
    config_or_default,
)
from mavest.estimator.frames import add_reported_alignment, report_attitude_into
from mavest.estimator.gyro_unit import gyro_unit_problem
from mavest.estimator.heading import turn_heading
from mavest.estimator.health import state_is_plausible
from mavest.estimator.layout import N_ERROR, StepFlags, make_coefficients, new_state
from mavest.estimator.linalg import copy_into, copy_matrix_into
from mavest.estimator.recursion import step


class InputError(ValueError):
    """Input that cannot be what it should (e.g. an accelerometer in g rather than
    m/s²), with what to do in the message."""


@inplace_kernel
def _turn_heading(state: np.ndarray, coefficients: np.ndarray, psi: float) -> None:
    """:func:`~mavest.estimator.heading.turn_heading` on the state record."""
    turn_heading(state[0], coefficients[0], psi)


_TURN_ENTRY_POINTS: dict[tuple[np.dtype, np.dtype], Callable[..., None]] = {}


def _turn_entry_point(state: np.ndarray, coefficients: np.ndarray) -> Callable[..., None]:
    """The compiled heading turn for these record types, without numba's per-call type
    dispatch (the records keep their dtypes for life).

    Resolved once per process, with the first estimator rather than when a
    declination first arrives: loading it takes milliseconds, which a live stream
    would stall for mid-flight.
    """
    key = (state.dtype, coefficients.dtype)
    found = _TURN_ENTRY_POINTS.get(key)
    if found is None:
        found = without_dispatch(_turn_heading, state.copy(), coefficients, 0.0)
        _TURN_ENTRY_POINTS[key] = found
    return found


# The online step: the extension's where it built (and numba compiles), else the
# Python path's, which gives the same estimates a few µs a sample slower.
_COMPILED = online.compiled()
_ONLINE: Callable[[np.ndarray, np.ndarray], Any]
if _COMPILED is not None:
    Estimate = _COMPILED.Estimate
    _ONLINE = _COMPILED.Online
else:
    Estimate = online.Estimate
    _ONLINE = online.PythonOnline


@inplace_kernel
def _run_batch(
    state: np.ndarray,
    coefficients: np.ndarray,
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray,
    linear_accel: np.ndarray,
    out_q: np.ndarray,
    out_bias: np.ndarray,
    out_cov: np.ndarray,
    out_innovation: np.ndarray,
    out_nis: np.ndarray,
    out_accel_used: np.ndarray,
    out_flags: np.ndarray,
    out_iterations: np.ndarray,
    out_at_rest: np.ndarray,
    out_heading_innovation: np.ndarray,
    out_heading_nis: np.ndarray,
    out_mag_used: np.ndarray,
) -> None:
    s = state[0]
    c = coefficients[0]
    # mag and linear_accel may be one row for all samples (NaN: none throughout)
    last_mag = mag.shape[0] - 1
    last_linear = linear_accel.shape[0] - 1
    for i in range(t.shape[0]):
        step(
            s, c, t[i], gyro[i], accel[i], mag[min(i, last_mag)], linear_accel[min(i, last_linear)]
        )
        report_attitude_into(s, c, gyro[i], out_q[i])
        copy_into(out_bias[i], s.b)
        copy_matrix_into(out_cov[i], s.P[:N_ERROR, :N_ERROR])
        add_reported_alignment(s, c, out_cov[i])
        copy_into(out_innovation[i], s.innovation)
        out_nis[i] = s.nis
        out_accel_used[i] = s.accel_used != 0
        out_flags[i] = s.flags
        out_iterations[i] = s.iterations
        out_at_rest[i] = s.at_rest != 0
        out_heading_innovation[i] = s.heading_innovation
        out_heading_nis[i] = s.heading_nis
        out_mag_used[i] = s.mag_used != 0


@dataclass(frozen=True)
class EstimateSeries:
    """Estimates for N samples (the batch form of :class:`Estimate`)."""

    t: np.ndarray  # (N,)
    q: np.ndarray  # (N, 4)
    bias: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 6, 6)
    # what the last gravity update measured (at a BETWEEN_UPDATES sample: the one before)
    innovation: np.ndarray  # (N, 2)
    nis: np.ndarray  # (N,)
    accel_used: np.ndarray  # (N,) bool
    flags: np.ndarray  # (N,) int32
    iterations: np.ndarray  # (N,) int16
    at_rest: np.ndarray  # (N,) bool
    heading_innovation: np.ndarray  # (N,)
    heading_nis: np.ndarray  # (N,)
    mag_used: np.ndarray  # (N,) bool

    @classmethod
    def empty(cls, n: int) -> EstimateSeries:
        """A series of N estimates yet to be written (e.g. by :meth:`Estimator.update_batch`)."""
        return cls(
            **{
                name: np.empty((n, *shape), dtype=dtype)
                for name, (shape, dtype) in SERIES_FIELDS.items()
            }
        )

    def check_writable(self, n: int) -> None:
        """That this series can take N estimates as :meth:`Estimator.update_batch` writes
        them: each array as :meth:`empty` makes it, (N, …) of its dtype, C-contiguous and
        writeable (the compiled loop writes them unchecked). Else a TypeError (a type) or
        ValueError (a shape, a layout) naming the array."""
        for name, (shape, dtype) in SERIES_FIELDS.items():
            array = getattr(self, name)
            if not isinstance(array, np.ndarray) or array.dtype != dtype:
                kind = array.dtype if isinstance(array, np.ndarray) else type(array).__name__
                raise TypeError(f"out.{name} must be a numpy array of {dtype}, got {kind}")
            if array.shape != (n, *shape):
                raise ValueError(f"out.{name} must have shape {(n, *shape)}, got {array.shape}")
            if not (array.flags.c_contiguous and array.flags.writeable):
                raise ValueError(f"out.{name} must be a C-contiguous, writeable array")

    def rows(self, start: int, stop: int) -> EstimateSeries:
        """Estimates [start, stop) as views of this series' arrays (writing them writes
        this series)."""
        return EstimateSeries(
            *(getattr(self, name)[start:stop] for name in self.__dataclass_fields__)
        )

    def __len__(self) -> int:
        return self.t.shape[0]

    @overload
    def __getitem__(self, i: int) -> Estimate: ...

    @overload
    def __getitem__(self, i: slice) -> EstimateSeries: ...

    def __getitem__(self, i: int | slice) -> Estimate | EstimateSeries:
        """Sample ``i``'s :class:`Estimate`; a slice of samples as a series of views of
        these arrays (as :meth:`rows` gives)."""
        if isinstance(i, slice):
            return EstimateSeries(*(getattr(self, name)[i] for name in SERIES_FIELDS))
        try:
            i = operator.index(i)
        except TypeError:
            raise TypeError(
                f"an EstimateSeries is indexed by a sample number or a slice, not "
                f"{type(i).__name__}; its arrays (series.q[mask], ...) take any numpy index"
            ) from None
        return Estimate.of(
            self.t[i],
            self.q[i],
            self.bias[i],
            self.cov[i],
            self.innovation[i],
            self.nis[i],
            self.accel_used[i],
            self.flags[i],
            self.iterations[i],
            self.at_rest[i],
            self.heading_innovation[i],
            self.heading_nis[i],
            self.mag_used[i],
        )

    @property
    def euler(self) -> np.ndarray:
        """(N, 3) roll, pitch, yaw in rad."""
        return so3.euler_zyx_from_quats(self.q)


# The narrowest types that hold every StepFlags value and any iteration count: a
# sample's estimate is 401 B, of which the covariance is 288.
FLAGS_DTYPE = np.int32
ITERATIONS_DTYPE = np.int16  # (EstimatorConfig's max_iterations is at most MAX_ITERATIONS)

# Each array of an EstimateSeries: its shape after N, its dtype.
SERIES_FIELDS: dict[str, tuple[tuple[int, ...], np.dtype]] = {
    "t": ((), np.dtype(np.float64)),
    "q": ((4,), np.dtype(np.float64)),
    "bias": ((3,), np.dtype(np.float64)),
    "cov": ((N_ERROR, N_ERROR), np.dtype(np.float64)),
    "innovation": ((2,), np.dtype(np.float64)),
    "nis": ((), np.dtype(np.float64)),
    "accel_used": ((), np.dtype(bool)),
    "flags": ((), np.dtype(FLAGS_DTYPE)),
    "iterations": ((), np.dtype(ITERATIONS_DTYPE)),
    "at_rest": ((), np.dtype(bool)),
    "heading_innovation": ((), np.dtype(np.float64)),
    "heading_nis": ((), np.dtype(np.float64)),
    "mag_used": ((), np.dtype(bool)),
}


def _series3(value: ArrayLike, n: int, name: str) -> np.ndarray:
    array = online.real_array(value, name)
    if array.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {array.shape}")
    return array


def batch_inputs(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    linear_accel: ArrayLike | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A batch's inputs as :meth:`Estimator.update_batch` takes them: float64,
    C-contiguous, ``t`` (N,) and the others (N, 3) (None stays None); ValueError
    naming the input whose shape is wrong."""
    t = online.real_array(t, "t")
    if t.ndim != 1:
        raise ValueError(f"t must be one-dimensional, got shape {t.shape}")
    n = t.shape[0]
    return (
        t,
        _series3(gyro, n, "gyro"),
        _series3(accel, n, "accel"),
        None if mag is None else _series3(mag, n, "mag"),
        None if linear_accel is None else _series3(linear_accel, n, "linear_accel"),
    )


def _sample3(value: ArrayLike, name: str) -> tuple[float, float, float]:
    """One sample's vector as the online step reads it: its three components
    (``online.components3``), each made a float by ``float()`` (a complex one is a
    TypeError, not its real part)."""
    x, y, z = online.components3(value, name)
    return float(x), float(y), float(z)


# Samples a batch-fed estimator's update takes as batches of one before it starts its
# online step (see Estimator): ~5 ms of them, against the step's 50 to load.
_LONE_BATCHES = 256


class _OnlineUpdate:
    """``Estimator.update`` as an estimator gives it: its online step's own method once
    that step is due, else the Python method below.

    A caller that fetches ``update`` once and calls it in a loop then gets the compiled
    method itself, with no Python frame of ours on the way: a frame costs about as much
    as the rest of the way in. (Fetching it makes the online step, as the first call
    would have; the instance attribute ``_bind_update`` sets then shadows this.)
    """

    def __init__(self, method: Callable[..., Any]) -> None:
        self._method = method
        self.__doc__ = method.__doc__

    def __get__(self, estimator: Estimator | None, cls: type | None = None) -> Any:
        if estimator is None:
            return self._method
        cls = type(estimator)
        compiled = cls._compiled_update(estimator)
        return compiled if compiled is not None else self._method.__get__(estimator, cls)


class Estimator:
    """Online attitude and gyro-bias estimator.

    >>> est = Estimator()
    >>> e = est.update(0.01, [0.0, 0.0, 0.0], [0.0, 0.0, -9.81])
    >>> e.q.round(6).tolist()
    [1.0, 0.0, 0.0, 0.0]

    The first usable sample sets tilt from the accelerometer (heading 0 until
    a heading reference exists); every later sample is a predict–update–reset
    step. Samples may arrive at any rate and with gaps. A single timestamp far
    off the timeline is skipped (``StepFlags.TIME_OFF_TIMELINE``); time that
    jumps and stays there is a gap, or, back, a restart (``TIME_RESTARTED``:
    ``EstimatorConfig.max_jump``, ``timeline_confirm``). An accelerometer in g,
    mg or mm/s² is flagged (``ACCEL_WRONG_UNIT``) and warned of, once.
    """

    def __init__(self, config: EstimatorConfig | None = None, *, batch_fed: bool = False) -> None:
        """``batch_fed``: for a caller that feeds batches and only now and then a single
        sample (``mavest replay``): :meth:`update` then runs the batch loop on that
        sample, for the same estimate at 20 µs a call instead of 1, and the online
        step's compiled code (0.05 s to load) is not loaded unless there are many of
        them (a damaged file, stepped sample by sample)."""
        self.config = config_or_default(config)
        self._coefficients = make_coefficients(self.config)
        self._state = new_state(self._coefficients)
        self._turn = _turn_entry_point(self._state, self._coefficients)
        # The online step is made by the first update (a batch-fed estimator's first
        # after _LONE_BATCHES): loading its compiled code takes tens of milliseconds,
        # which a caller of update_batch alone need not wait for. (Which step, the
        # extension's or the Python path's, is decided here.)
        self._online: Any = None
        self._online_kind = _ONLINE
        # the samples update has taken as batches of one (not batch-fed: none to take)
        self._batched_alone = 0 if batch_fed else _LONE_BATCHES

    def _compiled_update(self) -> Callable[..., Any] | None:
        """The online step's own update, made now if it is due (not batch-fed, or
        past its lone batches); None while update is to run as a batch of one."""
        if self._online is None and self._batched_alone >= _LONE_BATCHES:
            self._start_online()
        return None if self._online is None else self._online.update

    def _start_online(self) -> None:
        self._online = self._online_kind(self._state, self._coefficients)
        self._bind_update()

    def _bind_update(self) -> None:
        # This estimator's update is then its online step's own method, which a call
        # reaches with no Python frame of ours on the way (a frame costs as much as the
        # rest of the way in); the method below documents it and makes the step. The
        # online step stays the same object for life, so an update fetched once follows
        # resets.
        self.update = self._online.update

    def _bind(self, state: np.ndarray) -> None:
        """Adopt a state record; estimates go into a fresh output block."""
        self._state = state
        if self._online is not None:
            self._online.bind(state)

    def __getstate__(self) -> dict[str, Any]:
        # (for pickle and copy.deepcopy) the compiled code's entry points are not data: the
        # copy resolves its own, and makes its own online step if this one had made one
        attributes = self.__dict__.copy()
        attributes.pop("update", None)
        attributes.pop("_turn")
        attributes["_online"] = attributes["_online"] is not None
        return attributes

    def __setstate__(self, attributes: dict[str, Any]) -> None:
        online_started = attributes.pop("_online")
        self.__dict__.update(attributes)
        self._turn = _turn_entry_point(self._state, self._coefficients)
        self._online = None
        if online_started:
            self._start_online()

    def __copy__(self) -> Estimator:
        """An independent estimator (as :func:`copy.deepcopy`): two sharing one filter
        state would each step it."""
        return copy.deepcopy(self)

    def reset(self) -> None:
        """Forget everything; the next usable sample initialises again."""
        self._bind(new_state(self._coefficients))

    def snapshot(self) -> np.ndarray:
        """A copy of the filter's state: everything an update changes (not the
        configuration, nor the declination, which updates leave alone). Opaque: only
        for :meth:`restore`, on this estimator or one made with the same configuration."""
        return self._state.copy()

    def restore(self, snapshot: np.ndarray) -> None:
        """Put back a state taken by :meth:`snapshot`: the updates since are undone,
        as if they had not been made (an update fetched before follows, as it follows
        :meth:`reset`)."""
        if not (
            isinstance(snapshot, np.ndarray)
            and snapshot.dtype == self._state.dtype
            and snapshot.shape == self._state.shape
        ):
            raise TypeError("restore takes a snapshot() of an estimator of this configuration")
        # in place: the online step and the heading turn hold this record
        self._state[...] = snapshot

    def initialise(
        self,
        t: float,
        q: ArrayLike,
        bias: ArrayLike | None = None,
        cov: ArrayLike | None = None,
        heading_known: bool = True,
    ) -> None:
        """Start from a known state instead of aligning on the first sample.

        ``cov`` is the 6×6 covariance of [δθ, δb] with δθ in the *world* frame
        (R_true = Exp(δθ) R); it is converted to the configured error's frame.
        Default: the configured initial covariance. The next sample at a time
        after ``t`` is the first step. The heading counts as known: a
        magnetometer then corrects it instead of setting it afresh; with
        ``heading_known`` False the first magnetometer reading sets it, as after
        an alignment. ``q`` is the filter's own attitude (:attr:`q`): with an
        ``imu_delay``, the IMU's at ``t`` less the delay.
        """
        # Each refusal is one the health check would otherwise make at the next sample,
        # throwing the state given away (UNHEALTHY_RESET), or a time that never passes.
        state = new_state(self._coefficients)
        s = state[0]
        if not math.isfinite(t):
            raise ValueError(f"t must be a finite time in seconds, got {t}")
        q = online.real_array(q, "q")
        if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.any(q):
            raise ValueError("q must be a finite, non-zero quaternion (w, x, y, z)")
        with np.errstate(over="ignore", under="ignore"):
            norm = float(np.linalg.norm(q))
        if not (math.isfinite(norm) and norm > 0.0):  # its norm overflowed, or underflowed
            q = q / np.max(np.abs(q))
            norm = float(np.linalg.norm(q))
        s["q"] = q / norm
        if bias is not None:
            s["b"] = online.vector3(bias, "bias")
        if cov is not None:
            P = online.real_array(cov, "cov")
            if P.shape != (6, 6) or not np.all(np.isfinite(P)):
                raise ValueError("cov must be a finite (6, 6) matrix")
            if np.any(np.linalg.eigvalsh(0.5 * (P + P.T)) <= 0.0):
                raise ValueError("cov must be symmetric positive definite")
            s["P"][:N_ERROR, :N_ERROR] = 0.5 * (P + P.T)
        if self.config.error == "right":  # δθ_body = Rᵀ δθ_world
            A = np.eye(N_ERROR)
            A[:3, :3] = so3.matrix_from_quat(s["q"]).T
            s["P"][:N_ERROR, :N_ERROR] = A @ s["P"][:N_ERROR, :N_ERROR] @ A.T
        if not state_is_plausible(s, self._coefficients[0]):  # (the health check's rule)
            raise ValueError(
                f"bias must be finite and within ±{MAX_GYRO_BIAS:g} rad/s, and cov's "
                f"variances at most {MAX_ATTITUDE_VAR:g} rad² (attitude) and "
                f"{MAX_GYRO_BIAS**2:g} (rad/s)² (bias)"
            )
        s["t"] = float(t)
        s["t_accel"] = float(t)
        s["initialised"] = 1
        # heading given: a magnetometer corrects it; else its first reading sets it
        s["mag_state"] = 1 if heading_known else 0
        self._bind(state)

    @property
    def initialised(self) -> bool:
        return bool(self._state["initialised"][0])

    @property
    def q(self) -> np.ndarray:
        """The filter's own attitude: the IMU's at its last sample's time stamp less
        ``imu_delay``, which the estimates carry forward to the time stamp
        (docs/design.md#the-imus-delay); the same without a delay."""
        return self._state["q"][0].copy()

    @property
    def bias(self) -> np.ndarray:
        return self._state["b"][0].copy()

    @property
    def cov(self) -> np.ndarray:
        """The filter's own P (6×6), what :meth:`initialise` takes: without the
        accelerometer's alignment, which an estimate's ``cov`` adds."""
        return self._state["P"][0, :N_ERROR, :N_ERROR].copy()

    @property
    def accel_unit_problem(self) -> str | None:
        """What the filter found of the accelerometer's unit, in one line, if it reads g
        in another unit than m/s² (the samples flagged ``StepFlags.ACCEL_WRONG_UNIT``,
        on which it does not start); None while it has found nothing wrong."""
        if self._state["accel_unit"][0] <= 0:
            return None
        return online.accel_unit_message(self._state)

    @property
    def samples(self) -> int:
        """Samples taken so far (skipped ones not counted)."""
        return int(self._state["samples"][0])

    @property
    def accel_rejections(self) -> int:
        return int(self._state["accel_rejections"][0])

    @property
    def unhealthy_resets(self) -> int:
        """Re-initialisations after a failed health check (StepFlags.UNHEALTHY_RESET)."""
        return int(self._state["unhealthy_resets"][0])

    @property
    def divergence_resets(self) -> int:
        """Re-initialisations after a divergence (StepFlags.DIVERGED)."""
        return int(self._state["divergence_resets"][0])

    @property
    def declination(self) -> float:
        """Magnetic declination in use (rad, east positive); starts as ``config.compass_dec``."""
        return float(self._coefficients["mag_declination"][0])

    @declination.setter
    def declination(self, value: float) -> None:
        """Change the declination (e.g. to the vehicle's own COMPASS_DEC) while running.

        A heading the magnetometer has already referenced turns with it at once,
        its uncertainty kept: it was the field's azimuth plus the old
        declination. (Left to the magnetometer updates, a 12° change takes
        minutes at a converged heading's σ, or trips the innovation gate.)
        """
        if not abs(value) <= math.pi:  # (NaN too)
            raise ValueError(f"declination must be within ±π rad, got {value} (degrees?)")
        turn = math.remainder(value - self.declination, math.tau)
        self._coefficients["mag_declination"] = value
        if self.initialised and self._state["t_mag_used"][0] > -math.inf and turn != 0.0:
            self._turn(self._state, self._coefficients, turn)

    def gyro_clipped(self) -> None:
        """The gyro clipped (a sample the caller dropped, its field at the limit):
        the estimate waits for the vehicle to be calm, then re-aligns tilt from the
        accelerometer (``EstimatorConfig.gyro_clip``, ``StepFlags.CLIP_REALIGNED``)."""
        if self.initialised:
            self._state["clip_calm_time"] = 0.0

    @property
    def mag_rejections(self) -> int:
        """Magnetometer samples not used: field off the reference, or innovation gated."""
        return int(self._state["mag_disturbances"][0])

    @property
    def heading_referenced(self) -> bool:
        """Whether a magnetometer has set the heading (9-D); else heading is free (6-D)."""
        return bool(self._state["mag_state"][0])

    @_OnlineUpdate
    def update(
        self,
        t: float,
        gyro: ArrayLike,
        accel: ArrayLike,
        mag: ArrayLike | None = None,
        linear_accel: ArrayLike | None = None,
    ) -> Estimate:
        """Take one sample; return the estimate after it.

        ``mag`` (µT, FRD) when this sample carries a magnetometer reading; None
        (or NaN) when it does not: heading then runs on the gyro alone.
        ``linear_accel`` (m/s², NED) the vehicle's acceleration relative to the
        Earth when it is known (from GPS velocity): it is removed from the
        specific force, and in turns the gravity update then also sees heading.
        None (or NaN): unknown, averaged away by the low-pass.
        """
        if self._online is None:  # the first update: later ones go straight to the step
            if self._batched_alone < _LONE_BATCHES:
                self._batched_alone += 1
                return self._update_as_batch(t, gyro, accel, mag, linear_accel)
            self._start_online()
        return self._online.update(t, gyro, accel, mag, linear_accel)

    def _update_as_batch(
        self,
        t: float,
        gyro: ArrayLike,
        accel: ArrayLike,
        mag: ArrayLike | None,
        linear_accel: ArrayLike | None,
    ) -> Estimate:
        """:meth:`update` as a batch of one sample (``batch_fed``), its inputs taken as the
        online step takes them (the same values accepted, the same errors)."""
        series = self.update_batch(
            (float(t),),
            (_sample3(gyro, "gyro"),),
            (_sample3(accel, "accel"),),
            None if mag is None else (_sample3(mag, "mag"),),
            None if linear_accel is None else (_sample3(linear_accel, "linear_accel"),),
        )
        if series.flags[0] & StepFlags.ACCEL_WRONG_UNIT:
            online.warn_accel_unit(self._state, stacklevel=3)
        return series[0]

    def update_batch(
        self,
        t: ArrayLike,
        gyro: ArrayLike,
        accel: ArrayLike,
        mag: ArrayLike | None = None,
        linear_accel: ArrayLike | None = None,
        out: EstimateSeries | None = None,
    ) -> EstimateSeries:
        """Take N samples in one compiled loop; return the estimate after each.

        ``mag`` (N, 3) µT, NaN rows where a sample has no magnetometer reading;
        None: 6-D throughout. ``linear_accel`` (N, 3) m/s² NED, NaN rows where
        the vehicle's acceleration is not known (see :meth:`update`). An
        accelerometer in another unit is flagged (``StepFlags.ACCEL_WRONG_UNIT``),
        neither warned of nor raised (:meth:`update` warns, :func:`estimate` raises).
        ``out``: N estimates to write the result into (e.g. ``series.rows(i, i + N)``
        of a longer series filled a batch at a time), which is returned.
        """
        t, gyro, accel, mag, linear_accel = batch_inputs(t, gyro, accel, mag, linear_accel)
        n = t.shape[0]
        # one NaN row stands for "none" at every sample: an hour at 1 kHz would
        # otherwise hold 86 MB of NaN for each
        none = np.full((1, 3), np.nan)
        mag = none if mag is None else mag
        linear_accel = none if linear_accel is None else linear_accel
        if out is None:
            out = EstimateSeries.empty(n)
        elif not isinstance(out, EstimateSeries):
            raise TypeError(f"out must be an EstimateSeries, got {type(out).__name__}")
        else:
            out.check_writable(n)
        out.t[:] = t
        _run_batch(
            self._state,
            self._coefficients,
            t,
            gyro,
            accel,
            mag,
            linear_accel,
            out.q,
            out.bias,
            out.cov,
            out.innovation,
            out.nis,
            out.accel_used,
            out.flags,
            out.iterations,
            out.at_rest,
            out.heading_innovation,
            out.heading_nis,
            out.mag_used,
        )
        return out


def estimate(
    t: ArrayLike,
    gyro: ArrayLike,
    accel: ArrayLike,
    mag: ArrayLike | None = None,
    config: EstimatorConfig | None = None,
    linear_accel: ArrayLike | None = None,
) -> EstimateSeries:
    """Estimate attitude and gyro bias for a whole recording (see :class:`Estimator`).

    Raises :class:`InputError` when the gyroscope is not in rad/s (it turns gravity
    57× or 1000× as far as the accelerometer sees it turn: :mod:`.gyro_unit`), or when
    nothing would be estimated, every sample NOT_INITIALISED: the accelerometer is in
    another unit than m/s² (its norm over the first samples is g in g, mg or mm/s²), or
    no sample could start the estimate (the line says why, e.g. an accelerometer never
    near g, a gyro never finite).
    """
    config = config_or_default(config)
    t, gyro, accel, mag, linear_accel = batch_inputs(t, gyro, accel, mag, linear_accel)
    refuse_wrong_gyro_unit(t, gyro, accel, config)
    estimator = Estimator(config)
    series = estimator.update_batch(t, gyro, accel, mag, linear_accel)
    refuse_wrong_unit(estimator, series.flags)
    return series


def refuse_wrong_gyro_unit(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, config: EstimatorConfig
) -> None:
    """:class:`InputError` if a batch's gyroscope is not in rad/s, as its accelerometer
    sees it (:func:`.gyro_unit.gyro_unit_problem`): the estimate would be meaningless,
    every accelerometer sample rejected, and no flag would say why."""
    problem = gyro_unit_problem(t, gyro, accel, config.gravity, config.max_dt)
    if problem is not None:
        raise InputError(problem)


def refuse_wrong_unit(estimator: Estimator, flags: np.ndarray) -> None:
    """:class:`InputError` if the estimator's samples (``flags``: their steps' flags, as a
    series holds them) were flagged with an accelerometer in another unit
    (``StepFlags.ACCEL_WRONG_UNIT``), or if not one of them was estimated (each
    NOT_INITIALISED): a recording's estimate would be all placeholders. The message is
    one line, saying why."""
    problem = estimator.accel_unit_problem
    if problem is not None and np.any(flags & StepFlags.ACCEL_WRONG_UNIT):
        raise InputError(problem)
    if flags.shape[0] and np.all(flags & StepFlags.NOT_INITIALISED):
        raise InputError(_why_not_initialised(flags, estimator.config))


def _why_not_initialised(flags: np.ndarray, config: EstimatorConfig) -> str:
    """Why not one of these samples started the estimate, from their flags (what
    ``recursion`` sets on a sample that could not), in one line."""
    reasons = {
        StepFlags.ACCEL_INVALID: (
            f"accelerometer zero, not finite or beyond {MAX_SPECIFIC_FORCE:g} m/s²"
        ),
        StepFlags.ACCEL_REJECTED_NORM: (
            f"accelerometer norm not within {config.accel_norm_tolerance:g} of "
            f"g = {config.gravity:g} m/s² (not in m/s², or never at rest)"
        ),
        StepFlags.GYRO_INVALID: f"gyro not finite or beyond {MAX_ANGULAR_RATE:g} rad/s",
        StepFlags.TIME_NOT_INCREASING: "time not finite",
    }
    n = len(flags)
    counts = [
        f"{what} at {np.count_nonzero(flags & bit)} of {n} samples"
        for bit, what in reasons.items()
        if np.any(flags & bit)
    ]
    return "nothing estimated, no sample could start the estimate: " + "; ".join(counts)
