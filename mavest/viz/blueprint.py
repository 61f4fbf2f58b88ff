"""The default layout of a mavest recording: readable without clicking.

Left, the vehicle in 3-D as mavest, the autopilot and the truth see it. Right,
roll, pitch and yaw (ours with its ±3σ band, the smoothed one with its band after a
``replay --smooth``, the autopilot's, the truth), and
below them tabs for the errors, the gyro bias, the accelerometer update (NIS
against its χ² band, innovation, accepted/disturbed), the raw IMU and the
per-sample processing time.
"""

from __future__ import annotations

import rerun.blueprint as rrb

from mavest.viz.recorder import VEHICLE_TIME

# Plots show the last minute up to the time cursor: live, a moving window; in a
# recording opened at its end, the last minute of the flight.
_LAST_MINUTE = rrb.VisibleTimeRange(
    VEHICLE_TIME,
    start=rrb.TimeRangeBoundary.cursor_relative(seconds=-60.0),
    end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0),
)


def _series(origin: str, name: str) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(origin=origin, name=name, time_ranges=_LAST_MINUTE)


def stream_layout(root: str) -> rrb.Horizontal:
    """The views of one IMU stream (root as in :func:`mavest.viz.recorder.stream_root`)."""
    attitude = rrb.Vertical(
        _series(f"{root}/attitude/roll", "roll (°): mavest ±3σ, smoothed ±3σ, autopilot, truth"),
        _series(f"{root}/attitude/pitch", "pitch (°)"),
        _series(f"{root}/attitude/yaw", "yaw (°): from the magnetometer, free (6-D) without one"),
    )
    details = rrb.Tabs(
        rrb.Vertical(
            _series(f"{root}/error/roll", "roll error (°): mavest − reference"),
            _series(f"{root}/error/pitch", "pitch error (°)"),
            _series(f"{root}/error/yaw", "yaw error (°)"),
            name="errors",
        ),
        rrb.Vertical(
            _series(f"{root}/bias/x", "gyro bias x (°/s) ±1σ"),
            _series(f"{root}/bias/y", "gyro bias y (°/s) ±1σ"),
            _series(f"{root}/bias/z", "gyro bias z (°/s) ±1σ"),
            name="gyro bias",
        ),
        rrb.Vertical(
            _series(f"{root}/nis", "NIS (χ², 2 dof) and its 90 % band"),
            _series(f"{root}/innovation", "gravity innovation (°)"),
            _series(f"{root}/accel", "accelerometer: fraction used / disturbed (per 10 ms)"),
            name="accelerometer update",
        ),
        rrb.Vertical(
            _series(f"{root}/imu/gyro", "gyro (°/s)"),
            _series(f"{root}/imu/accel", "specific force (m/s²)"),
            name="raw IMU",
        ),
        _series(f"{root}/timing", "processing time per sample (µs)"),
        rrb.TextLogView(
            origin=f"{root}/events", name="filter events: tilt reopened, re-initialised"
        ),
        active_tab=0,
    )
    return rrb.Horizontal(
        rrb.Spatial3DView(
            origin=f"world/{root}",
            name="vehicle: mavest, autopilot, truth",
            # from behind, to the left and above (NED: up is −z), all three bodies in sight
            eye_controls=rrb.EyeControls3D(
                position=(-7.0, -5.0, -4.0), look_target=(0.0, 0.0, 0.0)
            ),
        ),
        rrb.Vertical(attitude, details, row_shares=[3, 2]),
        column_shares=[2, 3],
        name=root,
    )


def blueprint(roots: list[str]) -> rrb.Blueprint:
    """One tab per IMU stream; the side panels collapsed so the views get the screen."""
    layouts = [stream_layout(root) for root in roots]
    content = layouts[0] if len(layouts) == 1 else rrb.Tabs(*layouts)
    return rrb.Blueprint(
        content,
        # following: a recording opens at its end, a live one stays at the newest sample
        rrb.TimePanel(timeline=VEHICLE_TIME, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )
