"""Stopping on SIGINT/SIGTERM, the way a service should: finish, flush, exit 0 (or, for
a command that ends on its own, 130 with what it wrote valid)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
from collections.abc import Iterator

# Ctrl-C, a polite kill, and the terminal closed (SIGHUP's default would end the run
# where it stands, its recording without its footer and its table a hidden part)
STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


@contextlib.contextmanager
def stop_on_signals(stop: asyncio.Event | None = None) -> Iterator[asyncio.Event]:
    """The event to stop on: ``stop`` when the caller has one, else an event that
    SIGINT, SIGTERM and SIGHUP set while the block runs (inside a running event loop,
    in the main thread).

    The handlers are the signal module's, not the loop's (``add_signal_handler``):
    the loop hands a signal back by installing the interpreter's default first, so a
    second Ctrl-C in that instant, as the run closes, would end it with its summary
    unsaid. Here the handler goes straight from ours to the next one."""
    if stop is not None:
        yield stop
        return
    event = asyncio.Event()
    loop = asyncio.get_running_loop()

    def handler(signum: int, frame: object) -> None:
        # (run by the interpreter in the main thread, between two steps of whatever it
        # was doing, the loop's own bookkeeping included: the event is set by the loop)
        loop.call_soon_threadsafe(event.set)

    previous = {signum: signal.signal(signum, handler) for signum in STOP_SIGNALS}
    try:
        yield event
    finally:
        # A signal still pending runs ours as its handler is replaced (the signal
        # module runs pending handlers first): none is lost in between.
        stopping = event.is_set()
        for signum, earlier in previous.items():
            if stopping and signum == signal.SIGINT:
                # Asked to stop, and stopping: a second Ctrl-C from here to the exit (the
                # summary, Rerun's own shutdown) would only print a traceback.
                earlier = signal.SIG_IGN
            # (None: a handler set outside Python, which cannot be put back)
            signal.signal(signum, signal.SIG_DFL if earlier is None else earlier)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM and SIGHUP end the block as Ctrl-C does (a KeyboardInterrupt: a file
    being written is removed or left whole, the exit code is 130), for a command that
    runs without an event loop (with one, :func:`stop_on_signals`). Only the main
    thread can set a handler: elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    others = [signum for signum in STOP_SIGNALS if signum != signal.SIGINT]
    previous = {signum: signal.signal(signum, interrupt) for signum in others}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
