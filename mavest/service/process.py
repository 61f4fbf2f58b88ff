"""``mavest run`` as a separate process, as a user starts it: for the tests and the tools
that measure the live service from outside (a loopback vehicle on the other end)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path

# The command as the installed ``mavest`` script runs it (mavest.launch, which sets up
# the process before the program loads), with this interpreter.
MAVEST = [sys.executable, "-m", "mavest"]
READY_LINE = "mavest: listening on"


def mavest_command(tree: str | None = None) -> list[str]:
    """:data:`MAVEST` for the source tree ``tree`` (None: the installed one); a tree from
    before ``python -m mavest`` existed runs its ``mavest.cli`` (for comparisons with it)."""
    if tree is None:
        return MAVEST
    package = Path(tree) / "mavest"
    if package.is_dir() and not (package / "__main__.py").exists():
        return [sys.executable, "-m", "mavest.cli"]
    return MAVEST


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 free right now (TCP by default, ``SOCK_DGRAM`` for UDP)."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class ServiceProcess:
    """Starts ``mavest run ARGUMENTS`` and returns once it listens; ``log`` collects its
    standard error, :meth:`stop` sends SIGINT as Ctrl-C would. ``env``: its environment
    (default: this process's), e.g. another PYTHONPATH to run another version of mavest;
    ``cwd``: its working directory — with ``python -m`` that comes first on sys.path,
    before PYTHONPATH, so another version needs to run from its own tree."""

    def __init__(
        self,
        *arguments: str,
        start_timeout: float = 180.0,
        env: Mapping[str, str] | None = None,
        cwd: str | None = None,
    ) -> None:
        self.process = subprocess.Popen(
            [*mavest_command(cwd), "run", *arguments],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=cwd,
        )
        self.log: list[str] = []
        self._ready = threading.Event()
        threading.Thread(target=self._read_log, daemon=True).start()
        deadline = time.monotonic() + start_timeout  # a cold numba cache compiles first
        while not self._ready.wait(0.1):
            # a process that ended (a mistake, a crash) is not waited for until the deadline
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.process.kill()
                self.process.wait()
                time.sleep(0.1)  # its last lines, read by the thread
                raise RuntimeError("mavest run did not start: " + "".join(self.log))

    def _read_log(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.log.append(line)
            if line.startswith(READY_LINE):
                self._ready.set()

    def stop(self, timeout: float = 60.0) -> tuple[int, str]:
        """Interrupt it; its exit code and what it printed (the summary)."""
        self.process.send_signal(signal.SIGINT)
        out, _ = self.process.communicate(timeout=timeout)
        return self.process.returncode, out
