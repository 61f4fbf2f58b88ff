# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False
"""The online step, compiled: ``Online.update`` and its ``Estimate``.

Twins of :class:`mavest.estimator.online.PythonOnline` and
:class:`mavest.estimator.online.Estimate`, with the same behaviour and results bit for
bit, minus the Python objects on the way: the sample's vectors are read from their
memory (a tuple of three floats, a list of three floats, or a float64 array of three,
any stride) into C doubles, the filter step is called as a C function
(``online.step_callback``) that writes the whole estimate into a row of the output
block, and the Estimate reads that row in C when asked. Any other input takes
``online.components3``, the Python path's own conversion, so errors read the same.

``mavest.estimator.online.compiled`` decides whether this module is used.
"""

cimport cython
cimport numpy as cnp
from cpython.float cimport PyFloat_AS_DOUBLE, PyFloat_CheckExact
from cpython.list cimport PyList_GET_ITEM, PyList_GET_SIZE
from cpython.number cimport PyNumber_Float
from cpython.object cimport PyObject
from cpython.tuple cimport PyTuple_GET_ITEM, PyTuple_GET_SIZE
from libc.math cimport NAN
from libc.stdint cimport uintptr_t

import numpy as np

from mavest.estimator import layout, online

cnp.import_array()

cdef extern from *:
    """
    #ifndef MAVEST_ONLINE_SOURCE_DIGEST
    #define MAVEST_ONLINE_SOURCE_DIGEST ""
    #endif
    """
    const char* MAVEST_ONLINE_SOURCE_DIGEST

# SHA-256 of the _online.pyx this was built from (setup.py passes it): a build older than
# the source is not used.
SOURCE_DIGEST = MAVEST_ONLINE_SOURCE_DIGEST.decode("ascii")

# online.step_callback's C signature: the state record, the coefficients record, the
# row to fill, then t and the sample's twelve components.
ctypedef void (*StepFunction)(
    void*, void*, double*,
    double,
    double, double, double,
    double, double, double,
    double, double, double,
    double, double, double,
) noexcept nogil

# online.euler_callback's: the row whose Euler angles to fill in (if not there yet).
ctypedef void (*EulerFunction)(double*) noexcept nogil

cdef Py_ssize_t ROW_Q = layout.ROW_Q
cdef Py_ssize_t ROW_BIAS = layout.ROW_BIAS
cdef Py_ssize_t ROW_EULER = layout.ROW_EULER
cdef Py_ssize_t ROW_INNOVATION = layout.ROW_INNOVATION
cdef Py_ssize_t ROW_COV = layout.ROW_COV
cdef Py_ssize_t ROW_T = layout.ROW_T
cdef Py_ssize_t ROW_NIS = layout.ROW_NIS
cdef Py_ssize_t ROW_ACCEL_USED = layout.ROW_ACCEL_USED
cdef Py_ssize_t ROW_FLAGS = layout.ROW_FLAGS
cdef Py_ssize_t ROW_ITERATIONS = layout.ROW_ITERATIONS
cdef Py_ssize_t ROW_AT_REST = layout.ROW_AT_REST
cdef Py_ssize_t ROW_HEADING_INNOVATION = layout.ROW_HEADING_INNOVATION
cdef Py_ssize_t ROW_HEADING_NIS = layout.ROW_HEADING_NIS
cdef Py_ssize_t ROW_MAG_USED = layout.ROW_MAG_USED
cdef Py_ssize_t ROW_WIDTH = layout.ROW_WIDTH
cdef Py_ssize_t BLOCK_ROWS = online.BLOCK_ROWS
cdef cnp.npy_intp N_ERROR = layout.N_ERROR

cdef long long ACCEL_WRONG_UNIT = online.ACCEL_WRONG_UNIT

cdef object _components3 = online.components3
cdef object _warn_accel_unit = online.warn_accel_unit
cdef object _row_of = online.row_of
cdef object _describe = layout.StepFlags.describe
cdef object _STATE_DTYPE = layout.STATE_DTYPE
cdef object _COEFFICIENTS_DTYPE = layout.COEFFICIENTS_DTYPE
cdef type _FLOAT64 = np.float64

