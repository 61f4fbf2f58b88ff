"""Stopping a coroutine on SIGINT/SIGTERM, the way a service should: finish, flush, exit 0."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_on_signals(stop: asyncio.Event | None = None) -> Iterator[asyncio.Event]:
    """The event to stop on: ``stop`` when the caller has one, else an event that
    SIGINT and SIGTERM set while the block runs (inside a running event loop)."""
    if stop is not None:
        yield stop
        return
    event = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in STOP_SIGNALS:
        loop.add_signal_handler(signum, event.set)
    try:
        yield event
    finally:
        for signum in STOP_SIGNALS:
            loop.remove_signal_handler(signum)
        if event.is_set():
            # Asked to stop, and stopping: a second Ctrl-C from here to the exit (the
            # summary, Rerun's own shutdown) would only print a traceback.
            signal.signal(signal.SIGINT, signal.SIG_IGN)
