"""Where a recording goes: an .rrd file, a viewer on this machine, one already running,
or a served web viewer; any of them together.

The Python SDK's own ``serve_grpc``/``serve_web_viewer`` listen on every
interface. mavest never does that unasked: for ``serve`` (and ``spawn``) it
starts the ``rerun`` binary shipped in the rerun-sdk wheel with ``--bind``
(127.0.0.1 unless ``bind`` says otherwise) and streams to it over gRPC. A
viewer that cannot start, or goes away later, is reported once; the estimator
and the file go on.

A disk that fills up is watched for: the .rrd is closed, with the footer that
makes it a complete recording, while there is still room for that footer (see
:data:`RRD_DISK_RESERVE_BYTES`), and estimation goes on without it.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

if TYPE_CHECKING:
    import rerun as rr

log = logging.getLogger("mavest")

VIEWER_MODES = ("spawn", "connect", "serve")
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090

# Free space an .rrd's disk keeps: below it the recording is closed while its footer
# (a manifest of every chunk, written on close: about 2 % of the file) still fits.
# A write that fails instead leaves a file without a footer, which `rerun rrd verify`
# rejects, and rerun-sdk 0.41's file writer, once failed, can hang the process when
# the recording is dropped or at exit; so it is not left to fail.
RRD_DISK_RESERVE_BYTES = 1 << 20
RRD_FOOTER_SHARE = 0.05  # of the file's size so far, on top of the reserve
# …and twice the most the file grew between two checks (the next batch must fit too)


class ViewerError(Exception):
    """A recording that cannot be written (the message says why)."""


@dataclass(frozen=True)
class ViewerRequest:
    """What the user asked for (``--rrd``, ``--rerun MODE[=URL]``, ``--rerun-bind``)."""

    rrd: Path | None = None
    mode: str | None = None  # None, "spawn", "connect", "serve"
    url: str | None = None  # connect: the viewer's gRPC URL
    bind: str = "127.0.0.1"  # spawn/serve: the address the viewer listens on
    grpc_port: int = DEFAULT_GRPC_PORT
    web_port: int = DEFAULT_WEB_PORT

    @property
    def wanted(self) -> bool:
        return self.rrd is not None or self.mode is not None


def grpc_url(host: str, port: int) -> str:
    return f"rerun+http://{host}:{port}/proxy"


def rerun_binary() -> str | None:
    """The viewer executable of the installed rerun-sdk, else a ``rerun`` on PATH.

    The wheel's own binary, not the ``rerun`` script beside Python: that script is a
    Python shim that starts the binary as its child, so stopping the shim would
    leave the viewer running.
    """
    try:
        import rerun_cli

        shipped = Path(rerun_cli.__file__).parent / "rerun"
        if shipped.exists():
            return str(shipped)
    except ImportError:
        pass
    beside = Path(sys.executable).parent / "rerun"
    if beside.exists():
        return str(beside)
    return shutil.which("rerun")


def _reachable(url: str, timeout: float = 0.2) -> bool:
    parsed = urlparse(url.replace("rerun+http", "http", 1))
    try:
        with socket.create_connection((parsed.hostname or "127.0.0.1", parsed.port or 80), timeout):
            return True
    except OSError:
        return False


class Viewer:
    """A recording stream with its sinks, and the viewer process mavest started (if any)."""

    def __init__(self, request: ViewerRequest, application: str = "mavest") -> None:
        # imported here: rerun-sdk takes a second to import, which a run without a
        # viewer or a recording should not pay
        import rerun as rr

        self.request = request
        self.recording = rr.RecordingStream(application)
        self.process: subprocess.Popen[bytes] | None = None
        self.url: str | None = None
        self._said_gone = False
        self._roots: list[str] = []
        self._writing_file = False  # the FileSink is on and writing
        self._rrd_size = 0  # at the last space check
        self._largest_growth = 0  # between two space checks
        self._live_sink: rr.GrpcSink | None = None
        self._broken = False  # the file writer failed: the recording takes no more calls
        self.rrd_error: str | None = None  # why the .rrd stopped early, if it did
        sinks: list[rr.FileSink | rr.GrpcSink] = []
        if request.rrd is not None:
            try:  # (in an existing folder: a mistyped path is refused, as for --out-tlog)
                request.rrd.touch()
            except OSError as error:
                raise ViewerError(f"cannot write {request.rrd}: {error.strerror}") from None
            sinks.append(rr.FileSink(str(request.rrd)))
            self._writing_file = True
        if request.mode is not None:
            url = self._start_viewer()
            if url is not None:
                self.url = url
                self._live_sink = rr.GrpcSink(url)
                sinks.append(self._live_sink)
        if sinks:
            try:
                self.recording.set_sinks(*sinks)
            except RuntimeError as error:  # the file's header did not fit (a full disk)
                self._abandon()
                self._stop_process()
                raise ViewerError(f"cannot write {request.rrd}: {error}") from None

    @property
    def serving(self) -> bool:
        """Whether the web viewer mavest started for ``serve`` is up (it holds the data)."""
        return (
            self.request.mode == "serve"
            and self.process is not None
            and self.process.poll() is None
        )

    @property
    def active(self) -> bool:
        """Whether anything still takes the recording (the file or a live viewer)."""
        return not self._broken and (self._writing_file or self._live_sink is not None)

    # ------------------------------------------------------------ viewers

    def _start_viewer(self) -> str | None:
        request = self.request
        if request.mode == "connect":
            url = request.url or grpc_url("127.0.0.1", DEFAULT_GRPC_PORT)
            if not _reachable(url):
                log.warning(
                    "no Rerun viewer answers at %s; estimating on, will send when it does", url
                )
            else:
                log.info("streaming to the Rerun viewer at %s", url)
            return url
        binary = rerun_binary()
        if binary is None:
            log.warning("the rerun viewer executable was not found: no live viewer")
            return None
        if request.mode == "spawn" and sys.platform.startswith("linux"):
            if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                log.warning(
                    "no display to open a viewer on: use --rerun serve and a browser, or --rrd"
                )
                return None
        command = [binary, "--bind", request.bind, "--port", str(request.grpc_port)]
        if request.mode == "serve":
            command += ["--serve-web", "--web-viewer-port", str(request.web_port)]
        else:
            command += ["--hide-welcome-screen", "--expect-data-soon"]
        # its messages go to a file, never to a pipe nobody reads (a full pipe would stall it)
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 - lives as long as the viewer
        try:
            self.process = subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr
            )
        except OSError as error:
            log.warning("cannot start the Rerun viewer: %s", error)
            return None
        # a viewer bound to every interface is still reached here through loopback
        host = "127.0.0.1" if request.bind in ("0.0.0.0", "::") else request.bind
        url = grpc_url(host, request.grpc_port)
        deadline = time.monotonic() + 10.0
        while not _reachable(url):
            if self.process.poll() is not None or time.monotonic() > deadline:
                reason = self._process_error()
                log.warning("the Rerun viewer did not start%s; estimating on", reason)
                self._stop_process()
                return None
            time.sleep(0.05)
        if request.mode == "serve":
            log.info(
                "Rerun web viewer: http://%s:%d/?url=%s (bound to %s only)",
                host,
                request.web_port,
                url,
                request.bind,
            )
        else:
            log.info("Rerun viewer started (gRPC %s)", url)
        return url

    def _process_error(self) -> str:
        if self.process is None or self.process.poll() is None:
            return ""
        self._stderr.seek(0)
        text = self._stderr.read().decode(errors="replace").strip().splitlines()
        return f": {text[-1]}" if text else f" (exit code {self.process.returncode})"

    def _stop_process(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5)
        self.process = None

    def check(self) -> None:
        """Say once if the live viewer went away (called by the service's timer)."""
        if self._said_gone or self.url is None:
            return
        gone = (self.process is not None and self.process.poll() is not None) or (
            self.process is None and not _reachable(self.url)
        )
        if gone:
            self._said_gone = True
            log.warning("the Rerun viewer went away; estimating on (the .rrd, if any, continues)")

    # ------------------------------------------------------------ the file

    def check_space(self) -> None:
        """Close the .rrd, complete, when its disk is about to fill up (called often:
        by the service's timer, and every few hundred records on replay)."""
        rrd = self.request.rrd
        if rrd is None or not self._writing_file or self._broken:
            return
        try:
            free, reserve = self._room(rrd)
            if free < 2 * reserve:
                # near: decide on what the file holds, with what Rerun's batcher had yet
                # to write (a batch can be a few hundred kB) written
                self.flush()
                if self._broken or not self._writing_file:
                    return
                free, reserve = self._room(rrd)
        except OSError:
            return
        if free >= reserve:
            return
        self._writing_file = False
        try:
            self.recording.flush(timeout_sec=5.0)
            if self._live_sink is not None:  # dropping the FileSink writes its footer
                self.recording.set_sinks(self._live_sink)
            else:
                self.recording.disconnect()
        except RuntimeError as error:
            self._file_failed(error)
            return
        self.rrd_error = f"stopped with {free // 1024} kB left on its disk"
        log.error(
            "%s: only %d kB left on its disk: the recording stops here, complete (estimating on)",
            rrd,
            free // 1024,
        )

    def _room(self, rrd: Path) -> tuple[int, float]:
        """The free bytes on the .rrd's disk, and those it must keep (see
        :data:`RRD_DISK_RESERVE_BYTES`). The growth counted is the file's own, not the
        disk's: another program writing there must not close the recording early."""
        free = shutil.disk_usage(rrd.parent).free
        size = rrd.stat().st_size
        self._largest_growth = max(self._largest_growth, size - self._rrd_size)
        self._rrd_size = size
        reserve = RRD_DISK_RESERVE_BYTES + RRD_FOOTER_SHARE * size + 2 * self._largest_growth
        return free, reserve

    def _file_failed(self, error: RuntimeError) -> None:
        """The file writer gave up (a disk filled faster than :meth:`check_space` saw)."""
        rrd = self.request.rrd
        self._writing_file = False
        self._abandon()
        cause = str(error)
        with contextlib.suppress(OSError):
            if rrd is not None and shutil.disk_usage(rrd.parent).free < RRD_DISK_RESERVE_BYTES:
                cause = f"no space left on device ({error})"
        self.rrd_error = f"cannot write: {cause}"
        log.error(
            "cannot write %s: %s; the recording stops here without its footer "
            "(`rerun rrd optimize %s > repaired.rrd` recovers what it holds); estimating on",
            rrd,
            cause,
            rrd,
        )

    def _abandon(self) -> None:
        """Never call the recording again, and keep it from being dropped: rerun-sdk 0.41
        can hang for ever flushing a file writer that failed, when the recording is
        dropped or at exit (its exit hook flushes every recording)."""
        import rerun as rr

        self._broken = True
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(self.recording))
        rr.unregister_shutdown()

    # ------------------------------------------------------------ recording

    def add_stream(self, root: str) -> None:
        """A new IMU stream: send the default layout with its views."""
        from mavest.viz.blueprint import blueprint

        self._roots.append(root)
        if self._broken:
            return
        with contextlib.suppress(RuntimeError):
            self.recording.send_blueprint(
                blueprint(self._roots), make_active=True, make_default=True
            )

    def flush(self) -> None:
        """Push buffered data to the sinks; a viewer that cannot take it is reported once."""
        if self._broken:
            return
        try:
            self.recording.flush(timeout_sec=2.0)
        except RuntimeError as error:
            if self._writing_file and self._is_file_error(error):
                self._file_failed(error)
            elif not self._said_gone:  # the gRPC sink gave up on an unreachable viewer
                self._said_gone = True
                log.warning("the Rerun viewer is unreachable (%s); estimating on", error)

    def close(self) -> None:
        """Flush everything; a viewer mavest served for the browser goes with mavest, a
        spawned desktop viewer stays open for the user."""
        self.flush()
        if not self._broken:
            with contextlib.suppress(RuntimeError):
                self.recording.disconnect()
        if self.request.mode == "serve":
            self._stop_process()

    def _is_file_error(self, error: RuntimeError) -> bool:
        """Whether a failed flush is the file's: rerun names its file writer, or says it
        timed out, which with no live viewer can only be the file."""
        text = str(error).lower()
        return "file" in text or self._live_sink is None
