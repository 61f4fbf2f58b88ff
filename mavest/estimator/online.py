"""The online step around the compiled filter step: a sample in, an :class:`Estimate` out.

The filter step itself takes a microsecond or two; getting a sample into it and an
estimate out of it cost as much again while Python objects crossed on the way (numba
unboxing 13 floats and a record, boxing a 9-tuple, converting the vectors). So the
step's body, :func:`step_into_row`, writes everything an estimate shows, scalars
included, into one float64 row of an output block (layout ``ROW_*``; the Euler
angles are left to their first reader, :func:`euler_of_row`), and is compiled twice:

* as a C function, :data:`step_callback`, that the extension ``_online`` (Cython)
  calls through its address with the sample's components as C doubles; the
  extension's ``Online.update`` reads the vectors' memory directly and returns its
  ``Estimate``, which reads the row in C;
* as a numba kernel, called through its entry point by :class:`PythonOnline` with
  the inputs converted here, returning this module's :class:`Estimate`: the path
  where the extension did not build (no compiler) or under ``NUMBA_DISABLE_JIT``.

The two paths give the same estimates bit for bit, and take and reject the same inputs.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType

import numba
import numpy as np
from numba import types
from numpy.typing import ArrayLike

from mavest import so3
from mavest._jit import callback_kernel, inplace_kernel, kernel, without_dispatch
from mavest.estimator.frames import add_reported_alignment, report_attitude_into
from mavest.estimator.layout import (
    COEFFICIENTS_DTYPE,
    N_ERROR,
    ROW_ACCEL_USED,
    ROW_AT_REST,
    ROW_BIAS,
    ROW_COV,
    ROW_EULER,
    ROW_FLAGS,
    ROW_HEADING_INNOVATION,
    ROW_HEADING_NIS,
    ROW_INNOVATION,
    ROW_ITERATIONS,
    ROW_MAG_USED,
    ROW_NIS,
    ROW_Q,
    ROW_T,
    ROW_WIDTH,
    STATE_DTYPE,
    CoefficientsRecord,
    StateRecord,
    StepFlags,
)
from mavest.estimator.linalg import copy_into
from mavest.estimator.recursion import ACCEL_UNITS, accel_unit_of, step

# Rows per output block: a block is shared by the estimates made from it and freed with
# the last of them, so it is small (21 KiB) for callers that keep a few estimates.
BLOCK_ROWS = 48

UNKNOWN3 = (math.nan, math.nan, math.nan)  # no magnetometer, no known acceleration

ACCEL_WRONG_UNIT = StepFlags.ACCEL_WRONG_UNIT


class AccelUnitWarning(UserWarning):
    """The accelerometer reads g in another unit than m/s² (StepFlags.ACCEL_WRONG_UNIT):
    the filter does not start on it. The ``mavest`` command filters this category out:
    its service says so itself, once per stream (``pipeline.report_accel_unit``)."""


def accel_unit_message(state: np.ndarray) -> str:
    """What the step found of a state's accelerometer unit (StepFlags.ACCEL_WRONG_UNIT),
    in one line."""
    s = state[0]
    k = int(s["accel_unit"]) - 1
    name, scale = ACCEL_UNITS[k]
    norm = float(s["unit_norm_sum"][k] / s["unit_votes"][k])
    return (
        f"accelerometer norm ≈ {norm:.4g}: looks like {name}, mavest wants m/s²"
        f" (multiply by {scale:.6g})"
    )


def accel_unit_named(norm: float, gravity: float) -> tuple[str, float] | None:
    """The unit (its name, m/s² per unit) in which an accelerometer's ``norm`` is one g
    (``gravity``), if it is in one of ACCEL_UNITS: the step's rule, run as Python (for a
    sample the service rejects, which the step never sees; no compiling for it)."""
    k = getattr(accel_unit_of, "py_func", accel_unit_of)(norm, gravity)
    return ACCEL_UNITS[k] if k >= 0 else None


def warn_accel_unit(state: np.ndarray, stacklevel: int) -> None:
    """Warn that the accelerometer is in another unit, once for a state record (the
    caller saw ACCEL_WRONG_UNIT). ``stacklevel`` as :func:`warnings.warn`'s, counted
    from the caller: the frame that called :meth:`Estimator.update`."""
    if state["unit_warned"][0]:
        return
    state["unit_warned"] = 1
    warnings.warn(accel_unit_message(state), AccelUnitWarning, stacklevel=stacklevel + 1)


def real_array(value: ArrayLike, name: str) -> np.ndarray:
    """``value`` as a C-contiguous float64 array; a TypeError for complex numbers or text
    (which numpy would convert, dropping the imaginary part or parsing the text) and for
    dates or durations (their raw counts are no seconds). A masked array's masked
    values are NaN: not there, as the filter takes NaN (``np.asarray`` would pass the
    values under the mask on as if they were measured)."""
    if isinstance(value, np.ma.MaskedArray):
        value = value.astype(np.float64).filled(np.nan)
    array = np.asarray(value)
    if array.dtype.kind in "cUS":
        raise TypeError(f"{name} must be real numbers, got {array.dtype} values")
    if array.dtype.kind in "mM":
        raise TypeError(
            f"{name} must be seconds as float64, got {array.dtype} values "
            "(for times: (t - t[0]) / np.timedelta64(1, 's'))"
        )
    return np.ascontiguousarray(array, dtype=np.float64)


def vector3(value: ArrayLike, name: str) -> np.ndarray:
    array = real_array(value, name)
    if array.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {array.shape}")
    return array


def components3(value: ArrayLike, name: str) -> Sequence[float]:
    """The three components of a vector as Python floats (fast for a (3,) array and for
    a tuple of three floats, which is what the service's decoded samples carry)."""
    kind = type(value)
    if kind is tuple and len(value) == 3:
        x, y, z = value
        if type(x) is float and type(y) is float and type(z) is float:
            return value
    elif kind is np.ndarray and value.shape == (3,):
        return value.tolist()
    return vector3(value, name).tolist()


@inplace_kernel
def step_into_row(
    s: StateRecord,
    c: CoefficientsRecord,
    out: np.ndarray,
    t: float,
    gx: float,
    gy: float,
    gz: float,
    ax: float,
    ay: float,
    az: float,
    mx: float,
    my: float,
    mz: float,
    lx: float,
    ly: float,
    lz: float,
) -> None:
    """One step on a sample given as its components (the scratch ``w_online_sample`` holds
    them as the step's vectors); the estimate after it into ``out`` (ROW_WIDTH,)."""
    sample = s.w_online_sample
    sample[0] = gx
    sample[1] = gy
    sample[2] = gz
    sample[3] = ax
    sample[4] = ay
    sample[5] = az
    sample[6] = mx
    sample[7] = my
    sample[8] = mz
    sample[9] = lx
    sample[10] = ly
    sample[11] = lz
    step(s, c, t, sample[:3], sample[3:6], sample[6:9], sample[9:])
    report_attitude_into(s, c, sample[:3], out[ROW_Q : ROW_Q + 4])
    copy_into(out[ROW_BIAS : ROW_BIAS + 3], s.b)
    # The Euler angles are made from q when first read (:func:`euler_of_row`): three
    # atan2 and a hypot, 5 % of an online step that a caller reading q, as a filter
    # user mostly does, does not need. NaN until then.
    for i in range(3):
        out[ROW_EULER + i] = math.nan
    copy_into(out[ROW_INNOVATION : ROW_INNOVATION + 2], s.innovation)
    for i in range(N_ERROR):
        for j in range(N_ERROR):
            out[ROW_COV + N_ERROR * i + j] = s.P[i, j]
    if c.alignment_var != 0.0:  # (the row's 6×6 view only then: it costs 5 % of a step)
        add_reported_alignment(
            s, c, out[ROW_COV : ROW_COV + N_ERROR * N_ERROR].reshape((N_ERROR, N_ERROR))
        )
    out[ROW_T] = t  # (the sample's time, whatever the step did: update_batch's too)
    out[ROW_NIS] = s.nis
    out[ROW_ACCEL_USED] = 1.0 if s.accel_used != 0 else 0.0
    out[ROW_FLAGS] = s.flags
    out[ROW_ITERATIONS] = s.iterations
    out[ROW_AT_REST] = 1.0 if s.at_rest != 0 else 0.0
    out[ROW_HEADING_INNOVATION] = s.heading_innovation
    out[ROW_HEADING_NIS] = s.heading_nis
    out[ROW_MAG_USED] = 1.0 if s.mag_used != 0 else 0.0


@inplace_kernel
def euler_of_row(row: np.ndarray) -> None:
    """A row's Euler angles from its quaternion, if they are not there yet (NaN)."""
    if math.isnan(row[ROW_EULER]):
        so3.euler_zyx_from_quat_into(row[ROW_Q : ROW_Q + 4], row[ROW_EULER : ROW_EULER + 3])


@callback_kernel(types.void(types.CPointer(types.float64)))
def euler_callback(row: np.ndarray) -> None:
    """:func:`euler_of_row` as a C function: ``row`` points at the ROW_WIDTH doubles."""
    euler_of_row(numba.carray(row, ROW_WIDTH))


_SAMPLE_ARGUMENTS = (types.float64,) * 13  # t, then gyro, accel, mag, linear_accel


@callback_kernel(
    types.void(
        types.CPointer(numba.from_dtype(STATE_DTYPE)),
        types.CPointer(numba.from_dtype(COEFFICIENTS_DTYPE)),
        types.CPointer(types.float64),
        *_SAMPLE_ARGUMENTS,
    )
)
def step_callback(
    state: np.ndarray,
    coefficients: np.ndarray,
    row: np.ndarray,
    t: float,
    gx: float,
    gy: float,
    gz: float,
    ax: float,
    ay: float,
    az: float,
    mx: float,
    my: float,
    mz: float,
    lx: float,
    ly: float,
    lz: float,
) -> None:
    """:func:`step_into_row` as a C function: ``state`` and ``coefficients`` point at the
    records, ``row`` at the ROW_WIDTH doubles to fill."""
    step_into_row(
        numba.carray(state, 1)[0],
        numba.carray(coefficients, 1)[0],
        numba.carray(row, ROW_WIDTH),
        t,
        gx,
        gy,
        gz,
        ax,
        ay,
        az,
        mx,
        my,
        mz,
        lx,
        ly,
        lz,
    )


@kernel
def _step_row(
    state: np.ndarray,
    coefficients: np.ndarray,
    block: np.ndarray,
    row: int,
    t: float,
    gx: float,
    gy: float,
    gz: float,
    ax: float,
    ay: float,
    az: float,
    mx: float,
    my: float,
    mz: float,
    lx: float,
    ly: float,
    lz: float,
) -> None:
    """:func:`step_into_row` on ``block[row]``, for numba's entry point (the sample as
    scalars, which cross into numba far faster than arrays)."""
    step_into_row(
        state[0], coefficients[0], block[row], t, gx, gy, gz, ax, ay, az, mx, my, mz, lx, ly, lz
    )


_STEP_ENTRY_POINTS: dict[tuple[np.dtype, np.dtype], Callable[..., None]] = {}


def _step_entry_point(state: np.ndarray, coefficients: np.ndarray) -> Callable[..., None]:
    """The compiled :func:`_step_row` for these record types without numba's per-call
    type dispatch; resolved once per process (loading it takes milliseconds)."""
    key = (state.dtype, coefficients.dtype)
    found = _STEP_ENTRY_POINTS.get(key)
    if found is None:
        example = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8, *UNKNOWN3, *UNKNOWN3)
        block = np.empty((1, ROW_WIDTH))
        found = without_dispatch(_step_row, state.copy(), coefficients, block, 0, *example)
        _STEP_ENTRY_POINTS[key] = found
    return found


