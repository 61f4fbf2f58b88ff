"""The errors of the onboard-log readers: a file they cannot use, and a part of one left out."""

from __future__ import annotations


class OnboardLogError(Exception):
    """A file that is not a usable onboard log; the message is one line, for the user."""


class FieldError(ValueError):
    """A field (a DataFlash column, a ULog topic's field) a message type or topic lacks or
    holds as something other than a number, in a damaged or odd log: what is read from
    that message type or topic is left out, with a note, and the rest of the log read."""