# What an Estimate not made by a step reads (one made with Estimate.__new__): NaN.
cdef cnp.ndarray _NAN_ROW = np.full(ROW_WIDTH, np.nan)


cdef EulerFunction _euler_of_row = NULL  # loaded when an estimate's angles are first read


cdef int _fill_euler(double* row) except -1:
    """The row's Euler angles from its quaternion, which the step leaves to the first
    reader (``online.step_into_row``)."""
    global _euler_of_row
    if _euler_of_row == NULL:
        _euler_of_row = <EulerFunction><uintptr_t>online.euler_callback.address
    _euler_of_row(row)
    return 0


cdef inline cnp.ndarray _view(Estimate estimate, Py_ssize_t offset, int nd, cnp.npy_intp* shape):
    """A view of part of the estimate's row (writable, as the Python path's slices are),
    keeping the row's block alive."""
    cdef cnp.ndarray array = cnp.PyArray_SimpleNewFromData(
        nd, shape, cnp.NPY_FLOAT64, estimate._row + offset
    )
    cnp.set_array_base(array, estimate._block)
    return array


cdef cnp.npy_intp[1] _FOUR = [4]
cdef cnp.npy_intp[1] _THREE = [3]
cdef cnp.npy_intp[1] _TWO = [2]
cdef cnp.npy_intp[2] _COV_SHAPE = [N_ERROR, N_ERROR]