def row_of(
    t: float,
    q: ArrayLike,
    bias: ArrayLike,
    cov: ArrayLike,
    innovation: ArrayLike,
    nis: float,
    accel_used: bool,
    flags: int,
    iterations: int,
    at_rest: bool,
    heading_innovation: float,
    heading_nis: float,
    mag_used: bool,
) -> np.ndarray:
    """An estimate's fields as a row (ROW_WIDTH,), as the step writes it, but with its
    Euler angles made now: a batch-fed replay reads those of its lone samples, and
    making them at the first read would load the extension's C callback, which needs
    numba's runtime, which a replay otherwise never initialises (20 ms)."""
    row = np.empty(ROW_WIDTH)
    row[ROW_Q : ROW_Q + 4] = q
    row[ROW_BIAS : ROW_BIAS + 3] = bias
    so3.euler_zyx_from_quat_into(row[ROW_Q : ROW_Q + 4], row[ROW_EULER : ROW_EULER + 3])
    row[ROW_INNOVATION : ROW_INNOVATION + 2] = innovation
    row[ROW_COV : ROW_COV + N_ERROR * N_ERROR] = np.asarray(cov, dtype=np.float64).reshape(-1)
    row[ROW_T] = float(t)
    row[ROW_NIS] = float(nis)
    row[ROW_ACCEL_USED] = bool(accel_used)
    row[ROW_FLAGS] = int(flags)
    row[ROW_ITERATIONS] = int(iterations)
    row[ROW_AT_REST] = bool(at_rest)
    row[ROW_HEADING_INNOVATION] = float(heading_innovation)
    row[ROW_HEADING_NIS] = float(heading_nis)
    row[ROW_MAG_USED] = bool(mag_used)
    return row


