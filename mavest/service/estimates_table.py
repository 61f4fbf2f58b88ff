"""The estimates as a table: one row per estimated IMU sample, in CSV or Parquet.

``mavest replay LOG --estimates FILE.csv`` (or ``FILE.parquet``; ``mavest run`` too)
writes what the filter estimated for every sample it took, for pandas, polars or
DuckDB. The columns (:data:`COLUMNS`), in this order:

=================================================  =======  =================================
column                                             type     meaning
=================================================  =======  =================================
``system``, ``component``                          int64    the vehicle's MAVLink ids
``message``                                        string   the IMU message (``RAW_IMU``, …)
``instance``                                       int64    the IMU's instance (0 if one)
``time_s``                                         float64  the sample's vehicle time: the
                                                            log's own boot clock, s
``qw``, ``qx``, ``qy``, ``qz``                     float64  attitude, body → NED
``roll_deg``, ``pitch_deg``, ``yaw_deg``           float64  ZYX angles, as ATTITUDE has them
``sigma_roll_deg``, ``sigma_pitch_deg``,           float64  their 1σ (inf within 0.0001° of
``sigma_yaw_deg``                                           ±90° pitch: roll and yaw are one)
``bias_x_dps``, ``bias_y_dps``, ``bias_z_dps``     float64  gyro bias, °/s, body axes
``nis``                                            float64  the last gravity update's NIS
``accel_used``                                     bool     the accelerometer corrected tilt
``flags``                                          int64    what the step did (StepFlags)
=================================================  =======  =================================

With ``replay --smooth`` the same rows also hold the sample's smoothed estimate
(:data:`SMOOTHED_COLUMNS`, float64, after the others): ``smoothed_qw`` … ``smoothed_qz``,
``smoothed_roll_deg`` … ``smoothed_yaw_deg``, ``smoothed_sigma_roll_deg`` …
``smoothed_sigma_yaw_deg``, ``smoothed_bias_x_dps`` … ``smoothed_bias_z_dps``, as their
online namesakes are (NaN for a stream the smoother refused).

One file for all the streams a run estimates, a row each time one of them is
estimated (in the order they were): the four stream columns pick one out. In
Parquet ``message`` is dictionary-encoded (a category in pandas); in CSV
``accel_used`` is ``true``/``false`` and floats are written exactly (the shortest
text that reads back as the same number).

The file appears whole or not at all: rows are written, a block at a time (memory
stays flat however long the run), to a hidden file beside it (:func:`paths.partial_path`)
renamed at the end (with ``--smooth``, once the smoothed columns are added to its rows,
a block at a time too). A run stopped by Ctrl-C keeps the rows it has, all complete; a
run that fails on an error leaves no file. A symbolic link is written at the file it
points to; a character device or a FIFO (a FIFO made as ``table.csv``, say: the table's
name says its format) gets the whole table at the end, copied into it
(:func:`paths.publish`), and is never replaced.
Parquet needs pyarrow (``pip install 'mavest[parquet]'``), CSV nothing.
"""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import io
import itertools
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mavest.paths import OutputPathError, partial_path, publish
from mavest.so3 import euler_sigmas

log = logging.getLogger("mavest")

STREAM_COLUMNS = ("system", "component", "message", "instance")
COLUMNS: tuple[str, ...] = (
    *STREAM_COLUMNS,
    "time_s",
    "qw",
    "qx",
    "qy",
    "qz",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "sigma_roll_deg",
    "sigma_pitch_deg",
    "sigma_yaw_deg",
    "bias_x_dps",
    "bias_y_dps",
    "bias_z_dps",
    "nis",
    "accel_used",
    "flags",
)
# With replay --smooth, after COLUMNS: the smoothed estimate of the row's sample.
SMOOTHED_COLUMNS: tuple[str, ...] = tuple(
    f"smoothed_{name}"
    for name in (
        *("qw", "qx", "qy", "qz"),
        *("roll_deg", "pitch_deg", "yaw_deg"),
        *("sigma_roll_deg", "sigma_pitch_deg", "sigma_yaw_deg"),
        *("bias_x_dps", "bias_y_dps", "bias_z_dps"),
    )
)
FORMATS = {".csv": "csv", ".parquet": "parquet"}

