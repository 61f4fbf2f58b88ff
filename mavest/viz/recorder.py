"""What the filter is doing, as a Rerun recording: attitude, uncertainty, bias, innovations.

Per IMU stream (root ``vehicle_<sys>_<comp>/<message>_<instance>``):

- ``attitude/{roll,pitch,yaw}/mavest`` in degrees, with ``…/mavest_3sigma``
  (two series: ±3σ from the covariance, the world-frame attitude error mapped
  through the ZYX Euler kinematics); ``…/autopilot`` and ``…/truth`` beside;
- ``error/{roll,pitch,yaw}/{vs_autopilot,vs_truth}``: ours minus theirs at
  their times (ours interpolated); references faster than ``slow_rate`` (a
  simulator's truth at the IMU rate) are plotted at ``slow_rate``;
- ``bias/{x,y,z}`` in °/s: the estimate and ±1σ (bias and bounds change
  slowly and are logged at up to ``slow_rate``, 100 Hz);
- ``imu/gyro`` (°/s), ``imu/accel`` (m/s²): what came in, x, y, z;
- ``innovation`` (°, x, y) and ``nis/value`` with ``nis/chi2_band`` (χ², 2 dof,
  the central 90 % band): one sample per ``slow_rate`` slot (each still a
  single update's, so the band stays right); ``accel`` (the fraction of the
  slot's samples whose accelerometer was used, and disturbed), so that not one
  rejection is hidden by the thinning;
- ``timing/processing_us``: decode to estimate, per sample;
- ``world/<root>/{mavest,autopilot,truth}``: the vehicle body in 3-D (NED),
  side by side, posed at up to ``pose_rate`` Hz.

Two timelines: ``vehicle_time`` (the flight controller's clock, s since boot)
and ``receive_time`` (when the sample arrived; the tlog's record time on replay).

Rows are buffered and sent with ``send_columns`` (one call per entity per
batch, never a ``log()`` per sample); what a recording costs at 1 kHz is
measured by ``tools/service_bench.py``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr

from mavest import so3
from mavest.estimator.layout import StepFlags
from mavest.evaluation.metrics import wrap_angles

VEHICLE_TIME = "vehicle_time"
RECEIVE_TIME = "receive_time"

# χ² with 2 degrees of freedom: 5 % and 95 % points (the NIS of a consistent filter
# falls between them 90 % of the time).
CHI2_2_LOW = 0.1026
CHI2_2_HIGH = 5.9915

COLORS = {
    "mavest": (31, 119, 180),
    "autopilot": (255, 127, 14),
    "truth": (44, 160, 44),
    "bound": (150, 190, 230),
}
# Where each body sits in the 3-D view (m, NED), so the three do not overlap.
BODY_OFFSETS = {"mavest": (0.0, 0.0, 0.0), "autopilot": (0.0, 3.0, 0.0), "truth": (0.0, -3.0, 0.0)}


def stream_root(key: Any) -> str:
    """The entity path under which one IMU stream's recording lives."""
    return f"vehicle_{key.system}_{key.component}/{key.message.lower()}_{key.instance}"


def euler_sigmas(euler: np.ndarray, cov_attitude: np.ndarray) -> np.ndarray:
    """(N, 3) 1σ of roll, pitch, yaw from (N, 3, 3) covariances of the world-frame error.

    A world-frame rotation δθ changes the ZYX angles by E⁻¹ δθ, where the columns
    of E are the axes each angle turns about, in the world frame:
    roll about Rz(ψ)Ry(θ)x̂, pitch about Rz(ψ)ŷ, yaw about ẑ.
    """
    roll, pitch, yaw = euler[:, 0], euler[:, 1], euler[:, 2]
    del roll
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    n = len(euler)
    E = np.zeros((n, 3, 3))
    E[:, :, 0] = np.column_stack([cy * cp, sy * cp, -sp])
    E[:, :, 1] = np.column_stack([-sy, cy, np.zeros(n)])
    E[:, 2, 2] = 1.0
    # near ±90° pitch roll and yaw are not separable: their σ is unbounded
    safe = np.abs(cp) > 1e-6
    out = np.full((n, 3), np.inf)
    if np.any(safe):
        inverse = np.linalg.inv(E[safe])
        cov = inverse @ cov_attitude[safe] @ np.transpose(inverse, (0, 2, 1))
        out[safe] = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return out


