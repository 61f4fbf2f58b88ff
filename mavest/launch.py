"""The ``mavest`` command's entry point: Ctrl-C while the program loads ends it quietly.

Loading the filter (numba) and Rerun takes seconds; an interrupt then would
otherwise print a traceback from deep inside an import. Nothing is open yet,
so nothing is lost.

It also keeps OpenBLAS to one thread, unless the environment says otherwise
(``OPENBLAS_NUM_THREADS``). Every product the command makes is small: a second
thread never helped one, and OpenBLAS's idle threads spin after each, taking
the other core from the filter's thread (8 % of a replay's CPU time).
This must be set before numpy loads OpenBLAS, so here, not in the library.

The cyclic garbage collector is off while the program loads, and what loading
made is then frozen out of its reach: loading makes a few hundred thousand
objects (numba's types, pymavlink's dialect), none of them garbage, which the
collector would otherwise walk again and again, a tenth of a short replay's
time. Collection is on again before any input is read.

When the command is done, :func:`command` leaves without the interpreter's
teardown of every module it loaded, a fiftieth of a second after a replay
(numba's types and compiled code, pymavlink's dialect): what the user's files
need on the way out still runs first (the exit handlers: Rerun's flush, the
logging's), and the interpreter's own exit is kept whenever a thread of the
program is still running, which it would wait for.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import os
import sys
import threading
from typing import NoReturn


def main() -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    gc.disable()
    try:
        from mavest.cli import main as run
    except KeyboardInterrupt:
        print("mavest: interrupted while starting", file=sys.stderr)
        return 130
    finally:
        gc.freeze()
        gc.enable()
    return run()


def command() -> NoReturn:
    """The ``mavest`` command: :func:`main`, then out with its exit status."""
    leave(main())


def leave(code: int) -> NoReturn:
    """Exit with ``code`` after the exit handlers, skipping the modules' teardown."""
    others = [t for t in threading.enumerate() if t is not threading.main_thread()]
    # (the exit handlers' runner is the interpreter's own, not a documented function)
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    if any(not t.daemon for t in others) or run_exit_handlers is None:
        sys.exit(code)  # the interpreter's exit: it waits for those threads first
    run_exit_handlers()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # (a reader gone away: nothing to tell)
            stream.flush()
    os._exit(code)
