"""The Rerun recording read back with rerun's own reader and checked against what the
estimator sent (the output tlog, read by pymavlink); the viewer modes; the screenshot."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from pymavlink import mavutil
from rerun.chunk import RrdReader

from mavest.cli import main
from mavest.estimator import EstimatorConfig
from mavest.service.process import ServiceProcess, free_port
from mavest.sim.vehicle import AUTOPILOTS, stream_flight, write_flight_tlog
from mavest.viz.recorder import _Slots
from mavest.viz.viewer import rerun_binary

PROJECT = Path(__file__).resolve().parents[1]
ROOT = "/vehicle_1_1/raw_imu_0"
SECONDS, RATE = 12.0, 200.0
SAMPLES = round(SECONDS * RATE) + 1


def _scalars(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, bool]]:
    """entity → (vehicle time s, values (N, k), has receive_time), rows in time order."""
    parts: dict[str, list[tuple[np.ndarray, np.ndarray, bool]]] = {}
    for chunk in (
        RrdReader(str(path))
        .stream()
        .filter(has_timeline="vehicle_time", components="Scalars:scalars")
    ):
        batch = chunk.to_record_batch()
        t = batch.column("vehicle_time").cast(pa.int64()).to_numpy() / 1e9
        lists = batch.column("Scalars:scalars")
        width = len(lists[0]) if len(lists) else 1
        values = pc.list_flatten(lists).to_numpy().reshape(len(t), width)
        parts.setdefault(chunk.entity_path, []).append(
            (t, values, "receive_time" in batch.schema.names)
        )
    out = {}
    for entity, chunks in parts.items():
        t = np.concatenate([c[0] for c in chunks])
        values = np.vstack([c[1] for c in chunks])
        order = np.argsort(t, kind="stable")
        out[entity] = (t[order], values[order], all(c[2] for c in chunks))
    return out


def _rows(path: Path, entity: str, component: str) -> int:
    return sum(
        chunk.num_rows
        for chunk in RrdReader(str(path))
        .stream()
        .filter(content=entity, has_timeline="vehicle_time", components=component)
    )


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("rerun")
    flight = folder / "flight.tlog"
    write_flight_tlog(flight, SECONDS, RATE, AUTOPILOTS["ardupilot"], seed=6)
    out_tlog, rrd = folder / "ours.tlog", folder / "ours.rrd"
    arguments = ["replay", str(flight), "--rrd", str(rrd), "--out-tlog", str(out_tlog), "-q"]
    assert main(arguments) == 0
    return {"flight": flight, "tlog": out_tlog, "rrd": rrd}


def _messages(path: Path, name: str, component: int) -> list:
    connection = mavutil.mavlink_connection(str(path))
    out = []
    while (message := connection.recv_match(type=name)) is not None:
        if message.get_srcComponent() == component:
            out.append(message)
    return out


def test_recording_holds_what_the_estimator_sent(recorded: dict[str, Path]) -> None:
    series = _scalars(recorded["rrd"])
    attitude = _messages(recorded["tlog"], "ATTITUDE", 191)
    assert len(attitude) == SAMPLES
    sent_t = np.array([m.time_boot_ms for m in attitude]) / 1000.0
    for axis in ("roll", "pitch", "yaw"):
        t, values, has_receive_time = series[f"{ROOT}/attitude/{axis}/mavest"]
        assert has_receive_time
        assert values.shape == (SAMPLES, 1)
        np.testing.assert_allclose(t, sent_t, atol=1e-3)
        sent = np.degrees([getattr(m, axis) for m in attitude])  # float32 on the wire
        np.testing.assert_allclose(values[:, 0], sent, atol=1e-4)


def test_truth_and_raw_imu_are_the_inputs(recorded: dict[str, Path]) -> None:
    series = _scalars(recorded["rrd"])
    truth = _messages(recorded["flight"], "SIMSTATE", 1)
    raw = _messages(recorded["flight"], "RAW_IMU", 1)
    t_truth, roll, _ = series[f"{ROOT}/attitude/roll/truth"]
    # SIMSTATE comes with every RAW_IMU (200 Hz); the truth is plotted at up to 100 Hz
    raw_t = np.array([m.time_usec for m in _messages(recorded["flight"], "RAW_IMU", 1)]) * 1e-6
    assert 0.45 * len(truth) < len(t_truth) <= 0.5 * len(truth) + 2
    at = np.searchsorted(raw_t, t_truth - 1e-7)
    np.testing.assert_allclose(t_truth, raw_t[at], atol=1e-6)
    expected = np.degrees([truth[k].roll for k in at])
    np.testing.assert_allclose(roll[:, 0], expected, atol=1e-4)
    _, gyro, _ = series[f"{ROOT}/imu/gyro"]
    expected = np.degrees([[m.xgyro, m.ygyro, m.zgyro] for m in raw]) * 1e-3  # mrad/s
    np.testing.assert_allclose(gyro, expected, rtol=1e-9, atol=1e-9)
    _, accel, _ = series[f"{ROOT}/imu/accel"]
    assert accel.shape == (SAMPLES, 3)
    np.testing.assert_allclose(accel[:, 2], [m.zacc * 9.80665e-3 for m in raw], rtol=1e-12)


def test_uncertainty_bias_and_update_series(recorded: dict[str, Path]) -> None:
    series = _scalars(recorded["rrd"])
    t, roll, _ = series[f"{ROOT}/attitude/roll/mavest"]
    t3, bounds, _ = series[f"{ROOT}/attitude/roll/mavest_3sigma"]
    assert 0.4 * SECONDS * 100 < len(t3) <= SECONDS * 100 + 2  # at up to 100 Hz
    at = np.searchsorted(t, t3)
    centre = 0.5 * (bounds[:, 0] + bounds[:, 1])
    np.testing.assert_allclose(centre, roll[at, 0], atol=1e-9)  # ±3σ around the estimate
    assert np.all(bounds[:, 0] > bounds[:, 1])
    for axis in "xyz":
        _, bias, _ = series[f"{ROOT}/bias/{axis}"]
        assert (
            bias.shape[1] == 3
            and np.all(bias[:, 1] > bias[:, 0])
            and np.all(bias[:, 2] < bias[:, 0])
        )
    _, nis, _ = series[f"{ROOT}/nis/value"]
    assert np.all(nis >= 0) and 0.3 < np.mean(nis < 5.99) <= 1.0
    t_accel, accel_state, _ = series[f"{ROOT}/accel"]
    # one row per 100 Hz slot that holds an update (at update_rate, 40 Hz: two in five)
    holding = len(t3) * EstimatorConfig().update_rate / 100.0
    assert np.all(np.isin(t_accel, t3)) and 0.9 * holding < len(t_accel) <= 1.1 * holding + 2
    assert np.all((accel_state >= 0.0) & (accel_state <= 1.0))
    assert accel_state[:, 0].mean() > 0.5  # mostly used in this flight
    _, processing, _ = series[f"{ROOT}/timing/processing_us"]
    assert len(processing) == SAMPLES and np.all(processing > 0)
    _, error, _ = series[f"{ROOT}/error/roll/vs_truth"]
    assert np.sqrt(np.mean(error[t3.size // 2 :, 0] ** 2)) < 5.0
    # the 3-D bodies: posed at up to 50 Hz
    poses = _rows(recorded["rrd"], f"/world{ROOT}/mavest/attitude", "Transform3D:quaternion")
    assert 0.5 * SECONDS * 50 < poses <= SECONDS * 50 + 2


def test_slots_pick_the_first_sample_of_each_slot() -> None:
    """The inline interval test plus ``advance`` choose exactly the samples whose
    floor(t / period) differs from the previous sample's, also on the slots' boundaries
    (times on the millisecond grid) and far from zero, where rounding is coarser."""
    for start, step in ((0.0, 1e-3), (86_400.0, 1e-3), (3.0, 7.3e-4), (0.0, 0.02)):
        t = start + step * np.arange(3000)
        slots = _Slots(0.01, 0.02)
        chosen = []
        for t_k in t:
            starts = (False, False)
            if not slots.since <= t_k < slots.until:
                starts = slots.advance(float(t_k))
            chosen.append(starts)
        for column, period in enumerate((0.01, 0.02)):
            slot = np.floor(t / period)
            expected = np.concatenate([[True], slot[1:] != slot[:-1]])
            np.testing.assert_array_equal([c[column] for c in chosen], expected)


def test_recording_is_valid_and_carries_its_layout(recorded: dict[str, Path]) -> None:
    binary = rerun_binary()
    assert binary is not None
    result = subprocess.run(
        [binary, "rrd", "verify", str(recorded["rrd"])], capture_output=True, text=True
    )
    assert result.returncode == 0 and "1 file verified without error" in result.stderr
    assert RrdReader(str(recorded["rrd"])).blueprints()  # the default layout travels along


# ------------------------------------------------------------------ viewer modes


def _listening_addresses(port: int) -> set[str]:
    """Local addresses with a TCP socket listening on ``port`` (from /proc/net/tcp{,6})."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as stream:
            for line in stream.readlines()[1:]:
                fields = line.split()
                address, port_hex = fields[1].split(":")
                if int(port_hex, 16) == port and fields[3] == "0A":  # LISTEN
                    found.add(address)
    return found


