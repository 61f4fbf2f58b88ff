"""The fleet on Dask: every log's :func:`~mavest.fleet.rows.log_rows` on a worker.

A LocalCluster of N worker processes, one thread each (the replay holds the GIL
between its compiled stretches: threads would take turns), or an existing cluster
by its scheduler's address. ``Client.map`` sends one task per log; the rows come
back as each finishes (``as_completed``) and are put in the logs' order, so the
table does not depend on which worker was quicker. A worker that dies mid-log
(killed, out of memory) is Dask's to handle: the scheduler gives its logs to
another worker; a log that has killed workers ``distributed.scheduler.allowed-failures``
+ 1 times (4 by default) is given up, and its row says so; the hidden files a dead
worker was writing that log's ``--out-dir`` outputs into are removed at the end. Ctrl-C
(or SIGTERM) stops waiting: the rows finished so far are the result, the rest is
cancelled; one while the local cluster starts stops the run once it has started (a
cluster half-made cannot be closed).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from multiprocessing import resource_tracker
from pathlib import Path
from typing import Any, TextIO

import dask.config
from distributed import Client, LocalCluster, Security, as_completed, get_worker
from distributed.comm.addressing import parse_address, parse_host_port
from distributed.scheduler import KilledWorker
from distributed.utils import sync

from mavest.fleet.rows import LogTask, error_row, log_rows, warm_up
from mavest.paths import partial_path
from mavest.service.runners import ProgressBar
from mavest.service.signals import STOP_SIGNALS, sigterm_interrupts

log = logging.getLogger("mavest")

# Dask's own loggers: quiet unless -v (what a run needs said, mavest says in its words:
# a log given up after its workers died is its row, and a line)
DASK_LOGGERS = ("distributed", "dask", "tornado", "bokeh")

# The scheduler's event topic on which a worker process says, before it writes a log's
# outputs, that it is one of a run's (its pid names the hidden files it writes them into)
WRITERS_TOPIC = "mavest-fleet-writers"

# The schemes mavest connects to a scheduler by, for the messages
SCHEDULER_ADDRESSES = "tcp://HOST:PORT, or tls://HOST:PORT with Dask's TLS settings"


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
    """Dask's loggers at ``level`` within: :data:`DASK_LOGGERS`, and those below them
    that have a level of their own (Dask's configuration gives ``distributed.client``
    one, and a handler: the level of ``distributed`` is not theirs)."""
    names = [
        name
        for name, logger in logging.Logger.manager.loggerDict.items()
        if isinstance(logger, logging.Logger)
        and logger.level != logging.NOTSET
        and name.startswith(tuple(f"{root}." for root in DASK_LOGGERS))
    ]
    loggers = [logging.getLogger(name) for name in (*DASK_LOGGERS, *names)]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(level)
    try:
        yield
    finally:
        for logger, old in zip(loggers, levels, strict=True):
            logger.setLevel(old)


def fleet_log_rows(task: LogTask, run: str) -> list[dict[str, Any]]:
    """:func:`~mavest.fleet.rows.log_rows` on a worker of the run ``run``, which is told
    first (:func:`_announce`) that this process writes its logs' outputs."""
    if task.rrd is not None or task.estimates is not None:
        _announce(run)
    return log_rows(task)


# The runs this process has told the scheduler of (once each is enough)
_announced: set[str] = set()


def _announce(run: str) -> None:
    """Tell the scheduler that this worker process writes outputs of ``run``, and wait
    for it to have heard: a worker killed a moment later has named itself before any
    hidden file of its own (:func:`_partials`) was made."""
    if run in _announced:
        return
    try:
        worker = get_worker()
        message = {"run": run, "pid": os.getpid()}
        sync(worker.loop, worker.scheduler.log_event, topic=WRITERS_TOPIC, msg=message)
    except Exception as error:  # (its partial files could be left: not the log's failure)
        log.debug("cannot tell the scheduler of this worker: %s", error)
        return
    _announced.add(run)


def _writers(client: Client, run: str) -> set[int]:
    """The pids of the worker processes that wrote (or began to write) outputs of
    ``run``, dead ones too."""
    try:
        events = client.get_events(WRITERS_TOPIC)
    except Exception:  # (a scheduler gone: nothing known, nothing removed)
        return set()
    return {
        message["pid"]
        for _, message in events
        if isinstance(message, dict) and message.get("run") == run
    }


def _partials(task: LogTask, pids: set[int]) -> Iterator[Path]:
    """The hidden files the processes ``pids`` would write the task's outputs into: an
    output's partial file, and that file's own (the estimates table rewritten with its
    smoothed columns)."""
    for output in (task.rrd, task.estimates):
        if output is None:
            continue
        for pid in pids:
            partial = partial_path(output, pid)
            yield partial
            yield partial_path(partial, pid)


def _remove_partials(tasks: Iterable[LogTask], pids: set[int]) -> None:
    """What the workers ``pids`` of a run left of the tasks' outputs: their partial files
    (a worker killed mid-log, one stopped with Ctrl-C), and only those: a file of a
    user's, or of another run's writer, has another name."""
    for task in tasks:
        for partial in _partials(task, pids):
            with contextlib.suppress(OSError):
                partial.unlink(missing_ok=True)


