"""The estimates table (``--estimates FILE.csv|FILE.parquet``): a row per estimated IMU
sample, the same bytes by either replay path, whole or absent, and σ of the angles
that are the first-order spread of the filter's attitude error."""

from __future__ import annotations

import asyncio
import contextlib
import csv
import math
import re
import resource
import signal
import socket
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

import mavest.service.estimates_table as estimates_table
from mavest.cli import main
from mavest.estimator import Estimator, EstimatorConfig
from mavest.mavlink.messages import StreamKey, time_boot_ms
from mavest.mavlink.tlog import TlogReader, message_ids
from mavest.paths import OutputPathError, partial_path
from mavest.service.config import ServiceConfig
from mavest.service.estimates_table import COLUMNS, EstimatesTable
from mavest.service.pipeline import Pipeline
from mavest.service.process import free_port
from mavest.service.runners import Outputs, RunReport, replay, run_live
from mavest.sim import simulate
from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog
from mavest.so3 import euler_sigmas

FORMATS = ("csv", "parquet")
# small blocks, so that a replay writes several and the fast path's batches are split
BLOCK = 500


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 s at 200 Hz, turning, with GPS, airspeed, magnetometer and truth: 1601 samples."""
    path = tmp_path_factory.mktemp("flight") / "flight.tlog"
    write_flight_tlog(path, 8.0, 200.0, AUTOPILOTS["ardupilot"], seed=5)
    return path


def _replay(
    log: Path, outputs: Outputs, fast: bool = True, config: ServiceConfig | None = None
) -> RunReport:
    return asyncio.run(replay(log, config or ServiceConfig(), outputs, progress=False, fast=fast))


@pytest.fixture(scope="module")
def replays(flight: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[Any, Any]:
    """Each format written by the fast path and one by one, with the output tlog."""
    folder = tmp_path_factory.mktemp("tables")
    out: dict[Any, Any] = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(estimates_table, "BLOCK_ROWS", BLOCK)
        for kind in FORMATS:
            for fast in (True, False):
                table = folder / f"{'fast' if fast else 'one_by_one'}.{kind}"
                tlog = folder / f"{kind}_{fast}.tlog"
                report = _replay(flight, Outputs(tlog=tlog, estimates=table), fast)
                out[kind, fast] = (table, tlog, report)
    return out


def _estimated(report: RunReport) -> int:
    return sum(stream.stats.estimated for stream in report.pipeline.streams.values())


def _read(path: Path) -> dict[str, np.ndarray]:
    """The table's columns, read back by the format's own reader."""
    if path.suffix == ".parquet":
        table = pq.read_table(path)
        columns = {name: table.column(name).to_pylist() for name in table.column_names}
        return {name: np.array(values) for name, values in columns.items()}
    with path.open(newline="") as stream:
        rows = list(csv.reader(stream))
    header, body = rows[0], rows[1:]
    columns = {}
    for i, name in enumerate(header):
        values = [row[i] for row in body]
        if name == "message":
            columns[name] = np.array(values)
        elif name == "accel_used":
            assert set(values) <= {"true", "false"}
            columns[name] = np.array([value == "true" for value in values])
        elif name in ("system", "component", "instance", "flags"):
            columns[name] = np.array([int(value) for value in values])
        else:
            columns[name] = np.array([float(value) for value in values])
    return columns


# ------------------------------------------------------------------ a replay's table


@pytest.mark.parametrize("kind", FORMATS)
def test_a_row_per_estimated_sample(kind: str, replays: dict[Any, Any]) -> None:
    table, _, report = replays[kind, True]
    columns = _read(table)
    assert list(columns) == list(COLUMNS)
    estimated = int(re.search(r"(\d+) IMU samples estimated", report.summary())[1])
    assert estimated == _estimated(report) == 1601
    assert all(values.shape == (estimated,) for values in columns.values())
    assert f"wrote {table} (estimates table)" in report.summary()
    assert report.pipeline.batch_fed  # the fast path it was
    assert not replays[kind, False][2].pipeline.batch_fed
    assert set(columns["message"]) == {"RAW_IMU"}
    assert set(columns["system"]) == {1} and set(columns["instance"]) == {0}
    assert np.all(np.diff(columns["time_s"]) > 0)
    assert [path.name for path in table.parent.iterdir() if "partial" in path.name] == []


def test_the_formats_hold_the_same_values_with_their_types(replays: dict[Any, Any]) -> None:
    from_csv, from_parquet = _read(replays["csv", True][0]), _read(replays["parquet", True][0])
    for name in COLUMNS:  # CSV's floats read back exactly
        nan = from_csv[name].dtype == np.float64
        assert np.array_equal(from_csv[name], from_parquet[name], equal_nan=nan), name
    schema = pq.read_schema(replays["parquet", True][0])
    assert schema.field("message").type == pa.dictionary(pa.int32(), pa.string())
    assert schema.field("accel_used").type == pa.bool_()
    for name in ("system", "component", "instance", "flags"):
        assert schema.field(name).type == pa.int64()
    floats = [name for name in COLUMNS if name.endswith(("_s", "_deg", "_dps")) or name == "nis"]
    floats += ["qw", "qx", "qy", "qz"]
    assert len(floats) == 15
    assert all(schema.field(name).type == pa.float64() for name in floats)
    # a row group per block, as the replay went
    assert pq.ParquetFile(replays["parquet", True][0]).num_row_groups == math.ceil(1601 / BLOCK)


@pytest.mark.parametrize("kind", FORMATS)
def test_the_fast_path_and_one_by_one_write_the_same_bytes(
    kind: str, replays: dict[Any, Any]
) -> None:
    fast, one_by_one = replays[kind, True][0], replays[kind, False][0]
    assert fast.read_bytes() == one_by_one.read_bytes()


def test_the_angles_are_the_attitude_sent(replays: dict[Any, Any]) -> None:
    table, tlog, _ = replays["csv", True]
    columns = _read(table)
    q = np.column_stack([columns[name] for name in ("qw", "qx", "qy", "qz")])
    assert np.abs(np.linalg.norm(q, axis=1) - 1.0).max() < 1e-12
    sent = [
        record.message
        for record in TlogReader.open(tlog, message_ids(["ATTITUDE"]))
        if record.message is not None and record.message.get_srcComponent() == 191
    ]
    assert len(sent) == q.shape[0]  # one ATTITUDE per sample (attitude_rate 0)
    assert [m.time_boot_ms for m in sent] == [time_boot_ms(t) for t in columns["time_s"]]
    for axis in ("roll", "pitch", "yaw"):
        ours = np.radians(columns[f"{axis}_deg"])
        theirs = np.array([getattr(m, axis) for m in sent], dtype=np.float32)
        # ATTITUDE carries float32: the same angle to its last bit
        assert np.all(np.abs(ours - theirs) <= np.abs(np.spacing(theirs))), axis
    # and the quaternion is the angles' own
    angles = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_euler("ZYX")[:, ::-1]
    euler = np.radians(np.column_stack([columns[f"{a}_deg"] for a in ("roll", "pitch", "yaw")]))
    difference = (angles - euler + math.pi) % (2 * math.pi) - math.pi
    assert np.abs(difference).max() < 1e-9


def test_the_last_row_is_the_filters_state(replays: dict[Any, Any]) -> None:
    table, _, report = replays["parquet", False]
    last = {name: values[-1] for name, values in _read(table).items()}
    (stream,) = report.pipeline.streams.values()
    estimator = stream.estimator
    assert [last[n] for n in ("qw", "qx", "qy", "qz")] == estimator.q.tolist()
    bias = [last[f"bias_{axis}_dps"] for axis in "xyz"]
    assert np.array_equal(bias, np.degrees(estimator.bias))
    sigma = [last[f"sigma_{axis}_deg"] for axis in ("roll", "pitch", "yaw")]
    expected = np.degrees(euler_sigmas(estimator.q[None], estimator.cov[None, :3, :3]))[0]
    assert np.array_equal(sigma, expected)
    # heading from the magnetometer: yaw known to a few degrees, tilt better
    assert 0.0 < max(sigma[:2]) < sigma[2] < 5.0
    assert last["time_s"] == stream.stats.last_t


def test_a_right_error_filters_sigmas_are_of_its_body_frame_covariance(
    flight: Path, tmp_path: Path
) -> None:
    """With the right error, cov[:3, :3] is of a body-frame δθ: the table maps it as one
    (the same σ as the world-frame covariance it is, R P Rᵀ, would have), and so does
    the Rerun recording's ±3σ band."""
    from test_rerun import _scalars

    config = ServiceConfig().replace(estimator={"error": "right", "chart": "exp"})
    path, rrd = tmp_path / "right.parquet", tmp_path / "right.rrd"
    report = _replay(flight, Outputs(estimates=path, rrd=rrd), config=config)
    columns = _read(path)
    t, bounds, _ = _scalars(rrd)["/vehicle_1_1/raw_imu_0/attitude/pitch/mavest_3sigma"]
    rows = np.searchsorted(columns["time_s"], t - 1e-6)
    assert np.allclose(columns["time_s"][rows], t, rtol=0, atol=1e-6)
    band = 0.5 * (bounds[:, 0] - bounds[:, 1])
    assert np.allclose(band, 3.0 * columns["sigma_pitch_deg"][rows], rtol=0, atol=1e-9)
    sigma = [columns[f"sigma_{axis}_deg"][-1] for axis in ("roll", "pitch", "yaw")]
    (stream,) = report.pipeline.streams.values()
    q, P = stream.estimator.q, stream.estimator.cov[:3, :3]
    R = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
    world = np.degrees(euler_sigmas(q[None], (R @ P @ R.T)[None], "left"))[0]
    assert np.allclose(sigma, world, rtol=1e-9, atol=0)
    as_if_world = np.degrees(euler_sigmas(q[None], P[None], "left"))[0]
    assert not np.allclose(sigma, as_if_world, rtol=0.01)  # the frame matters here


