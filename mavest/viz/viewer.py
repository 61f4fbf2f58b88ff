"""Where a recording goes: an .rrd file, a viewer on this machine, one already running,
or a served web viewer; any of them together.

The Python SDK's own ``serve_grpc``/``serve_web_viewer`` listen on every
interface. mavest never does that unasked: for ``serve`` (and ``spawn``) it
starts the ``rerun`` binary shipped in the rerun-sdk wheel with ``--bind``
(127.0.0.1 unless ``bind`` says otherwise) and streams to it over gRPC. A
viewer that cannot start, or goes away later, is reported once; the estimator
and the file go on.
"""

from __future__ import annotations

import contextlib
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
from urllib.parse import urlparse

import rerun as rr

from mavest.viz.blueprint import blueprint

log = logging.getLogger("mavest")

VIEWER_MODES = ("spawn", "connect", "serve")
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090


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
        self.request = request
        self.recording = rr.RecordingStream(application)
        self.process: subprocess.Popen[bytes] | None = None
        self.url: str | None = None
        self._said_gone = False
        self._roots: list[str] = []
        sinks: list[rr.FileSink | rr.GrpcSink] = []
        if request.rrd is not None:
            try:
                request.rrd.parent.mkdir(parents=True, exist_ok=True)
                request.rrd.touch()
            except OSError as error:
                raise ViewerError(f"cannot write {request.rrd}: {error.strerror}") from None
            sinks.append(rr.FileSink(str(request.rrd)))
        if request.mode is not None:
            url = self._start_viewer()
            if url is not None:
                self.url = url
                sinks.append(rr.GrpcSink(url))
        if sinks:
            self.recording.set_sinks(*sinks)

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

    # ------------------------------------------------------------ recording

    def add_stream(self, root: str) -> None:
        """A new IMU stream: send the default layout with its views."""
        self._roots.append(root)
        with contextlib.suppress(RuntimeError):
            self.recording.send_blueprint(
                blueprint(self._roots), make_active=True, make_default=True
            )

    def flush(self) -> None:
        """Push buffered data to the sinks; a viewer that cannot take it is reported once."""
        try:
            self.recording.flush(timeout_sec=2.0)
        except RuntimeError as error:  # the gRPC sink gave up on an unreachable viewer
            if not self._said_gone:
                self._said_gone = True
                log.warning("the Rerun viewer is unreachable (%s); estimating on", error)

    def close(self) -> None:
        """Flush everything; a viewer mavest served for the browser goes with mavest, a
        spawned desktop viewer stays open for the user."""
        self.flush()
        with contextlib.suppress(RuntimeError):
            self.recording.disconnect()
        if self.request.mode == "serve":
            self._stop_process()