def _check_address(scheduler: str) -> Security | None:
    """Refuse (:class:`FleetError`) an address mavest does not connect by, before a
    Client is made (one that fails on it is left half-made, and hangs at exit); the
    security to connect with (None: Dask's own, a security loader's)."""
    try:
        scheme, location = parse_address(scheduler)
    except ValueError as error:
        raise FleetError(f"--scheduler {scheduler}: {error} ({SCHEDULER_ADDRESSES})") from None
    if scheme not in ("tcp", "tls"):
        dashboard = " (http:// is a dashboard's)" if scheme in ("http", "https") else ""
        raise FleetError(
            f"--scheduler {scheduler}: not a scheduler's address{dashboard}: "
            f"give {SCHEDULER_ADDRESSES}"
        )
    try:
        parse_host_port(location)
    except ValueError as error:
        raise FleetError(f"--scheduler {scheduler}: {error} (tcp://HOST:PORT)") from None
    if scheme == "tcp" or dask.config.get("distributed.client.security-loader", None):
        return None
    try:
        security = Security()
        context = security.get_connection_args("client")["ssl_context"]
    except (OSError, ValueError) as error:  # (a file named that cannot be read)
        raise FleetError(f"--scheduler {scheduler}: Dask's TLS settings: {error}") from None
    if context is None:
        raise FleetError(
            f"--scheduler {scheduler}: tls:// needs Dask's TLS settings: "
            "distributed.comm.tls.ca-file and distributed.comm.tls.client.cert (and "
            ".client.key) in its configuration"
        )
    return security


def _connect(scheduler: str | None, workers: int, level: int) -> tuple[Client, LocalCluster | None]:
    if scheduler is not None:
        security = _check_address(scheduler)
        try:
            client = Client(scheduler, timeout="10s", set_as_default=False, security=security)
        except (OSError, ValueError, TypeError, TimeoutError) as error:
            raise FleetError(f"--scheduler {scheduler}: {error}") from None
        return client, None
    cluster = local_cluster(workers, level)
    try:
        return Client(cluster, set_as_default=False), cluster
    except BaseException:
        cluster.close(timeout=5)
        raise


def local_cluster(workers: int, level: int = logging.WARNING) -> LocalCluster:
    """A LocalCluster of ``workers`` processes of one thread each, its logs at ``level``
    (worker processes: none, unless ``level`` is below warnings)."""
    with _sigint_blocked():
        return LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            # the scheduler's HTTP endpoints (health, metrics) on a free port of this
            # machine only: not 8787 of every address, which another cluster may hold
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            # the worker processes' own logs: none (a log that fails is a row; a worker
            # stopped mid-run errs of the scheduler it lost, with a traceback), unless -v
            silence_logs=level if level < logging.WARNING else logging.CRITICAL,
        )


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread within, and so in the threads started within (the
    cluster's) and the processes they start (its workers, now and when one is restarted):
    Ctrl-C on a terminal reaches the whole process group, and it is mavest's to stop
    them, with the table written, not theirs to die with a traceback each. A Ctrl-C
    that reaches this thread meanwhile waits for the block's end."""
    # multiprocessing's resource tracker, started now if not yet: the thread that starts
    # it unblocks SIGINT after (the cluster's, were it started there)
    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def _stops_held() -> Iterator[None]:
    """A stop (Ctrl-C, SIGTERM, SIGHUP) held until the block's end, then delivered as it
    would have been (a KeyboardInterrupt): a cluster (or Client) half-made when it comes
    can be neither used nor closed, and Dask's own closing of it at exit fails with a
    traceback. Only the main thread can set a handler: elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum: int, frame: object) -> None:
        held.append(signum)

    # (SIGINT's handler too: a thread started before, not blocking it, may be given it)
    previous = {signum: signal.signal(signum, hold) for signum in STOP_SIGNALS}
    with _sigint_blocked():  # (a Ctrl-C pending comes as it ends: after the handlers)
        try:
            yield
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
    for signum in dict.fromkeys(held):
        signal.raise_signal(signum)


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
    scheduler is at ``scheduler`` (:data:`SCHEDULER_ADDRESSES`), or through a Dask ``Client``
    given. ``on_done(n)`` is called after each log (n: logs done so far).

    :class:`FleetError` if the cluster cannot be reached; a log's failure is its row.
    """
    level = logging.INFO if verbose else logging.WARNING
    # Dask's logs in this process (a local cluster's scheduler is here): -v's, or none
    dask_level = logging.INFO if verbose else logging.CRITICAL
    total = len(tasks)
    result = FleetResult(total=total)
    finished: dict[int, list[dict[str, Any]]] = {}
    bar = Progress(total, enabled=progress)
    run = uuid.uuid4().hex
    writers: set[int] = set()
    with dask_logs(dask_level), sigterm_interrupts():
        own = not isinstance(scheduler, Client)
        client = None if own else scheduler
        cluster = None
        futures = []
        try:
            if client is None:
                with _stops_held():
                    client, cluster = _connect(scheduler, workers, level)
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
            futures = client.map(fleet_log_rows, list(tasks), run=run, pure=False)
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
            with dask_logs(logging.CRITICAL if result.interrupted else dask_level):
                if futures and result.interrupted:
                    with contextlib.suppress(Exception):
                        client.cancel(futures)
                if futures:  # (before the scheduler of a local cluster is gone)
                    writers = _writers(client, run)
                if own and client is not None:
                    with contextlib.suppress(Exception):
                        client.close(timeout=5)
                    if cluster is not None:
                        with contextlib.suppress(Exception):
                            cluster.close(timeout=5)
            # a log not finished may still be written on a cluster not ours (the task
            # cancelled runs on): its files are left to it; ours is closed, its workers gone
            done = range(total) if cluster is not None else sorted(finished)
            _remove_partials([tasks[i] for i in done], writers)
    result.done = len(finished)
    result.rows = [row for i in sorted(finished) for row in finished[i]]
    return result