# ------------------------------------------------------------------ σ of the angles


def _random_cases(seed: int, n: int, degrees: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Attitudes, and covariances of about ``degrees`` (at most) σ."""
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]
    A = rng.normal(size=(n, 3, 3)) * np.radians(rng.uniform(0.1, degrees, size=(n, 1, 1)))
    return q, A @ np.transpose(A, (0, 2, 1))


def _angles(R: np.ndarray) -> np.ndarray:
    """roll, pitch, yaw of rotation matrices, by scipy."""
    return Rotation.from_matrix(R).as_euler("ZYX")[..., ::-1]


@pytest.mark.parametrize("error", ["left", "right"])
def test_sigmas_are_the_angles_jacobian_by_finite_differences(error: str) -> None:
    q, P = _random_cases(1, 200)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    step = 1e-6
    J = np.empty((len(q), 3, 3))
    for j in range(3):
        turn = Rotation.from_rotvec(step * np.eye(3)[j]).as_matrix()
        plus, minus = (turn @ R, turn.T @ R) if error == "left" else (R @ turn, R @ turn.T)
        change = (_angles(plus) - _angles(minus) + math.pi) % (2 * math.pi) - math.pi
        J[:, :, j] = change / (2 * step)
    expected = np.sqrt(np.diagonal(J @ P @ np.transpose(J, (0, 2, 1)), axis1=1, axis2=2))
    assert np.allclose(euler_sigmas(q, P, error), expected, rtol=1e-6, atol=0)


def test_sigmas_are_the_spread_of_the_angles_by_monte_carlo() -> None:
    q, P = _random_cases(2, 3, degrees=0.5)  # small: first order is all there is
    rng = np.random.default_rng(3)
    for error in ("left", "right"):
        sigma = euler_sigmas(q, P, error)
        for i in range(len(q)):
            R = Rotation.from_quat(q[i, [1, 2, 3, 0]]).as_matrix()
            errors = Rotation.from_rotvec(rng.multivariate_normal(np.zeros(3), P[i], 40000))
            drawn = errors.as_matrix() @ R if error == "left" else R @ errors.as_matrix()
            spread = (_angles(drawn) - _angles(R) + math.pi) % (2 * math.pi) - math.pi
            # 40000 draws: the sample σ is within ~1.5 % at 3σ
            assert np.allclose(spread.std(axis=0), sigma[i], rtol=0.02), (error, i)


def test_sigmas_of_the_two_errors_are_one_distribution() -> None:
    """P_left = R P_right Rᵀ describes the same errors: the same σ."""
    q, P = _random_cases(4, 100)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    left = R @ P @ np.transpose(R, (0, 2, 1))
    assert np.allclose(euler_sigmas(q, P, "right"), euler_sigmas(q, left, "left"), rtol=1e-9)


def test_roll_and_yaw_are_unbounded_at_ninety_degrees_pitch() -> None:
    q = Rotation.from_euler("ZYX", [[0.3, math.pi / 2, 0.0], [0.3, 0.5, 0.2]]).as_quat()
    sigma = euler_sigmas(q[:, [3, 0, 1, 2]], np.tile(np.eye(3) * 1e-4, (2, 1, 1)))
    assert np.all(np.isinf(sigma[0])) and np.all(np.isfinite(sigma[1]))
    with pytest.raises(ValueError, match="left"):
        euler_sigmas(q, np.tile(np.eye(3), (2, 1, 1)), "up")


# ------------------------------------------------------------------ whole or absent


def test_rows_go_to_disk_a_block_at_a_time(tmp_path: Path) -> None:
    """Memory stays flat: every full block is in the (hidden) file before the end."""
    path = tmp_path / "table.csv"
    table = EstimatesTable(path, block_rows=64)
    estimator = Estimator(EstimatorConfig())
    stream = SimpleNamespace(key=StreamKey(1, 1, "RAW_IMU", 0), estimator=estimator)
    data = simulate(3.0, 100.0, seed=1)
    for t, gyro, accel in zip(data.t, data.gyro, data.accel, strict=True):
        estimate = estimator.update(float(t), gyro, accel)
        table.on_estimate(stream, None, estimate, tuple(estimate.euler), 0, 0.0)
    n = len(data.t)
    assert not path.exists()
    assert partial_path(path).read_text().count("\n") == 1 + n // 64 * 64
    table.close()
    assert not partial_path(path).exists()
    assert _read(path)["time_s"].tolist() == data.t.tolist()


@pytest.mark.parametrize("kind", FORMATS)
def test_an_interrupted_replay_keeps_its_whole_rows(
    kind: str, flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(estimates_table, "BLOCK_ROWS", 128)
    path = tmp_path / f"table.{kind}"
    stop = asyncio.Event()
    stop.set()  # Ctrl-C as soon as the replay looks (after its first records)
    report = asyncio.run(
        replay(
            flight, ServiceConfig(), Outputs(estimates=path), progress=False, stop=stop, fast=False
        )
    )
    assert report.interrupted
    rows = _read(path)["time_s"].shape[0]
    assert 0 < rows == _estimated(report) < 1601
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize("kind", FORMATS)
def test_a_failed_replay_leaves_no_table(
    kind: str, flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(estimates_table, "BLOCK_ROWS", 64)
    beats = 0
    heartbeat = Pipeline.heartbeat

    def failing(pipeline: Pipeline) -> None:
        nonlocal beats
        beats += 1
        if beats == 4:  # seconds into the flight: blocks written already
            raise RuntimeError("a bug")
        heartbeat(pipeline)

    monkeypatch.setattr(Pipeline, "heartbeat", failing)
    path = tmp_path / f"table.{kind}"
    with pytest.raises(RuntimeError, match="a bug"):
        _replay(flight, Outputs(estimates=path, tlog=tmp_path / "out.tlog"), fast=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tlog"]


@contextlib.contextmanager
def file_size_limit(limit: int) -> Iterator[None]:
    """Writes past ``limit`` bytes of a file fail (EFBIG), as on a full disk."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)


def test_a_full_disk_stops_the_table_and_not_the_replay(
    flight: Path, replays: dict[Any, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(estimates_table, "BLOCK_ROWS", BLOCK)
    csv_path, parquet_path = tmp_path / "table.csv", tmp_path / "table.parquet"
    with file_size_limit(100_000):  # well under either table
        reports = [_replay(flight, Outputs(estimates=p)) for p in (csv_path, parquet_path)]
    assert all(_estimated(report) == 1601 for report in reports)  # estimating went on
    # the CSV stops at its last whole row: the first rows of the whole table
    kept = csv_path.read_bytes()
    whole = replays["csv", True][0].read_bytes()
    assert kept.endswith(b"\n") and whole.startswith(kept) and 0 < len(kept) <= 100_000
    assert "stopped early: cannot write" in reports[0].summary()
    # a Parquet file is whole or absent, and the summary does not say it was written
    assert not parquet_path.exists() and parquet_path in reports[1].output_errors
    summary = reports[1].summary()
    assert f"wrote {parquet_path}" not in summary
    assert f"no estimates table written: cannot write {parquet_path}" in summary
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]


# ------------------------------------------------------------------ the command line


def _one_line(err: str, message: str) -> None:
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--estimates", "{tmp}/link.csv"], "--estimates {tmp}/link.csv is the log being replayed"),
        (["--estimates", "{tmp}/o.csv", "--out-tlog", "{tmp}/o.csv"], "are both"),
        (["--estimates", "{tmp}/o.parquet", "--rrd", "{tmp}/o.parquet"], "are both"),
        (["--estimates", "{tmp}/none/o.csv"], "no folder"),
        (["--estimates", "{tmp}/o.txt"], "argument --estimates: {tmp}/o.txt: name a .csv or a"),
        (["--estimates", "{tmp}/o"], "name a .csv or a .parquet file"),
    ],
)
def test_the_table_is_checked_as_every_output(
    flight: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    arguments: list[str],
    message: str,
) -> None:
    log = tmp_path / "f.tlog"
    log.write_bytes(flight.read_bytes())
    (tmp_path / "link.csv").symlink_to(log)
    before = log.read_bytes()
    assert main(["replay", str(log), *(a.format(tmp=tmp_path) for a in arguments)]) == 2
    _one_line(capsys.readouterr().err, message.format(tmp=tmp_path))
    assert log.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.tlog", "link.csv"]