_Q = slice(ROW_Q, ROW_Q + 4)
_BIAS = slice(ROW_BIAS, ROW_BIAS + 3)
_EULER = slice(ROW_EULER, ROW_EULER + 3)
_INNOVATION = slice(ROW_INNOVATION, ROW_INNOVATION + 2)
_COV = slice(ROW_COV, ROW_COV + N_ERROR * N_ERROR)


class Estimate:
    """The estimate after one sample, with what the step did.

    The live service makes one per IMU sample, so it is lean: it holds the row of
    an output block that the compiled step filled (``ROW_*`` in
    :mod:`mavest.estimator.layout`); its arrays are views of that row. No later
    step writes the row, so an estimate kept stays as it was made. (The extension
    ``_online`` has this class's twin, reading the row in C.)
    """

    __slots__ = ("_row",)

    def __init__(self, row: np.ndarray) -> None:
        self._row = row  # (ROW_WIDTH,), written again only to fill in the Euler angles

    @classmethod
    def of(
        cls,
        t: float,
        q: ArrayLike,
        bias: ArrayLike,
        cov: ArrayLike,
        innovation: ArrayLike,
        nis: float,
        accel_used: bool,
        flags: int,
        iterations: int,
        at_rest: bool,
        heading_innovation: float,
        heading_nis: float,
        mag_used: bool,
    ) -> Estimate:
        """An estimate from its fields (e.g. one row of an :class:`EstimateSeries`)."""
        return cls(
            row_of(
                t,
                q,
                bias,
                cov,
                innovation,
                nis,
                accel_used,
                flags,
                iterations,
                at_rest,
                heading_innovation,
                heading_nis,
                mag_used,
            )
        )

    @property
    def t(self) -> float:
        """Time of the sample (s)."""
        return float(self._row[ROW_T])

    @property
    def q(self) -> np.ndarray:
        """(4,) w, x, y, z; body → NED."""
        return self._row[_Q]

    @property
    def bias(self) -> np.ndarray:
        """(3,) gyro bias, rad/s."""
        return self._row[_BIAS]

    @property
    def cov(self) -> np.ndarray:
        """(6, 6) covariance of [δθ, δb]."""
        return self._row[_COV].reshape(N_ERROR, N_ERROR)

    @property
    def innovation(self) -> np.ndarray:
        """(2,) gravity residual before the update, rad (between updates: the last update's)."""
        return self._row[_INNOVATION]

    @property
    def nis(self) -> float:
        """Normalised innovation squared (χ², 2 dof); NaN if no measurement (between
        updates: the last update's)."""
        return float(self._row[ROW_NIS])

    @property
    def accel_used(self) -> bool:
        """This sample's accelerometer was a gravity update (or set tilt)."""
        return bool(self._row[ROW_ACCEL_USED])

    @property
    def flags(self) -> int:
        """:class:`StepFlags` bits."""
        return int(self._row[ROW_FLAGS])

    @property
    def iterations(self) -> int:
        return int(self._row[ROW_ITERATIONS])

    @property
    def at_rest(self) -> bool:
        """Rest detected: the bias got a zero-rate update."""
        return bool(self._row[ROW_AT_REST])

    @property
    def heading_innovation(self) -> float:
        """Magnetometer azimuth − declination, rad; NaN if none (between the magnetometer's
        updates: the last one's)."""
        return float(self._row[ROW_HEADING_INNOVATION])

    @property
    def heading_nis(self) -> float:
        """Its normalised square (χ², 1 dof)."""
        return float(self._row[ROW_HEADING_NIS])

    @property
    def mag_used(self) -> bool:
        """The magnetometer corrected (or set) heading."""
        return bool(self._row[ROW_MAG_USED])

    @property
    def euler(self) -> np.ndarray:
        """(roll, pitch, yaw) in rad, ZYX as MAVLink's ATTITUDE (made when first read)."""
        row = self._row
        if math.isnan(row[ROW_EULER]):
            euler_of_row(row)
        return row[_EULER]

    @property
    def status(self) -> list[str]:
        """Names of the flags set, e.g. ``["ACCEL_DISTURBED"]``."""
        return StepFlags.describe(self.flags)

    def __repr__(self) -> str:
        return (
            f"Estimate(t={self.t!r}, q={self.q.tolist()!r}, bias={self.bias.tolist()!r},"
            f" nis={self.nis!r}, status={self.status!r})"
        )


