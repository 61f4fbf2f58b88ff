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
"""

from __future__ import annotations

import gc
import os
import sys


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
