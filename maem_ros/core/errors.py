"""The one input-error type: bad input a stage refuses, with a short ``reason`` code.

Every decoder, backend and validator raises a subclass (ros.wire.WireError,
core.interchange.MissingDataError, core.limits.LimitError); a node counts the frame as dropped
under ``reason`` in /diagnostics without matching exception class names.
"""

from __future__ import annotations


class InputError(ValueError):
    """Input that cannot be processed: one-line message naming the input, plus ``reason``
    (snake_case, the /diagnostics ``dropped/<reason>`` key)."""

    reason: str = "bad_input"

    def __init__(self, message: str, reason: str | None = None):
        super().__init__(message)
        if reason is not None:
            self.reason = reason