def test_served_viewer_listens_on_this_machine_only(tmp_path: Path) -> None:
    grpc, web, udp = free_port(), free_port(), free_port(socket.SOCK_DGRAM)
    rrd = tmp_path / "served.rrd"
    service = ServiceProcess(
        f"udpin:127.0.0.1:{udp}",
        "--rerun",
        "serve",
        "--rerun-port",
        str(grpc),
        "--rerun-web-port",
        str(web),
        "--rrd",
        str(rrd),  # saved and served at once
    )
    try:
        assert any("Rerun web viewer: http://127.0.0.1" in line for line in service.log)
        loopback = "0100007F"  # 127.0.0.1 as /proc/net/tcp writes it
        assert _listening_addresses(grpc) == {loopback}
        assert _listening_addresses(web) == {loopback}
        report = asyncio.run(stream_flight(f"udpout:127.0.0.1:{udp}", 100.0, seconds=3.0))
        assert report.answered_fraction >= 0.99
    finally:
        assert service.stop()[0] == 0
    assert not _listening_addresses(grpc)  # the served viewer went with the service
    series = _scalars(rrd)
    assert len(series[f"{ROOT}/attitude/roll/mavest"][0]) == report.answered


@pytest.mark.parametrize(
    ("mode", "message"),
    [
        ("connect=rerun+http://127.0.0.1:9/proxy", "no Rerun viewer answers"),
        ("spawn", "no display to open a viewer on"),
    ],
)
def test_a_viewer_that_cannot_start_is_reported_and_estimation_goes_on(
    recorded: dict[str, Path], mode: str, message: str, tmp_path: Path
) -> None:
    environment = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = subprocess.run(
        [sys.executable, "-m", "mavest.cli", "replay", str(recorded["flight"]), "--rerun", mode],
        capture_output=True,
        text=True,
        env=environment,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert f"{SAMPLES} of {SAMPLES} samples" in result.stdout


def test_a_viewer_that_goes_away_does_not_stop_the_service() -> None:
    binary = rerun_binary()
    assert binary is not None
    grpc, udp = free_port(), free_port(socket.SOCK_DGRAM)
    proxy = subprocess.Popen(
        [binary, "--serve-grpc", "--bind", "127.0.0.1", "--port", str(grpc)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 30
    while not _listening_addresses(grpc):
        assert time.monotonic() < deadline, "rerun --serve-grpc did not start"
        time.sleep(0.1)
    service = ServiceProcess(
        f"udpin:127.0.0.1:{udp}", "--rerun", f"connect=rerun+http://127.0.0.1:{grpc}/proxy"
    )

    async def fly_and_kill() -> object:
        flight = asyncio.create_task(
            stream_flight(f"udpout:127.0.0.1:{udp}", 200.0, seed=3, seconds=8.0)
        )
        await asyncio.sleep(3.0)
        proxy.kill()
        return await flight

    report = asyncio.run(fly_and_kill())
    proxy.wait(10)
    assert service.stop()[0] == 0
    assert report.answered_fraction >= 0.99, report.describe()  # type: ignore[attr-defined]
    log = "".join(service.log)
    assert "Traceback" not in log
    assert "went away" in log or "unreachable" in log


# ------------------------------------------------------------------ the picture


@pytest.mark.skipif(
    not any(Path("/usr/share/vulkan/icd.d").glob("*.json")),
    reason="no Vulkan driver for the headless viewer: apt-get install mesa-vulkan-drivers",
)
def test_screenshot_tool_renders_the_recording(recorded: dict[str, Path], tmp_path: Path) -> None:
    png = tmp_path / "shot.png"
    result = subprocess.run(
        [sys.executable, str(PROJECT / "tools" / "screenshot.py"), str(recorded["rrd"]), str(png)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert result.returncode == 0, result.stderr
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000  # a drawn page, not a blank one
