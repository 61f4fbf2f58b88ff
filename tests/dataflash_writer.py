"""Writes DataFlash logs for the tests: FMT records, then records of the formats defined
(ArduPilot's format letters, little-endian, each record after the two header bytes and
its type)."""

from __future__ import annotations

import struct
from pathlib import Path

HEADER = b"\xa3\x95"
STRUCT = {
    "b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d",
    "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I",
    "L": "i", "M": "B", "q": "q", "Q": "Q",
}  # fmt: skip


class DataflashWriter:
    """Builds a DataFlash log: FMT records, then records of the formats defined."""

    def __init__(self) -> None:
        self.out = bytearray()
        self.formats: dict[str, tuple[int, str]] = {}
        self.define(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")

    def define(self, kind: int, name: str, fmt: str, columns: str) -> None:
        length = 3 + struct.calcsize("<" + "".join(STRUCT[c] for c in fmt))
        self.formats[name] = (kind, fmt)
        self.out += (
            HEADER
            + bytes([128])
            + struct.pack(
                "<BB4s16s64s", kind, length, name.encode(), fmt.encode(), columns.encode()
            )
        )

    def record(self, name: str, *values: object) -> bytes:
        kind, fmt = self.formats[name]
        values = tuple(v.encode() if isinstance(v, str) else v for v in values)
        packed = (
            HEADER + bytes([kind]) + struct.pack("<" + "".join(STRUCT[c] for c in fmt), *values)
        )
        self.out += packed
        return packed

    def save(self, path: Path) -> Path:
        path.write_bytes(bytes(self.out))
        return path