# no_gc: an Estimate refers to a float64 array only, so it is never part of a cycle
# (and making one per sample then does not drive the collector).
@cython.final
@cython.no_gc
@cython.freelist(16)
cdef class Estimate:
    """The estimate after one sample, with what the step did.

    The live service makes one per IMU sample, so it is lean: it holds the row of
    an output block that the compiled step filled (``ROW_*`` in
    :mod:`mavest.estimator.layout`) and reads it when asked; its arrays are views of
    that row. No later step writes the row, so an estimate kept stays as it was made
    (its Euler angles are filled in when first read).
    """

    cdef cnp.ndarray _block  # holds the row: kept alive by this estimate
    cdef double* _row

    def __cinit__(self):
        self._block = _NAN_ROW
        self._row = <double*>cnp.PyArray_DATA(_NAN_ROW)

    def __init__(self, *args, **kwargs):
        raise TypeError("an Estimate comes from Estimator.update, or Estimate.of(...)")

    @classmethod
    def of(
        cls,
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
    ):
        """An estimate from its fields (e.g. one row of an :class:`EstimateSeries`)."""
        return _estimate_of_row(
            _row_of(
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

    def __reduce__(self):
        cdef cnp.npy_intp width = ROW_WIDTH
        row = cnp.PyArray_SimpleNewFromData(1, &width, cnp.NPY_FLOAT64, self._row)
        return (_estimate_of_row, (row.copy(),))

    @property
    def t(self):
        """Time of the sample (s)."""
        return self._row[ROW_T]

    @property
    def q(self):
        """(4,) w, x, y, z; body → NED."""
        return _view(self, ROW_Q, 1, _FOUR)

    @property
    def bias(self):
        """(3,) gyro bias, rad/s."""
        return _view(self, ROW_BIAS, 1, _THREE)

    @property
    def cov(self):
        """(6, 6) covariance of [δθ, δb]."""
        return _view(self, ROW_COV, 2, _COV_SHAPE)

    @property
    def innovation(self):
        """(2,) gravity residual before the update, rad (between updates: the last update's)."""
        return _view(self, ROW_INNOVATION, 1, _TWO)

    @property
    def nis(self):
        """Normalised innovation squared (χ², 2 dof); NaN if no measurement (between
        updates: the last update's)."""
        return self._row[ROW_NIS]

    @property
    def accel_used(self):
        """This sample's accelerometer was a gravity update (or set tilt)."""
        return self._row[ROW_ACCEL_USED] != 0.0

    @property
    def flags(self):
        """:class:`StepFlags` bits."""
        return <long long>self._row[ROW_FLAGS]

    @property
    def iterations(self):
        return <long long>self._row[ROW_ITERATIONS]

    @property
    def at_rest(self):
        """Rest detected: the bias got a zero-rate update."""
        return self._row[ROW_AT_REST] != 0.0

    @property
    def heading_innovation(self):
        """Magnetometer azimuth − declination, rad; NaN if none (between the magnetometer's
        updates: the last one's)."""
        return self._row[ROW_HEADING_INNOVATION]

    @property
    def heading_nis(self):
        """Its normalised square (χ², 1 dof)."""
        return self._row[ROW_HEADING_NIS]

    @property
    def mag_used(self):
        """The magnetometer corrected (or set) heading."""
        return self._row[ROW_MAG_USED] != 0.0

    @property
    def euler(self):
        """(roll, pitch, yaw) in rad, ZYX as MAVLink's ATTITUDE (made when first read)."""
        if self._row[ROW_EULER] != self._row[ROW_EULER]:  # NaN: not yet
            _fill_euler(self._row)
        return _view(self, ROW_EULER, 1, _THREE)

    @property
    def status(self):
        """Names of the flags set, e.g. ``["ACCEL_DISTURBED"]``."""
        return _describe(self.flags)

    def __repr__(self):
        return (
            f"Estimate(t={self.t!r}, q={self.q.tolist()!r}, bias={self.bias.tolist()!r},"
            f" nis={self.nis!r}, status={self.status!r})"
        )


def _estimate_of_row(row):
    """An Estimate of a row (ROW_WIDTH,) of float64 (Estimate.of's, or a pickled one's)."""
    block = np.ascontiguousarray(row, dtype=np.float64)
    if block.shape != (ROW_WIDTH,):
        raise ValueError(f"an estimate's row has {ROW_WIDTH} values, got shape {block.shape}")
    cdef Estimate estimate = Estimate.__new__(Estimate)
    estimate._block = block
    estimate._row = <double*>cnp.PyArray_DATA(block)
    return estimate


cdef inline bint _floats3(PyObject* x, PyObject* y, PyObject* z, double* out) noexcept:
    """Whether all three are Python floats (exactly); if so, their values into ``out``."""
    if PyFloat_CheckExact(<object>x) and PyFloat_CheckExact(<object>y) and PyFloat_CheckExact(<object>z):
        out[0] = PyFloat_AS_DOUBLE(<object>x)
        out[1] = PyFloat_AS_DOUBLE(<object>y)
        out[2] = PyFloat_AS_DOUBLE(<object>z)
        return True
    return False


cdef int _read3(object value, str name, double* out) except -1:
    """A vector's three components into ``out``, as the Python path reads them: a float64
    array of three or a tuple or list of three floats directly, anything else through
    ``online.components3`` (and PyNumber_Float, as numba's unboxing takes a float)."""
    cdef cnp.ndarray array
    cdef char* data
    cdef cnp.npy_intp stride
    cdef type kind = type(value)
    if kind is cnp.ndarray:
        array = <cnp.ndarray>value
        if (
            cnp.PyArray_NDIM(array) == 1
            and cnp.PyArray_DIM(array, 0) == 3
            and cnp.PyArray_TYPE(array) == cnp.NPY_FLOAT64
            and cnp.PyArray_ISBEHAVED_RO(array)
        ):
            data = cnp.PyArray_BYTES(array)
            stride = cnp.PyArray_STRIDE(array, 0)
            out[0] = (<double*>data)[0]
            out[1] = (<double*>(data + stride))[0]
            out[2] = (<double*>(data + 2 * stride))[0]
            return 0
    elif kind is tuple:
        if PyTuple_GET_SIZE(value) == 3 and _floats3(
            PyTuple_GET_ITEM(value, 0), PyTuple_GET_ITEM(value, 1), PyTuple_GET_ITEM(value, 2), out
        ):
            return 0
    elif kind is list:
        if PyList_GET_SIZE(value) == 3 and _floats3(
            PyList_GET_ITEM(value, 0), PyList_GET_ITEM(value, 1), PyList_GET_ITEM(value, 2), out
        ):
            return 0
    x, y, z = _components3(value, name)
    out[0] = PyFloat_AS_DOUBLE(PyNumber_Float(x))
    out[1] = PyFloat_AS_DOUBLE(PyNumber_Float(y))
    out[2] = PyFloat_AS_DOUBLE(PyNumber_Float(z))
    return 0


cdef int _check_record(object record, object dtype, str name) except -1:
    """The step reads and writes the record through a pointer: it must be exactly one
    record of the layout the step was compiled for, in memory the step may write."""
    if (
        type(record) is not cnp.ndarray
        or record.dtype != dtype
        or record.shape != (1,)
        or not cnp.PyArray_ISCARRAY(<cnp.ndarray>record)
    ):
        raise TypeError(f"{name} must be a writable (1,) array of its layout's dtype")
    return 0


cdef class Online:
    """The online step: ``update`` takes a sample and returns the :class:`Estimate`
    after it, stepping the state record it is bound to."""

    cdef cnp.ndarray _state
    cdef cnp.ndarray _coefficients
    cdef cnp.ndarray _block  # the output block the next estimates take rows of
    cdef Py_ssize_t _next_row
    cdef StepFunction _step

    def __init__(self, state, coefficients):
        _check_record(coefficients, _COEFFICIENTS_DTYPE, "coefficients")
        self._coefficients = coefficients
        self._step = <StepFunction><uintptr_t>online.step_callback.address
        self.bind(state)

    def bind(self, state):
        """Step this state record from now on, into a fresh output block."""
        _check_record(state, _STATE_DTYPE, "state")
        self._state = state
        self._new_block()

    cdef int _new_block(self) except -1:
        cdef cnp.npy_intp[2] shape = [BLOCK_ROWS, ROW_WIDTH]
        self._block = cnp.PyArray_EMPTY(2, shape, cnp.NPY_FLOAT64, 0)
        self._next_row = 0
        return 0

    def __reduce__(self):
        # for copy.deepcopy(estimator): the copy steps a copy of the state
        return (Online, (self._state, self._coefficients))

    def update(self, t, gyro, accel, mag=None, linear_accel=None):
        """:meth:`Estimator.update <mavest.estimator.Estimator.update>`."""
        cdef double sample[12]  # gyro, accel, mag, linear_accel
        cdef double time
        cdef Py_ssize_t row
        cdef double* out
        cdef Estimate estimate
        # read in the Python path's order, so that a call with two bad inputs says the same
        if mag is None:
            sample[6] = sample[7] = sample[8] = NAN
        else:
            _read3(mag, "mag", sample + 6)
        if linear_accel is None:
            sample[9] = sample[10] = sample[11] = NAN
        else:
            _read3(linear_accel, "linear_accel", sample + 9)
        if PyFloat_CheckExact(t) or type(t) is _FLOAT64:  # np.float64 is a float
            time = PyFloat_AS_DOUBLE(t)
        else:
            time = PyFloat_AS_DOUBLE(PyNumber_Float(t))
        _read3(gyro, "gyro", sample)
        _read3(accel, "accel", sample + 3)
        row = self._next_row
        if row == BLOCK_ROWS:  # the estimates made from the full block keep it alive
            self._new_block()
            row = 0
        self._next_row = row + 1
        out = <double*>cnp.PyArray_DATA(self._block) + row * ROW_WIDTH
        self._step(
            cnp.PyArray_DATA(self._state),
            cnp.PyArray_DATA(self._coefficients),
            out,
            time,
            sample[0], sample[1], sample[2],
            sample[3], sample[4], sample[5],
            sample[6], sample[7], sample[8],
            sample[9], sample[10], sample[11],
        )
        if (<long long>out[ROW_FLAGS]) & ACCEL_WRONG_UNIT:
            _warn_accel_unit(self._state, 1)  # (no frame of ours: 1 is the caller's)
        estimate = Estimate.__new__(Estimate)
        estimate._block = self._block
        estimate._row = out
        return estimate
