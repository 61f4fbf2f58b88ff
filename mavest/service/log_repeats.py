"""Repeated log lines, rate-limited and counted.

A log that repeats one event (a stream at 2 Hz re-aligns on every sample: "no
samples for 2.01 s: attitude re-aligned", seventy times a replay) hides the
lines that matter. :class:`RepeatLimiter` lets the first few lines of each kind
through in each period and counts the rest; the next line of that kind to pass
says how many were held back, and :meth:`RepeatLimiter.report` tells the totals
still untold at the end of a run. A kind is the message's template (``%s``
before the arguments are put in), so one rule covers every stream.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

# A record with this attribute true (``extra={UNLIMITED: True}``) always passes: a line
# of a list whose lines share a template but not a subject (each failed log of a fleet).
UNLIMITED = "unlimited"


@dataclass
class _Window:
    start: float
    shown: int = 1
    held: int = 0  # lines of this kind held back since one was last shown
    last: str = ""  # the last of them, as it would have read


class RepeatLimiter(logging.Filter):
    """At most ``burst`` lines of one kind every ``period`` seconds pass."""

    def __init__(self, burst: int = 3, period: float = 30.0) -> None:
        super().__init__()
        self.burst = burst
        self.period = period
        self._windows: dict[tuple[str, int, str], _Window] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, UNLIMITED, False):  # (a list of distinct things, each once)
            return True
        key = (record.name, record.levelno, str(record.msg))
        now = time.monotonic()
        window = self._windows.get(key)
        if window is None:
            self._windows[key] = _Window(now)
            return True
        if now - window.start >= self.period:
            held = window.held
            self._windows[key] = _Window(now)
            if held:
                record.msg = f"{record.msg} ({held} more like this not shown)"
            return True
        if window.shown < self.burst:
            window.shown += 1
            return True
        window.held += 1
        window.last = record.getMessage()
        return False

    def reset(self) -> None:
        """Forget every kind (a new run in the same process starts afresh)."""
        self._windows.clear()

    def report(self, logger: logging.Logger) -> None:
        """Tell, once, how many lines of each kind are held back and untold."""
        for (_, level, _), window in list(self._windows.items()):
            if window.held:
                logger.log(
                    level,
                    "%d more lines like this not shown, the last: %s",
                    *(window.held, window.last),
                )
                window.held = 0
