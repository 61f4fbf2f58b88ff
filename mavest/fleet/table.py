"""The fleet table: one row per log and IMU stream, in Parquet or CSV, written whole.

Parquet (pyarrow) has typed columns (:data:`~mavest.fleet.rows.COLUMNS`): an empty
cell is a null; an RMS with nothing to compare against is NaN. CSV (the csv module)
writes an empty cell for a null, ``nan`` for NaN, ``true``/``false``, and floats as
the shortest text that reads back as the same number, as the estimates table does.
The same rows give the same bytes. The file is written to a hidden file beside it
and renamed (:func:`mavest.paths.write_atomically`): a run stopped half-way leaves
the old table, or none.

Text is UTF-8. A log's name that is not (Linux names are bytes: ``caf\\xe9.tlog``
from a Latin-1 system) is written with each such byte as ``\\xNN``: visible, and the
name's bytes can be told from it (:func:`visible_text`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mavest.fleet.rows import COLUMN_NAMES, COLUMNS
from mavest.paths import write_atomically
from mavest.service.estimates_table import table_format


def visible_text(text: str) -> str:
    """``text`` as UTF-8 can hold it: a byte of a file name that was not UTF-8 (which
    Python keeps as a lone surrogate, ``os.fsdecode``) as ``\\xNN``; any other lone
    surrogate as ``\\udNNN``."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a surrogate that no file name's byte gave
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _visible(row: dict[str, Any]) -> dict[str, Any]:
    return {name: visible_text(v) if isinstance(v, str) else v for name, v in row.items()}


def _csv_cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return visible_text(value)
    return value


def csv_bytes(rows: Sequence[dict[str, Any]]) -> bytes:
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(COLUMN_NAMES)
    writer.writerows([_csv_cell(row[name]) for name in COLUMN_NAMES] for row in rows)
    return text.getvalue().encode()


def parquet_bytes(rows: Sequence[dict[str, Any]]) -> bytes:
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema([(name, pa.type_for_alias(kind)) for name, kind in COLUMNS])
    table = pa.Table.from_pylist([_visible(row) for row in rows], schema=schema)
    buffer = io.BytesIO()
    pq.write_table(table, buffer)
    return buffer.getvalue()


def write_table(path: str | Path, rows: Sequence[dict[str, Any]]) -> None:
    """The rows as ``path``'s format (.csv or .parquet, by its suffix), whole or not at all
    (:class:`OSError` if it cannot be written)."""
    kind = table_format(path)
    write_atomically(path, parquet_bytes(rows) if kind == "parquet" else csv_bytes(rows))