class PythonOnline:
    """The online step without the extension: the inputs converted in Python, the step
    through numba's entry point, :class:`Estimate` out. (``_online.Online`` is the
    compiled twin; :class:`~mavest.estimator.Estimator` binds one of the two.)"""

    def __init__(self, state: np.ndarray, coefficients: np.ndarray) -> None:
        self._coefficients = coefficients
        self._step = _step_entry_point(state, coefficients)
        self.bind(state)

    def bind(self, state: np.ndarray) -> None:
        """Step this state record from now on, into a fresh output block."""
        self._state = state
        self._block = np.empty((BLOCK_ROWS, ROW_WIDTH))  # rows the next estimates take
        self._next_row = 0

    def update(
        self,
        t: float,
        gyro: ArrayLike,
        accel: ArrayLike,
        mag: ArrayLike | None = None,
        linear_accel: ArrayLike | None = None,
    ) -> Estimate:
        """:meth:`Estimator.update <mavest.estimator.Estimator.update>`."""
        m = UNKNOWN3 if mag is None else components3(mag, "mag")
        a = UNKNOWN3 if linear_accel is None else components3(linear_accel, "linear_accel")
        t = float(t)
        g = components3(gyro, "gyro")
        f = components3(accel, "accel")
        row = self._next_row
        if row == BLOCK_ROWS:  # the estimates made from the full block keep it alive
            self._block = np.empty((BLOCK_ROWS, ROW_WIDTH))
            row = 0
        self._next_row = row + 1
        block = self._block
        self._step(self._state, self._coefficients, block, row, t, *g, *f, *m, *a)
        if int(block[row, ROW_FLAGS]) & ACCEL_WRONG_UNIT:
            warn_accel_unit(self._state, stacklevel=2)
        return Estimate(block[row])


def compiled() -> ModuleType | None:
    """The extension ``_online`` if it can be used: built (it is optional), built from
    the ``_online.pyx`` beside it when that is there (a development tree whose build
    is older than its source would run old code), and numba compiling."""
    if not step_callback.available:
        return None
    try:
        from mavest.estimator import _online
    except ImportError:
        return None
    source = Path(__file__).with_name("_online.pyx")
    if source.is_file():
        digest = hashlib.sha256(source.read_bytes()).hexdigest()
        if digest != _online.SOURCE_DIGEST:
            warnings.warn(
                f"{_online.__file__} was built from another {source.name}: the Python path"
                " runs instead (rebuild it with pip install -e .)",
                RuntimeWarning,
                stacklevel=2,
            )
            return None
    return _online
