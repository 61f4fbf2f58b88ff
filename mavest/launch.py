"""The ``mavest`` command's entry point: Ctrl-C while the program loads ends it quietly.

Loading the filter (numba) and Rerun takes seconds; an interrupt then would
otherwise print a traceback from deep inside an import. Nothing is open yet,
so nothing is lost.
"""

from __future__ import annotations

import sys


def main() -> int:
    try:
        from mavest.cli import main as run
    except KeyboardInterrupt:
        print("mavest: interrupted while starting", file=sys.stderr)
        return 130
    return run()
