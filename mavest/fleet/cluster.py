"""The fleet on Dask: every log's :func:`~mavest.fleet.rows.log_rows` on a worker.

A LocalCluster of N worker processes, one thread each (the replay holds the GIL
between its compiled stretches: threads would take turns), or an existing cluster
by its scheduler's address. ``Client.map`` sends one task per log; the rows come
back as each finishes (``as_completed``) and are put in the logs' order, so the
table does not depend on which worker was quicker. A worker that dies mid-log
(killed, out of memory) is Dask's to handle: the scheduler gives its logs to
another worker; a log that has killed workers ``distributed.scheduler.allowed-failures``
+ 1 times (4 by default) is given up, and its row says so. Ctrl-C (or SIGTERM) stops
waiting: the rows finished so far are the result, the rest is cancelled.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

from distributed import Client, LocalCluster, as_completed
from distributed.comm.addressing import parse_address, parse_host_port
from distributed.scheduler import KilledWorker

from mavest.fleet.rows import LogTask, error_row, log_rows, warm_up
from mavest.paths import output_target
from mavest.service.runners import ProgressBar
from mavest.service.signals import sigterm_interrupts

log = logging.getLogger("mavest")

# Dask's own loggers: held to warnings (a worker lost, a retry) unless -v.
DASK_LOGGERS = ("distributed", "dask", "tornado", "bokeh")


class FleetError(Exception):
    """The fleet cannot run: no scheduler at that address, workers that cannot run mavest."""


@dataclass
class FleetResult:
    """The rows of the logs that finished, in the logs' order; whether all did."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    done: int = 0  # logs finished
    total: int = 0
    interrupted: bool = False


class Progress(ProgressBar):
    """A one-line bar on a terminal: logs done of all, logs per second, time left
    (nothing when the output is not a terminal)."""

    def __init__(self, total: int, stream: TextIO = sys.stderr, enabled: bool | None = None):
        super().__init__(stream, enabled)
        self.total = total

    def begin(self) -> None:
        """The logs start now (the rate is counted from here, not from the cluster's start)."""
        self.start = time.perf_counter()
        self.update(0)

    def update(self, done: int) -> None:
        now = time.perf_counter()
        if not self.due(now, final=done >= self.total):
            return
        rate = done / max(now - self.start, 1e-9)
        left = (self.total - done) / rate if rate > 0 else math.inf
        eta = f"{left:.0f} s left" if math.isfinite(left) else "…"
        self.draw(
            done / max(self.total, 1),
            f"{done} of {self.total} logs, {rate:.2f} logs/s, {eta}   ",
        )


@contextlib.contextmanager
def dask_logs(level: int) -> Iterator[None]:
    """Dask's loggers at ``level`` within."""
    loggers = [logging.getLogger(name) for name in DASK_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(level)
    try:
        yield
    finally:
        for logger, old in zip(loggers, levels, strict=True):
            logger.setLevel(old)


def _remove_partials(tasks: list[LogTask]) -> None:
    """The hidden files that the workers of a local cluster, stopped with Ctrl-C, were
    writing the logs' ``--out-dir`` outputs into (:func:`mavest.paths.partial_path`, named
    after the worker's process, so found by the output's name)."""
    for task in tasks:
        for output in (task.rrd, task.estimates):
            if output is None:
                continue
            target = output_target(output)
            for partial in target.parent.glob(f".{glob.escape(target.name)}.*.partial"):
                with contextlib.suppress(OSError):
                    partial.unlink()


def _connect(scheduler: str | None, workers: int, level: int) -> tuple[Client, LocalCluster | None]:
    if scheduler is not None:
        try:
            # the address first: a Client that fails on one is left to hang at exit
            scheme, location = parse_address(scheduler)
            if scheme in ("tcp", "tls"):
                parse_host_port(location)
        except ValueError as error:
            raise FleetError(f"--scheduler {scheduler}: {error} (tcp://HOST:PORT)") from None
        try:
            return Client(scheduler, timeout="10s", set_as_default=False), None
        except (OSError, ValueError, TimeoutError) as error:
            raise FleetError(f"--scheduler {scheduler}: {error}") from None
    cluster = local_cluster(workers, level)
    return Client(cluster, set_as_default=False), cluster


def local_cluster(workers: int, level: int = logging.WARNING) -> LocalCluster:
    """A LocalCluster of ``workers`` processes of one thread each, its logs at ``level``
    (worker processes: errors only, unless ``level`` is below warnings)."""
    with _workers_ignore_sigint():
        return LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            # the scheduler's HTTP endpoints (health, metrics) on a free port of this
            # machine only: not 8787 of every address, which another cluster may hold
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            # the worker processes' own logs: their errors (a log that fails is a row)
            silence_logs=level if level < logging.WARNING else logging.ERROR,
        )