def test_run_checks_the_table_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "c.csv"  # a configuration, whatever its name
    config.write_text("[output]\nattitude_rate = 10.0\n")
    arguments = ["run", "udpin:127.0.0.1:1", "--config", str(config), "--estimates", str(config)]
    assert main(arguments) == 2
    _one_line(capsys.readouterr().err, "is the --config file")
    assert config.read_text() == "[output]\nattitude_rate = 10.0\n"


def test_parquet_without_pyarrow_says_what_to_install(
    flight: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    find_spec = estimates_table.importlib.util.find_spec
    monkeypatch.setattr(
        estimates_table.importlib.util,
        "find_spec",
        lambda name, *args: None if name == "pyarrow" else find_spec(name, *args),
    )
    out = tmp_path / "o.parquet"
    assert main(["replay", str(flight), "--estimates", str(out)]) == 2
    _one_line(capsys.readouterr().err, "pip install 'mavest[parquet]'")
    with pytest.raises(OutputPathError, match="needs pyarrow"):
        _replay(flight, Outputs(estimates=out, tlog=tmp_path / "o.tlog"))
    assert list(tmp_path.iterdir()) == []  # refused before any file was opened


def test_a_live_run_writes_its_table(flight: Path, tmp_path: Path) -> None:
    packets = [record.packet for record in TlogReader.open(flight)]
    path = tmp_path / "live.csv"

    async def session() -> RunReport:
        port = free_port(socket.SOCK_DGRAM)
        stop, ready = asyncio.Event(), asyncio.Event()
        service = asyncio.create_task(
            run_live(
                f"udpin:127.0.0.1:{port}",
                ServiceConfig(),
                outputs=Outputs(estimates=path),
                stop=stop,
                ready=ready,
                status_period=0,
            )
        )
        await asyncio.wait_for(ready.wait(), 120)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for start in range(0, 1000, 20):  # the first ~2 s of the flight
                sock.sendto(b"".join(packets[start : start + 20]), ("127.0.0.1", port))
                await asyncio.sleep(0.002)
        await asyncio.sleep(0.3)
        stop.set()
        return await service

    report = asyncio.run(session())
    rows = _read(path)["time_s"].shape[0]
    assert rows == _estimated(report) > 100


def test_a_replay_that_lingers_for_its_viewer_has_its_table_whole(
    flight: Path, tmp_path: Path
) -> None:
    path = tmp_path / "table.csv"
    seen: list[int] = []

    async def linger(report: RunReport) -> None:
        seen.append(_read(path)["time_s"].shape[0])

    outputs = Outputs(
        estimates=path,
        rerun="serve",
        rerun_port=free_port(socket.SOCK_STREAM),
        rerun_web_port=free_port(socket.SOCK_STREAM),
    )
    report = asyncio.run(replay(flight, ServiceConfig(), outputs, progress=False, linger=linger))
    assert report.lingered and seen == [_estimated(report)] == [1601]
    assert _read(path)["time_s"].shape[0] == 1601
