"""Estimates into a Rerun recording (.rrd), logged in column batches.

One ``log()`` call per sample per entity costs more than the filter step at
1 kHz; rows are buffered and sent with ``send_columns`` every ``batch`` rows
(and when the recording closes), on the vehicle's clock.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

TIMELINE = "vehicle_time"


class RerunRecorder:
    """An estimate sink that writes roll/pitch/yaw (ours, autopilot's, truth) and 3σ tilt."""

    def __init__(self, path: str | Path, batch: int = 4096, application: str = "mavest") -> None:
        self.path = Path(path)
        self.batch = batch
        self.recording = rr.RecordingStream(application)
        self.recording.save(str(self.path))
        self._rows: dict[str, tuple[list[float], list[float]]] = defaultdict(lambda: ([], []))
        self.rows_written = 0

    def _add(self, entity: str, t: float, value: float) -> None:
        times, values = self._rows[entity]
        times.append(t)
        values.append(value)
        if len(times) >= self.batch:
            self._flush_entity(entity)

    @staticmethod
    def _prefix(stream: Any) -> str:
        key = stream.key
        return f"vehicle_{key.system}_{key.component}/{key.message.lower()}_{key.instance}"

    def on_estimate(self, stream: Any, sample: Any, estimate: Any) -> None:
        prefix = self._prefix(stream)
        t = estimate.t
        euler = estimate.euler
        for axis, value in zip(("roll", "pitch", "yaw"), euler, strict=True):
            self._add(f"{prefix}/attitude/{axis}/mavest", t, math.degrees(value))
        cov = estimate.cov
        self._add(
            f"{prefix}/tilt_sigma_3x",
            t,
            3.0 * math.degrees(math.sqrt(max(0.5 * (cov[0, 0] + cov[1, 1]), 0.0))),
        )
        if estimate.nis == estimate.nis:  # NaN when no accelerometer update
            self._add(f"{prefix}/nis", t, float(estimate.nis))

    def on_reference(self, stream: Any, source: str, t: float, euler: tuple) -> None:
        prefix = self._prefix(stream)
        for axis, value in zip(("roll", "pitch", "yaw"), euler, strict=True):
            self._add(f"{prefix}/attitude/{axis}/{source}", t, math.degrees(value))

    def _flush_entity(self, entity: str) -> None:
        times, values = self._rows[entity]
        if not times:
            return
        rr.send_columns(
            entity,
            indexes=[rr.TimeColumn(TIMELINE, duration=np.asarray(times))],
            columns=rr.Scalars.columns(scalars=np.asarray(values)),
            recording=self.recording,
        )
        self.rows_written += len(times)
        times.clear()
        values.clear()

    def flush(self) -> None:
        for entity in list(self._rows):
            self._flush_entity(entity)
        self.recording.flush()

    def close(self) -> None:
        self.flush()
        self.recording.disconnect()
