"""Repeated log lines, rate-limited and counted.

A log that repeats one event (a stream at 2 Hz re-aligns on every sample: "no
samples for 2.01 s: attitude re-aligned", seventy times a replay) hides the
lines that matter. :class:`RepeatLimiter` lets the first few lines of each kind
through in each period and counts the rest; the next line of that kind to pass
says how many were held back, and :meth:`RepeatLimiter.report` tells the totals
still untold at the end of a run. A kind is the message's template (``%s``
before the arguments are put in), so one rule covers every stream, and its
subject, the first argument of a line that begins with it (``"%s: …"``: the
stream, the vehicle, the log), so that one stream's repeats do not hide another's
first line. Up to ``subjects`` subjects of a kind are shown in a period, so that a
thousand vehicles (spoofed, or a fleet's logs) are not a thousand lines.
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

    def admit(self, limit: int, record: logging.LogRecord) -> bool:
        """One more line in this window: shown while fewer than ``limit`` were, else
        held back (and counted)."""
        if self.shown < limit:
            self.shown += 1
            return True
        self.held += 1
        self.last = record.getMessage()
        return False


class RepeatLimiter(logging.Filter):
    """At most ``burst`` lines of one kind and subject, and lines of at most ``subjects``
    subjects of one kind, every ``period`` seconds pass."""

    def __init__(self, burst: int = 3, period: float = 30.0, subjects: int = 10) -> None:
        super().__init__()
        self.burst = burst
        self.period = period
        self.subjects = subjects
        self._windows: dict[tuple[str, int, str, str], _Window] = {}
        # per kind: its subjects shown in the period (shown), the lines of others held
        self._kinds: dict[tuple[str, int, str], _Window] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, UNLIMITED, False):  # (a list of distinct things, each once)
            return True
        kind = (record.name, record.levelno, str(record.msg))
        args = record.args if isinstance(record.args, tuple) else ()
        subject = str(args[0]) if args and kind[2].startswith("%s") else ""
        now = time.monotonic()
        window = self._windows.get((*kind, subject))
        if window is None:
            if not self._new_subject(kind, now, record):
                return False
            self._windows[(*kind, subject)] = _Window(now)
            return True
        if now - window.start >= self.period:
            held = window.held
            self._windows[(*kind, subject)] = _Window(now)
            if held:
                record.msg = f"{record.msg} ({held} more like this not shown)"
            return True
        return window.admit(self.burst, record)

    def _new_subject(
        self, kind: tuple[str, int, str], now: float, record: logging.LogRecord
    ) -> bool:
        """Whether a subject not shown in this period may be (else its line is held)."""
        window = self._kinds.get(kind)
        if window is None or now - window.start >= self.period:
            self._kinds[kind] = _Window(now)
            return True
        return window.admit(self.subjects, record)

    def reset(self) -> None:
        """Forget every kind (a new run in the same process starts afresh)."""
        self._windows.clear()
        self._kinds.clear()

    def report(self, logger: logging.Logger) -> None:
        """Tell, once, how many lines of each kind are held back and untold."""
        for (_, level, *_), window in [*self._windows.items(), *self._kinds.items()]:
            if window.held:
                logger.log(
                    level,
                    "%d more lines like this not shown, the last: %s",
                    *(window.held, window.last),
                )
                window.held = 0