# Rows gathered before they are written: a Parquet row group each (large enough for
# its columns to compress and scan well, ~10 MB buffered), CSV in pieces of
# _CSV_PIECE rows (the text of a piece is made at once).
BLOCK_ROWS = 32768
_CSV_PIECE = 4096


class EstimatesTableError(OutputPathError):
    """The table cannot be written as asked: not .csv or .parquet, no pyarrow, no file."""


def table_format(path: str | Path) -> str:
    """``"csv"`` or ``"parquet"``, from the file's suffix (:class:`EstimatesTableError`
    for another, or for Parquet without pyarrow)."""
    path = Path(path)
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise EstimatesTableError(f"{path}: name a .csv or a .parquet file")
    if kind == "parquet" and importlib.util.find_spec("pyarrow") is None:
        raise EstimatesTableError(
            f"{path}: Parquet needs pyarrow: pip install 'mavest[parquet]' (or write a .csv)"
        )
    return kind


# ---------------------------------------------------------------------------- the sink


class EstimatesTable:
    """An estimate sink writing one row per estimate to a CSV or Parquet file.

    A file that cannot be written any more (a full disk) stops with one line in the
    log: a CSV keeps its rows up to there, all whole; a Parquet file, whose footer
    could no longer be trusted, is not written. The run goes on without it
    (:attr:`error` says what happened).
    """

    def __init__(
        self, path: str | Path, block_rows: int | None = None, smoothing: bool = False
    ) -> None:
        """``smoothing``: the run may add smoothed columns at its end (:meth:`add_smoothed`):
        each row's stream is kept (4 bytes a row) to find its smoothed estimate."""
        self.path = Path(path)
        kind = table_format(self.path)
        block_rows = block_rows or BLOCK_ROWS
        self.rows = 0  # rows in the file
        self.error: str | None = None  # why writing stopped, if it did
        self.published = False  # the file is there under its name (or written into)
        self._temporary = partial_path(self.path)
        self._size = block_rows
        self._t = np.empty(block_rows)
        self._q = np.empty((block_rows, 4))
        self._euler = np.empty((block_rows, 3))
        self._bias = np.empty((block_rows, 3))
        self._cov = np.empty((block_rows, 3, 3))
        self._nis = np.empty(block_rows)
        self._used = np.empty(block_rows, dtype=bool)
        self._flags = np.empty(block_rows, dtype=np.int64)
        self._stream = np.empty(block_rows, dtype=np.int64)  # index into _keys
        self._n = 0  # rows buffered
        self._indices: dict[Any, int] = {}  # stream key → its index
        self._keys: list[tuple[int, int, str, int]] = []
        self._errors: list[str] = []  # each stream's error side ("left", "right")
        self._last_key: Any = None
        self._last_index = 0
        self._file: _CsvFile | _ParquetFile | None = None
        # each written row's stream (with ``smoothing``), a block at a time
        self._order: list[np.ndarray] | None = [] if smoothing else None
        # stream index → its smoothed (q, euler, sigma, bias), as add_smoothed took them
        self._smoothed: dict[int, tuple[np.ndarray, ...]] = {}
        try:
            self._file = (
                _CsvFile(self._temporary) if kind == "csv" else _ParquetFile(self._temporary)
            )
        except OSError as error:
            with contextlib.suppress(OSError):  # (a read-only folder refuses even this)
                self._temporary.unlink(missing_ok=True)
            raise EstimatesTableError(
                f"cannot write {self.path}: {error.strerror or error}"
            ) from None

    # ------------------------------------------------------------ sink interface

    def _index(self, stream: Any) -> int:
        key = stream.key
        if key is self._last_key:
            return self._last_index
        index = self._indices.get(key)
        if index is None:
            index = self._indices[key] = len(self._keys)
            self._keys.append((int(key.system), int(key.component), str(key.message), key.instance))
            self._errors.append(stream.estimator.config.error)
        self._last_key, self._last_index = key, index
        return index

    def on_estimate(
        self,
        stream: Any,
        sample: Any,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None:
        if self._file is None:
            return
        k = self._n
        self._stream[k] = self._index(stream)
        self._t[k] = estimate.t
        self._q[k] = estimate.q
        self._euler[k] = euler
        self._bias[k] = estimate.bias
        self._cov[k] = estimate.cov[:3, :3]
        self._nis[k] = estimate.nis
        self._used[k] = estimate.accel_used
        self._flags[k] = estimate.flags
        self._n = k + 1
        if self._n == self._size:
            self._write_block()

    def on_estimates(
        self,
        stream: Any,
        t: np.ndarray,
        euler: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        accel_used: np.ndarray,
        flags: np.ndarray,
        q: np.ndarray,
        series: Any,
        index: np.ndarray,
        receive_us: np.ndarray,
        processing_s: float,
    ) -> None:
        """Many estimates of one stream, in order (a replay's fast path), as
        :meth:`on_estimate` for each: the i-th is ``series[index[i]]``."""
        if self._file is None:
            return
        stream_index = self._index(stream)
        n = t.shape[0]
        done = 0
        while done < n:
            k = self._n
            take = min(n - done, self._size - k)
            part, rows = slice(done, done + take), slice(k, k + take)
            where = index[part]
            self._stream[rows] = stream_index
            self._t[rows] = t[part]
            self._q[rows] = q[part]
            self._euler[rows] = euler[part]
            self._bias[rows] = series.bias[where]
            self._cov[rows] = series.cov[where, :3, :3]
            self._nis[rows] = series.nis[where]
            self._used[rows] = accel_used[part]
            self._flags[rows] = flags[part]
            self._n = k + take
            done += take
            if self._n == self._size:
                self._write_block()

    def on_reference(
        self, stream: Any, source: str, t: float, euler: tuple, receive_us: int = 0
    ) -> None:
        """References (the autopilot's attitude, the truth) are not the table's."""

    def on_references(
        self, stream: Any, source: str, t: np.ndarray, euler: np.ndarray, receive_us: np.ndarray
    ) -> None:
        """As :meth:`on_reference`: nothing."""

    # ------------------------------------------------------------ writing

    def _columns(self) -> list[np.ndarray]:
        """The buffered rows, a column each, in :data:`COLUMNS`' order (``message``: each
        row's stream index, its name in ``_keys``)."""
        n = self._n
        stream = self._stream[:n]
        keys = np.array([(s, c, i) for s, c, _, i in self._keys], dtype=np.int64)
        q = self._q[:n]
        sigma = np.empty((n, 3))
        sides = np.array(self._errors)[stream]
        for side in sorted(set(self._errors)):
            rows = sides == side
            sigma[rows] = euler_sigmas(q[rows], self._cov[:n][rows], side)
        euler = np.degrees(self._euler[:n])
        sigma = np.degrees(sigma)
        bias = np.degrees(self._bias[:n])
        return [
            keys[stream, 0],
            keys[stream, 1],
            stream,
            keys[stream, 2],
            self._t[:n],
            *(q[:, i] for i in range(4)),
            *(euler[:, i] for i in range(3)),
            *(sigma[:, i] for i in range(3)),
            *(bias[:, i] for i in range(3)),
            self._nis[:n],
            self._used[:n],
            self._flags[:n],
        ]

    def _write_block(self) -> None:
        if self._file is None or not self._n:
            self._n = 0
            return
        columns = self._columns()
        names = [key[2] for key in self._keys]
        try:
            self.rows += self._file.write(columns, names)
        except OSError as error:
            self._stop(error)
        if self._order is not None:
            self._order.append(self._stream[: self._n].astype(np.int32))
        self._n = 0

    def add_smoothed(
        self,
        stream: Any,
        q: np.ndarray,
        euler: np.ndarray,
        sigma: np.ndarray,
        bias: np.ndarray,
    ) -> None:
        """A stream's smoothed estimates (radians, rad/s), one per row it has, in order:
        written in :data:`SMOOTHED_COLUMNS` when the table closes (a table made with
        ``smoothing``; every stream gets the columns, NaN for one not given here)."""
        if self._order is None:
            raise ValueError("a table made without smoothing takes no smoothed columns")
        self._smoothed[self._index(stream)] = (q, euler, sigma, bias)

    def _stop(self, error: OSError) -> None:
        """Write no more: a CSV keeps its whole rows, a Parquet file goes."""
        assert self._file is not None
        self.error = f"cannot write {self.path}: {error.strerror or error}"
        if isinstance(self._file, _CsvFile):
            self.rows = self._file.rows
            self._file.close_quietly()
            self._file = None
            self._publish()
            log.error(
                "%s; the table stops here with its first %d rows, whole (estimating on)",
                self.error,
                self.rows,
            )
        else:
            self.discard()
            log.error("%s; no table written (estimating on)", self.error)

    def _publish(self) -> None:
        """The file whole under its own name (written where a link points, copied into
        a device or a FIFO: :func:`paths.publish`)."""
        try:
            publish(self._temporary, self.path)
            self.published = True
        except OSError as error:
            with contextlib.suppress(OSError):
                self._temporary.unlink(missing_ok=True)
            self.error = f"cannot write {self.path}: {error.strerror or error}"
            log.error("%s; no table written", self.error)

    def close(self) -> None:
        """Write what is buffered and give the file its name (a run that ends, or is
        stopped: every row estimated is in it)."""
        if self._file is None:
            return
        self._write_block()
        file, self._file = self._file, None
        if file is None:  # writing stopped just now: done
            return
        try:
            file.close()
        except OSError as error:
            self._file = file
            self._stop(error)
            return
        if self._order is not None and self._smoothed:
            self._add_smoothed_columns(isinstance(file, _CsvFile))
        self._publish()

    def _add_smoothed_columns(self, csv_file: bool) -> None:
        """Rewrite the written table with the smoothed columns added to its rows, a block
        at a time; if that fails, the table stays as it is, without them (said)."""
        assert self._order is not None
        order = np.concatenate(self._order) if self._order else np.empty(0, np.int32)
        self._order = None
        position = np.empty(order.shape[0], dtype=np.int64)  # the row's index in its stream
        for index in range(len(self._keys)):
            rows = np.flatnonzero(order == index)
            position[rows] = np.arange(rows.shape[0])
        smoothed, self._smoothed = self._smoothed, {}

        def values(start: int, stop: int) -> np.ndarray:
            """The smoothed columns of rows [start, stop)."""
            out = np.full((stop - start, len(SMOOTHED_COLUMNS)), np.nan)
            streams, at = order[start:stop], position[start:stop]
            for index, (q, euler, sigma, bias) in smoothed.items():
                rows = np.flatnonzero((streams == index) & (at < q.shape[0]))
                taken = at[rows]
                out[rows, :4] = q[taken]
                out[rows, 4:] = np.degrees(np.hstack([euler[taken], sigma[taken], bias[taken]]))
            return out

        rewritten = partial_path(self._temporary)
        try:
            if csv_file:
                _add_csv_columns(self._temporary, rewritten, values)
            else:
                _add_parquet_columns(self._temporary, rewritten, values)
            os.replace(rewritten, self._temporary)
        except OSError as error:
            with contextlib.suppress(OSError):
                rewritten.unlink(missing_ok=True)
            log.error(
                "cannot add the smoothed columns to %s: %s; it holds the online estimates only",
                self.path,
                error.strerror or error,
            )

    def discard(self) -> None:
        """No file: the run failed (whatever is buffered or written goes)."""
        file, self._file = self._file, None
        if file is not None:
            file.close_quietly()
        with contextlib.suppress(OSError):
            self._temporary.unlink(missing_ok=True)
        self._n = 0


# the smoothed columns of a table's rows [start, stop)
_Values = Callable[[int, int], np.ndarray]


def _add_csv_columns(source: Path, target: Path, values: _Values, piece: int = _CSV_PIECE) -> None:
    """``source``'s CSV rows, each followed by its :data:`SMOOTHED_COLUMNS` (``values(start,
    stop)``: those of rows [start, stop), as an array), into ``target``."""
    with source.open("rb") as rows, target.open("wb") as out:
        header = rows.readline()
        out.write(header.rstrip(b"\n") + b"," + ",".join(SMOOTHED_COLUMNS).encode() + b"\n")
        start = 0
        while lines := list(itertools.islice(rows, piece)):
            text = io.StringIO()
            csv.writer(text, lineterminator="\n").writerows(
                values(start, start + len(lines)).tolist()
            )
            added = text.getvalue().encode().split(b"\n")
            out.write(
                b"".join(
                    line.rstrip(b"\n") + b"," + more + b"\n"
                    for line, more in zip(lines, added, strict=False)
                )
            )
            start += len(lines)


def _add_parquet_columns(source: Path, target: Path, values: _Values) -> None:
    """``source``'s Parquet row groups, each with the :data:`SMOOTHED_COLUMNS` of its rows
    (``values(start, stop)``), into ``target``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    with pq.ParquetFile(source) as table:
        schema = table.schema_arrow
        for name in SMOOTHED_COLUMNS:
            schema = schema.append(pa.field(name, pa.float64()))
        start = 0
        with pq.ParquetWriter(target, schema) as writer:
            for group in range(table.num_row_groups):
                rows = table.read_row_group(group)
                added = values(start, start + rows.num_rows)
                arrays = [*rows.columns, *(pa.array(added[:, i]) for i in range(added.shape[1]))]
                writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
                start += rows.num_rows


def csv_rows(columns: Sequence[np.ndarray], piece: int = _CSV_PIECE) -> Iterator[tuple[bytes, int]]:
    """The CSV text of these columns' rows, ``piece`` rows at a time (the text of a
    whole table at once is several times its numbers' size), with how many rows each
    holds. Each number as Python writes it, shortest and exact: a time of 1e6 s at
    1 kHz keeps its milliseconds (nine significant digits did not)."""
    n = columns[0].shape[0] if len(columns) else 0
    for start in range(0, n, piece):
        values = [column[start : start + piece] for column in columns]
        text = io.StringIO()
        csv.writer(text, lineterminator="\n").writerows(
            zip(*(column.tolist() for column in values), strict=True)
        )
        yield text.getvalue().encode(), values[0].shape[0]


class _CsvFile:
    """The CSV, written whole rows at a time; cut back to its last whole row on a failure."""

    def __init__(self, path: Path) -> None:
        # unbuffered: the buffering is ours, so that we know what reached the file
        self._file = path.open("wb", buffering=0)
        self.rows = 0  # whole rows on disk
        self._on_disk = 0  # bytes of whole rows (and the header) on disk
        self._write((",".join(COLUMNS) + "\n").encode(), 0)

    def write(self, columns: list[np.ndarray], messages: list[str]) -> int:
        """The rows of these columns (``message``: indices into ``messages``); how many."""
        at_message, at_used = COLUMNS.index("message"), COLUMNS.index("accel_used")
        values = list(columns)
        values[at_message] = np.array(messages, dtype=object)[columns[at_message]]
        values[at_used] = np.array(["false", "true"], dtype=object)[
            columns[at_used].astype(np.intp)
        ]
        for data, rows in csv_rows(values):
            self._write(data, rows)
        return columns[0].shape[0]

    def _write(self, data: bytes, rows: int) -> None:
        done = 0
        try:
            with memoryview(data) as view:
                while done < len(data):
                    done += self._file.write(view[done:]) or 0
        except OSError:
            with contextlib.suppress(OSError):  # a device (/dev/full) cannot be truncated
                self._file.truncate(self._on_disk)
            raise
        self._on_disk += done
        self.rows += rows

    def close(self) -> None:
        self._file.close()

    def close_quietly(self) -> None:
        with contextlib.suppress(OSError):
            self._file.close()


class _ParquetFile:
    """The Parquet file: a row group per block; whole only once closed (its footer)."""

    def __init__(self, path: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        self._pa = pa
        types = {"system": pa.int64(), "component": pa.int64(), "instance": pa.int64()}
        types["message"] = pa.dictionary(pa.int32(), pa.string())
        types["accel_used"] = pa.bool_()
        types["flags"] = pa.int64()
        self._schema = pa.schema([(name, types.get(name, pa.float64())) for name in COLUMNS])
        self._writer = pq.ParquetWriter(path, self._schema)

    def write(self, columns: list[np.ndarray], messages: list[str]) -> int:
        pa = self._pa
        arrays = [pa.array(column) for column in columns]
        at_message = COLUMNS.index("message")
        arrays[at_message] = pa.DictionaryArray.from_arrays(
            pa.array(columns[at_message].astype(np.int32)), pa.array(messages, pa.string())
        )
        self._writer.write_table(pa.Table.from_arrays(arrays, schema=self._schema))
        return columns[0].shape[0]

    def close(self) -> None:
        self._writer.close()

    def close_quietly(self) -> None:
        with contextlib.suppress(Exception):  # pyarrow's own errors, beside OSError
            self._writer.close()