@dataclass
class _StreamBuffer:
    root: str
    # (estimate, euler, gyro, accel, receive s, processing s) per sample: kept as the
    # objects they are and turned into columns at flush, which costs far less per
    # sample than converting each one as it comes
    samples: list[tuple[Any, tuple, tuple, tuple, float, float]] = field(default_factory=list)
    references: dict[str, list[tuple[float, float, float, float, float]]] = field(
        default_factory=dict
    )  # source → (t, receive, roll, pitch, yaw)
    # our last estimate already sent: the anchor for references just after a batch
    anchor: tuple[float, float, float, float] | None = None
    last_pose_t: dict[str, float] = field(default_factory=dict)  # body → last posed time
    last_slow_t: float = -math.inf  # last sample logged at the slow rate
    last_reference_t: dict[str, float] = field(default_factory=dict)  # source → time


class RerunRecorder:
    """An estimate sink writing to a Rerun recording stream (file, viewer, or both)."""

    def __init__(
        self,
        recording: rr.RecordingStream,
        batch_rows: int = 32768,
        batch_seconds: float = 2.0,  # a live viewer wants less: see ``for_viewer``
        pose_rate: float = 50.0,
        slow_rate: float = 100.0,
    ) -> None:
        self.recording = recording
        self.batch_rows = batch_rows
        self.batch_seconds = batch_seconds
        self.pose_period = 1.0 / pose_rate
        self.slow_period = 1.0 / slow_rate
        self._streams: dict[Any, _StreamBuffer] = {}
        self._last_flush = time.monotonic()
        self.on_new_stream: list[Any] = []  # callbacks(root) when a stream appears
        self._last_key: Any = None
        self._last: _StreamBuffer | None = None

    @classmethod
    def for_viewer(cls, recording: rr.RecordingStream, live: bool) -> RerunRecorder:
        """Batches of 0.25 s for a live viewer (it should feel live), 2 s for a file only
        (bigger chunks cost less to encode)."""
        return cls(recording, batch_rows=4096, batch_seconds=0.25 if live else 2.0)

    # ------------------------------------------------------------ sink interface

    def _switch(self, stream: Any) -> _StreamBuffer:
        self._last_key = stream.key
        self._last = self._buffer(stream)
        return self._last

    def _buffer(self, stream: Any) -> _StreamBuffer:
        buffer = self._streams.get(stream.key)
        if buffer is None:
            buffer = _StreamBuffer(stream_root(stream.key))
            self._streams[stream.key] = buffer
            self._log_static(buffer.root)
            for callback in self.on_new_stream:
                callback(buffer.root)
        return buffer

    def on_estimate(
        self,
        stream: Any,
        sample: Any,
        estimate: Any,
        euler: tuple[float, float, float],
        receive_us: int,
        processing_s: float,
    ) -> None:
        buffer = self._last if stream.key is self._last_key else self._switch(stream)
        samples = buffer.samples
        samples.append(
            (estimate, euler, sample.gyro, sample.accel, receive_us * 1e-6, processing_s)
        )
        count = len(samples)
        if count >= self.batch_rows or (
            count % 64 == 0 and time.monotonic() - self._last_flush >= self.batch_seconds
        ):
            self.flush()

    def on_reference(
        self, stream: Any, source: str, t: float, euler: tuple, receive_us: int = 0
    ) -> None:
        buffer = self._buffer(stream)
        buffer.references.setdefault(source, []).append((t, receive_us * 1e-6, *euler))

    # ------------------------------------------------------------ sending

    def _log_static(self, root: str) -> None:
        """Series names and colours, and the bodies' shapes, once per stream."""
        rec = self.recording

        def style(entity: str, colors: list[tuple[int, int, int]], names: list[str]) -> None:
            rec.log(entity, rr.SeriesLines(colors=colors, names=names), static=True)

        bound = COLORS["bound"]
        for axis in ("roll", "pitch", "yaw"):
            style(f"{root}/attitude/{axis}/mavest", [COLORS["mavest"]], ["mavest"])
            style(f"{root}/attitude/{axis}/mavest_3sigma", [bound, bound], ["+3σ", "−3σ"])
            for source in ("autopilot", "truth"):
                style(f"{root}/attitude/{axis}/{source}", [COLORS[source]], [source])
                style(f"{root}/error/{axis}/vs_{source}", [COLORS[source]], [f"mavest − {source}"])
        for axis in "xyz":
            style(
                f"{root}/bias/{axis}",
                [COLORS["mavest"], bound, bound],
                [f"bias {axis}", "+1σ", "−1σ"],
            )
        xyz = [(220, 40, 40), (40, 160, 40), (40, 90, 230)]
        style(f"{root}/imu/gyro", xyz, ["x", "y", "z"])
        style(f"{root}/imu/accel", xyz, ["x", "y", "z"])
        style(f"{root}/innovation", xyz[:2], ["x", "y"])
        style(f"{root}/nis/chi2_band", [bound, bound], ["χ² 5 %", "χ² 95 %"])
        rec.log(
            f"{root}/nis/value",
            rr.SeriesPoints(colors=[COLORS["mavest"]], names=["NIS"], marker_sizes=[1.5]),
            static=True,
        )
        style(
            f"{root}/accel",
            [COLORS["truth"], COLORS["autopilot"]],
            ["fraction used", "fraction disturbed"],
        )
        style(f"{root}/timing/processing_us", [COLORS["mavest"]], ["µs per sample"])
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)  # NED

    def _log_body(self, buffer: _StreamBuffer, source: str) -> None:
        """A body in the 3-D view, the first time its source has an attitude to show."""
        rec = self.recording
        body = f"world/{buffer.root}/{source}"
        rec.log(body, rr.Transform3D(translation=BODY_OFFSETS[source]), static=True)
        rec.log(
            f"{body}/attitude/airframe",
            rr.Boxes3D(
                half_sizes=[[0.9, 0.08, 0.08], [0.12, 1.1, 0.02], [0.08, 0.35, 0.02]],
                centers=[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [-0.8, 0.0, 0.0]],
                colors=[COLORS[source]] * 3,
                fill_mode="solid",
            ),
            static=True,
        )
        rec.log(
            f"{body}/attitude/axes",
            rr.Arrows3D(
                vectors=[[1.4, 0, 0], [0, 1.4, 0], [0, 0, 1.0]],
                colors=[(220, 40, 40), (40, 160, 40), (40, 90, 230)],
                labels=["forward", "right", "down"] if source == "mavest" else None,
            ),
            static=True,
        )
        rec.log(f"{body}/label", rr.Points3D([[0, 0, -1.2]], labels=[source]), static=True)

    def _send(
        self, entity: str, times: np.ndarray, receive: np.ndarray | None, values: Any
    ) -> None:
        """One entity's rows; (N, k) values are k series of one entity."""
        values = np.asarray(values, dtype=np.float64)
        indexes = [rr.TimeColumn(VEHICLE_TIME, duration=times)]
        if receive is not None:
            indexes.append(rr.TimeColumn(RECEIVE_TIME, timestamp=receive))
        columns = rr.Scalars.columns(scalars=values.reshape(-1))
        if values.ndim == 2:
            columns = columns.partition(np.full(len(values), values.shape[1]))
        rr.send_columns(entity, indexes=indexes, columns=columns, recording=self.recording)

    def _flush_stream(self, buffer: _StreamBuffer) -> None:
        root = buffer.root
        n = len(buffer.samples)
        if n:
            estimates, eulers, gyros, accels, receives, processing = zip(
                *buffer.samples, strict=True
            )
            buffer.samples.clear()
            t = np.fromiter((e.t for e in estimates), float, n)
            rx = np.array(receives)
            euler = np.array(eulers)
            angle = np.degrees(euler)
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                self._send(f"{root}/attitude/{axis}/mavest", t, rx, angle[:, i])
            # Uncertainty and bias change slowly: at up to slow_rate, from those samples only.
            slow = _grid_samples(t, self.slow_period, buffer.last_slow_t)
            if len(slow):
                buffer.last_slow_t = t[slow[-1]]
                ts, rxs = t[slow], rx[slow]
                covariance = np.array([estimates[k].cov for k in slow])
                band = 3.0 * np.degrees(euler_sigmas(euler[slow], covariance[:, :3, :3]))
                for i, axis in enumerate(("roll", "pitch", "yaw")):
                    bounds = np.column_stack(
                        [angle[slow, i] + band[:, i], angle[slow, i] - band[:, i]]
                    )
                    self._send(f"{root}/attitude/{axis}/mavest_3sigma", ts, rxs, bounds)
                bias = np.degrees(np.array([estimates[k].bias for k in slow]))
                bias_variance = np.diagonal(covariance[:, 3:, 3:], axis1=1, axis2=2)
                bias_sigma = np.degrees(np.sqrt(np.maximum(bias_variance, 0.0)))
                for i, axis in enumerate("xyz"):
                    series = np.column_stack(
                        [bias[:, i], bias[:, i] + bias_sigma[:, i], bias[:, i] - bias_sigma[:, i]]
                    )
                    self._send(f"{root}/bias/{axis}", ts, rxs, series)
            self._send(f"{root}/imu/gyro", t, rx, np.degrees(np.array(gyros)))
            self._send(f"{root}/imu/accel", t, rx, np.array(accels))
            if len(slow):
                self._send_update(root, estimates, slow, t, rx)
            self._send(f"{root}/timing/processing_us", t, rx, 1e6 * np.array(processing))
            self._send_poses(buffer, "mavest", t, estimates)
        if n:
            buffer.anchor = (t[-1], *euler[-1])
        for source, references in buffer.references.items():
            if not references:
                continue
            everything = np.array(references)
            references.clear()
            self._send_poses(buffer, source, everything[:, 0], everything[:, 2:5])
            # a reference at the IMU rate (a simulator's truth) is plotted at up to slow_rate
            last = buffer.last_reference_t.get(source, -math.inf)
            kept = _grid_samples(everything[:, 0], self.slow_period, last)
            if not len(kept):
                continue
            data = everything[kept]
            buffer.last_reference_t[source] = data[-1, 0]
            receive = data[:, 1] if np.all(data[:, 1] > 0) else None
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                self._send(
                    f"{root}/attitude/{axis}/{source}",
                    data[:, 0],
                    receive,
                    np.degrees(data[:, 2 + i]),
                )
            if n:
                self._send_differences(buffer, source, t, euler, data)

    def _send_update(
        self, root: str, estimates: tuple, slow: np.ndarray, t: np.ndarray, rx: np.ndarray
    ) -> None:
        """The accelerometer update, per ``slow_rate`` slot (``slow``: each slot's first)."""
        ts, rxs = t[slow], rx[slow]
        innovation = np.array([estimates[k].innovation for k in slow])
        self._send(f"{root}/innovation", ts, rxs, np.degrees(innovation))
        nis = np.fromiter((estimates[k].nis for k in slow), float, len(slow))
        measured = np.isfinite(nis)
        if np.any(measured):
            self._send(f"{root}/nis/value", ts[measured], rxs[measured], nis[measured])
        ends = [0, len(slow) - 1] if len(slow) > 1 else [0]  # a constant band: its ends
        self._send(
            f"{root}/nis/chi2_band",
            ts[ends],
            rxs[ends],
            np.tile([CHI2_2_LOW, CHI2_2_HIGH], (len(ends), 1)),
        )
        n = len(estimates)
        used = np.fromiter((e.accel_used for e in estimates), float, n)
        flags = np.fromiter((e.flags for e in estimates), np.int64, n)
        disturbed = ((flags & StepFlags.ACCEL_DISTURBED) != 0).astype(float)
        # fractions per slot; the first slot may have begun in the previous batch
        counts = np.diff(np.append(slow, n))
        fractions = np.column_stack(
            [np.add.reduceat(used, slow) / counts, np.add.reduceat(disturbed, slow) / counts]
        )
        self._send(f"{root}/accel", ts, rxs, fractions)

    def _send_differences(
        self,
        buffer: _StreamBuffer,
        source: str,
        t: np.ndarray,
        euler: np.ndarray,
        references: np.ndarray,
    ) -> None:
        """Ours minus theirs at their times, ours interpolated between the samples around.

        References later than this batch's last estimate are left out (rare: a
        reference arriving before the IMU sample of its time); earlier ones down to
        the previous batch's last estimate are covered by its anchor.
        """
        times = t
        angles = euler
        if buffer.anchor is not None and buffer.anchor[0] < t[0]:
            times = np.concatenate([[buffer.anchor[0]], t])
            angles = np.vstack([buffer.anchor[1:], euler])
        inside = (references[:, 0] >= times[0]) & (references[:, 0] <= times[-1])
        if not np.any(inside):
            return
        at = references[inside, 0]
        unwrapped = np.unwrap(angles, axis=0)
        ours = np.column_stack([np.interp(at, times, unwrapped[:, i]) for i in range(3)])
        difference = ours - references[inside, 2:5]
        difference[:, [0, 2]] = wrap_angles(difference[:, [0, 2]])
        for i, axis in enumerate(("roll", "pitch", "yaw")):
            self._send(
                f"{buffer.root}/error/{axis}/vs_{source}",
                at,
                None,
                np.degrees(difference[:, i]),
            )

    def _send_poses(self, buffer: _StreamBuffer, body: str, t: np.ndarray, attitude: Any) -> None:
        """Body poses at up to ``pose_rate`` (3-D needs no more than the eye sees);
        ``attitude``: our estimates, or (N, 3) ZYX angles of a reference."""
        if body not in buffer.last_pose_t:
            self._log_body(buffer, body)
        keep = _grid_samples(t, self.pose_period, buffer.last_pose_t.get(body, -math.inf))
        if not len(keep):
            return
        buffer.last_pose_t[body] = t[keep[-1]]
        if isinstance(attitude, np.ndarray):
            q = so3.quats_from_euler_zyx(attitude[keep])
        else:
            q = np.array([attitude[k].q for k in keep])
        rr.send_columns(
            f"world/{buffer.root}/{body}/attitude",
            indexes=[rr.TimeColumn(VEHICLE_TIME, duration=t[keep])],
            columns=rr.Transform3D.columns(quaternion=q[:, [1, 2, 3, 0]]),  # x, y, z, w
            recording=self.recording,
        )

    def flush(self) -> None:
        for buffer in self._streams.values():
            self._flush_stream(buffer)
        self._last_flush = time.monotonic()

    def close(self) -> None:
        """Send what is buffered (the recording stream itself is closed by its owner)."""
        self.flush()


def _grid_samples(t: np.ndarray, period: float, last: float) -> np.ndarray:
    """Indices of the samples that start a new ``period`` slot after ``last`` (at most one
    per slot, the first in it): a decimation that keeps the original samples."""
    slots = np.floor(t / period)
    previous = np.concatenate(
        [[math.floor(last / period) if math.isfinite(last) else -np.inf], slots[:-1]]
    )
    return np.flatnonzero(slots != previous)
