"""The one error an onboard-log reader raises for a file it cannot use."""

from __future__ import annotations


class OnboardLogError(Exception):
    """A file that is not a usable onboard log; the message is one line, for the user."""
