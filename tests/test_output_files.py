"""What an output path names is written, never replaced, and a run that cannot write
one of its outputs says so before it has touched any.

A symbolic link is written at the file it points to; a character device or a FIFO is
written into as a stream; a block device or a socket is refused. Every output is
tried for writing before the first is opened: a run refused for its last output
leaves the files of the others as they were.
"""

from __future__ import annotations

import asyncio
import builtins
import errno
import io
import os
import socket
import stat
import struct
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

import mavest.service.runners as runners
from mavest.cli import main
from mavest.paths import OutputPathError, check_outputs, partial_path, write_atomically
from mavest.service.config import ServiceConfig
from mavest.service.estimates_table import COLUMNS, EstimatesTableError
from mavest.service.runners import Outputs, replay
from mavest.sim import simulate

T0_US = 1_700_000_000_000_000  # a ground station's clock, µs


def imu_tlog(path: Path, seconds: float, rate: float = 200.0, pause_s: float = 0.0) -> Path:
    """A vehicle at rest sending RAW_IMU (and a HEARTBEAT a second); with ``pause_s``, the
    recording paused that long half-way (the vehicle's clock went on as usual)."""
    encoder = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    n = int(seconds * rate)
    step_us = int(1e6 / rate)
    with path.open("wb") as stream:
        for i in range(n):
            stamp = T0_US + i * step_us + (int(pause_s * 1e6) if i >= n // 2 else 0)
            if i % int(rate) == 0:
                beat = encoder.heartbeat_encode(2, 3, 0, 0, 0).pack(encoder)
                stream.write(struct.pack(">Q", stamp) + beat)
            imu = encoder.raw_imu_encode(i * step_us, 0, 0, -1000, 0, 0, 0, 200, 0, 400)
            stream.write(struct.pack(">Q", stamp) + imu.pack(encoder))
    return path


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return imu_tlog(tmp_path_factory.mktemp("log") / "f.tlog", 4.0)


@pytest.fixture(scope="module")
def imu_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("csv") / "imu.csv"
    data = simulate(2.0, 100.0, seed=1)
    np.savetxt(path, np.column_stack([data.t, data.gyro, data.accel]), delimiter=",")
    return path


def _one_line(err: str, message: str) -> None:
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


# ------------------------------------------------------------------ links, devices, pipes


def test_an_output_through_a_symbolic_link_writes_the_file_it_points_to(
    flight: Path, imu_csv: Path, tmp_path: Path
) -> None:
    targets = tmp_path / "targets"
    targets.mkdir()
    links = {}
    for name in ("est.csv", "table.csv", "out.tlog", "dangling.csv"):
        link = tmp_path / name
        if name != "dangling.csv":  # (a link to a file not made yet: the file is made)
            (targets / name).write_bytes(b"old")
        link.symlink_to(targets / name)
        links[name] = link
    assert main(["estimate", str(imu_csv), "-o", str(links["est.csv"])]) == 0
    arguments = ["--estimates", str(links["table.csv"]), "--out-tlog", str(links["out.tlog"])]
    assert main(["replay", str(flight), "-q", *arguments]) == 0
    write_atomically(links["dangling.csv"], b"whole\n")
    for name, link in links.items():
        assert link.is_symlink() and link.resolve() == targets / name, name
    assert (targets / "est.csv").read_text().startswith("t,qw,qx,qy,qz,")
    assert (targets / "table.csv").read_text().startswith(",".join(COLUMNS) + "\n")
    # the log's records and the ATTITUDE answered, after the first record
    tlog = (targets / "out.tlog").read_bytes()
    assert tlog[:30] == flight.read_bytes()[:30] and len(tlog) > flight.stat().st_size
    assert (targets / "dangling.csv").read_bytes() == b"whole\n"
    # nothing left beside the links or the files (the partial files are renamed)
    assert sorted(p.name for p in targets.iterdir()) == sorted(links)


@pytest.mark.parametrize("table", ["table.csv", "table.parquet"])
def test_an_output_replaced_keeps_its_permissions(
    table: str, flight: Path, imu_csv: Path, tmp_path: Path
) -> None:
    """Every output a run replaces whole keeps the permissions its user gave it (the
    estimate's CSV, the estimates table, written first beside it and renamed)."""
    outputs = {name: tmp_path / name for name in ("est.csv", table)}
    for path in outputs.values():
        path.write_bytes(b"old")
        path.chmod(0o600)
    assert main(["estimate", str(imu_csv), "-o", str(outputs["est.csv"])]) == 0
    assert main(["replay", str(flight), "-q", "--estimates", str(outputs[table])]) == 0
    for name, path in outputs.items():
        assert path.read_bytes() != b"old", name
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, name


def _read_fifo(path: Path) -> tuple[threading.Thread, list[bytes]]:
    """A reader of the FIFO at ``path``, in a thread, until its writer closes it."""
    got: list[bytes] = []

    def read() -> None:
        with path.open("rb") as stream:
            got.append(stream.read())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return reader, got


def test_a_fifo_is_written_into_and_stays_a_fifo(
    flight: Path, imu_csv: Path, tmp_path: Path
) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    files = tmp_path / "files"
    files.mkdir()
    for command in (
        ["estimate", str(imu_csv), "-o"],
        ["replay", str(flight), "-q", "--estimates"],
    ):
        reader, got = _read_fifo(fifo)
        assert main([*command, str(fifo)]) == 0
        reader.join(30)
        # what a file would have got, whole
        assert main([*command, str(files / "file.csv")]) == 0
        assert got == [(files / "file.csv").read_bytes()] and got[0].count(b"\n") > 100
        assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["files", "pipe.csv"]


def _char_device(path: Path) -> None:
    """A copy of /dev/null's node at ``path`` (root only), or the test is skipped."""
    if os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except PermissionError:
        pytest.skip("this system does not let us make a device node")


def test_a_character_device_is_written_into_and_stays_a_device(
    flight: Path, imu_csv: Path, tmp_path: Path
) -> None:
    null = tmp_path / "null.csv"
    _char_device(null)
    assert main(["estimate", str(imu_csv), "-o", str(null)]) == 0
    arguments = ["--estimates", str(null), "--out-tlog", str(null.with_name("null.tlog"))]
    os.mknod(null.with_name("null.tlog"), stat.S_IFCHR | 0o666, os.makedev(1, 3))
    assert main(["replay", str(flight), "-q", *arguments]) == 0
    for node in (null, null.with_name("null.tlog")):
        status = os.stat(node)
        assert stat.S_ISCHR(status.st_mode) and status.st_rdev == os.makedev(1, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["null.csv", "null.tlog"]


def test_a_block_device_or_a_socket_is_refused(tmp_path: Path) -> None:
    server = socket.socket(socket.AF_UNIX)
    try:
        server.bind(str(tmp_path / "s.csv"))
        with pytest.raises(OutputPathError, match=r"^-o .*s\.csv is a socket: name a file$"):
            check_outputs({}, {"-o": tmp_path / "s.csv"})
    finally:
        server.close()
    if os.geteuid() == 0:  # (only checked: nothing is ever written to it)
        disk = tmp_path / "disk.csv"
        try:
            os.mknod(disk, stat.S_IFBLK | 0o600, os.makedev(7, 0))
        except PermissionError:
            return
        with pytest.raises(OutputPathError, match=r"is a block device: name a file$"):
            check_outputs({}, {"--estimates": disk})


# ------------------------------------------------------------------ outputs that cannot be


@pytest.fixture
def read_only_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """``tmp_path/ro``, as on a read-only file system: nothing in it can be made, opened
    for writing or removed. Not as root: by its permissions; root ignores those, so
    then by the functions that open and remove files failing as the system would
    (EROFS, even for a file that is not there)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    inside = str(folder.resolve()) + os.sep
    real_open, real_io_open, real_unlink = os.open, io.open, os.unlink

    def refused(path: Any) -> bool:
        if not isinstance(path, (str, bytes, os.PathLike)):
            return False  # (a file descriptor)
        return os.path.realpath(os.fsdecode(path)).startswith(inside)

    def read_only() -> OSError:
        return OSError(errno.EROFS, os.strerror(errno.EROFS))

    def os_open(path: Any, flags: int, mode: int = 0o777, *, dir_fd: int | None = None) -> int:
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and refused(path):
            raise read_only()
        return real_open(path, flags, mode, dir_fd=dir_fd)

    def io_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        if any(c in mode for c in "wax+") and refused(file):
            raise read_only()
        return real_io_open(file, mode, *args, **kwargs)

    def unlink(path: Any, *, dir_fd: int | None = None) -> None:
        if refused(path):
            raise read_only()
        real_unlink(path, dir_fd=dir_fd)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)
    monkeypatch.setattr(os, "unlink", unlink)
    yield folder


def test_an_output_that_cannot_be_written_is_refused_before_any_is_opened(
    flight: Path,
    imu_csv: Path,
    tmp_path: Path,
    read_only_folder: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "prev.tlog").write_bytes(b"an earlier run's tlog")
    (out / "prev.rrd").write_bytes(b"an earlier run's recording")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    earlier = ["--out-tlog", str(out / "prev.tlog"), "--rrd", str(out / "prev.rrd")]
    for arguments, option in (
        (["replay", str(flight), *earlier, "--estimates", str(read_only_folder / "a.csv")],
         "--estimates"),
        (["replay", str(flight), "--out-tlog", str(out / "x.tlog"),
          "--rrd", str(read_only_folder / "a.rrd")], "--rrd"),
        (["replay", str(flight), "--out-tlog", str(read_only_folder / "a.tlog")], "--out-tlog"),
        (["estimate", str(imu_csv), "-o", str(read_only_folder / "a.csv")], "-o"),
        (["sim", "--tlog", str(read_only_folder / "s.tlog"), "--seconds", "1"], "--tlog"),
    ):  # fmt: skip
        assert main(arguments) == 2, arguments
        _one_line(capsys.readouterr().err, f"mavest: {option} {read_only_folder}")
        # the earlier outputs as they were, and no file begun
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, arguments
    assert list(read_only_folder.iterdir()) == []


def test_a_file_name_near_the_longest_is_written(flight: Path, tmp_path: Path) -> None:
    """A name of 244 bytes is a file name; the probe and the partial file beside it, 15
    bytes longer, were not, and the output was refused as "File name too long"."""
    table = tmp_path / ("n" * 240 + ".csv")
    assert main(["replay", str(flight), "--estimates", str(table), "-q"]) == 0
    assert table.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [table.name]  # (nothing beside)
    for name in ("é" * 126 + ".csv", os.fsdecode(b"caf\xe9" * 60 + b".csv")):  # 256, 244
        partial = partial_path(tmp_path / name)
        assert len(os.fsencode(partial.name)) <= 255 and partial.name.startswith(".")
        assert partial != partial_path(tmp_path / ("x" + name))  # (each file its own)


def test_an_output_that_fails_to_open_all_the_same_leaves_the_others_untouched(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """(A folder that turns read-only between the check and the opening.)"""
    earlier = tmp_path / "prev.tlog"
    earlier.write_bytes(b"an earlier run's tlog")

    def unwritable(path: Path, **_: Any) -> None:
        raise EstimatesTableError(f"cannot write {path}: Read-only file system")

    monkeypatch.setattr(runners, "EstimatesTable", unwritable)
    outputs = Outputs(tlog=earlier, estimates=tmp_path / "e.csv")
    with pytest.raises(EstimatesTableError, match="Read-only file system"):
        asyncio.run(replay(flight, ServiceConfig(), outputs, progress=False))
    assert earlier.read_bytes() == b"an earlier run's tlog"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prev.tlog"]