@contextlib.contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """Worker processes started within ignore SIGINT (inherited through exec): Ctrl-C
    on a terminal reaches the whole process group, and it is mavest's to stop them, with
    the table written, not theirs to die with a traceback each."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _died(task: LogTask, error: BaseException) -> dict[str, Any]:
    if isinstance(error, KilledWorker):
        return error_row(
            task.source,
            "the workers replaying it died (more than distributed.scheduler.allowed-failures "
            "times): out of memory?",
        )
    return error_row(task.source, f"{type(error).__name__}: {error}")


def _collect_finished(futures: list[Any], finished: dict[int, list[dict[str, Any]]]) -> None:
    """After Ctrl-C: the rows of the logs done but not yet taken, if they come at once."""
    for i, future in enumerate(futures):
        if i not in finished and future.status == "finished":
            with contextlib.suppress(Exception):
                finished[i] = future.result(timeout=2)


def run_fleet(
    tasks: Sequence[LogTask],
    scheduler: str | Client | None = None,
    workers: int = 1,
    progress: bool | None = None,
    verbose: bool = False,
    on_done: Callable[[int], None] | None = None,
) -> FleetResult:
    """Every task's rows, on a LocalCluster of ``workers`` processes, on the cluster whose
    scheduler is at ``scheduler`` (``tcp://host:port``), or through a Dask ``Client``
    given. ``on_done(n)`` is called after each log (n: logs done so far).

    :class:`FleetError` if the cluster cannot be reached; a log's failure is its row.
    """
    level = logging.INFO if verbose else logging.WARNING
    total = len(tasks)
    result = FleetResult(total=total)
    finished: dict[int, list[dict[str, Any]]] = {}
    bar = Progress(total, enabled=progress)
    with dask_logs(level), sigterm_interrupts():
        own = not isinstance(scheduler, Client)
        cluster = None
        if isinstance(scheduler, Client):
            client = scheduler
        else:
            client, cluster = _connect(scheduler, workers, level)
        futures = []
        try:
            try:
                # each worker loads the kernels once, before its first log (and in
                # parallel): a later log never waits for them
                client.run(warm_up)
            except Exception as error:
                raise FleetError(
                    f"the workers cannot run mavest ({type(error).__name__}: {error}); "
                    "install mavest[fleet] where they run"
                ) from None
            if not client.scheduler_info()["workers"]:
                log.warning("the cluster has no worker yet: the logs wait for one")
            bar.begin()
            futures = client.map(log_rows, list(tasks), pure=False)
            index = {future.key: i for i, future in enumerate(futures)}
            for future in as_completed(futures, loop=client.loop):
                i = index[future.key]
                try:
                    finished[i] = future.result()
                except Exception as error:  # a worker lost for good on this log
                    finished[i] = [_died(tasks[i], error)]
                bar.update(len(finished))
                if on_done is not None:
                    on_done(len(finished))
        except KeyboardInterrupt:
            result.interrupted = True
            _collect_finished(futures, finished)
        finally:
            bar.finish()
            # stopping: what Dask says of the work cut short is no news
            with dask_logs(logging.CRITICAL if result.interrupted else level):
                if futures and result.interrupted:
                    with contextlib.suppress(Exception):
                        client.cancel(futures)
                if own:
                    with contextlib.suppress(Exception):
                        client.close(timeout=5)
                    if cluster is not None:
                        with contextlib.suppress(Exception):
                            cluster.close(timeout=5)
            if result.interrupted and cluster is not None:  # (its workers are gone)
                _remove_partials(tasks)
    result.done = len(finished)
    result.rows = [row for i in sorted(finished) for row in finished[i]]
    return result
