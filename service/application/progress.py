"""A job's progress as the caller sees it: a fraction that only moves forward.

A job is made of stages whose own progress callbacks start from zero (the avatar fit, then the
garment fit, then the basis); mapped into shares of the whole they may still report a little
less than the previous stage's last word. :class:`MonotoneProgress` keeps the reported fraction
non-decreasing, so a progress bar never goes back.
"""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[float, str], None]


class MonotoneProgress:
    """Wraps a :data:`Progress` callback; ``value`` is the last fraction reported.

    ``self(f, m)`` reports ``max(f, value)`` clipped to ``[0, ceiling]``; a call that would not
    move the fraction still passes a new message on. ``scaled(start, span)`` is a callback for a
    stage that covers ``[start, start + span]`` of the whole."""

    def __init__(self, report: Progress, start: float = 0.0, ceiling: float = 1.0):
        self.report = report
        self.value = float(start)
        self.ceiling = float(ceiling)

    def __call__(self, fraction: float, message: str = "") -> None:
        value = min(max(float(fraction), self.value), self.ceiling)
        if value > self.value or message:
            self.value = value
            self.report(value, message)

    def scaled(self, start: float, span: float, prefix: str = "") -> Progress:
        def stage(fraction: float, message: str = "") -> None:
            self(start + span * min(max(float(fraction), 0.0), 1.0), f"{prefix}{message}" if message else "")
        return stage
