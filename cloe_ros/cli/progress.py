"""A small progress bar on stderr for long runs (a line per 10% when stderr is not a terminal)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressBar:
    """``bar(stage, fraction)`` redraws ``stage [#####.....]  50%  12.3 s`` on one line.

    Args:
        stream: Where to draw (stderr by default).
        enabled: Draw nothing when False (``--quiet``).

    """

    def __init__(self, stream: TextIO | None = None, enabled: bool = True) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, 'isatty', lambda: False)())
        self._stage: str | None = None
        self._last_decile = -1
        self._start = time.monotonic()

    def __call__(self, stage: str, fraction: float) -> None:
        if not self.enabled:
            return
        fraction = min(max(fraction, 0.0), 1.0)
        if stage != self._stage:
            self._finish_line()
            self._stage, self._last_decile, self._start = stage, -1, time.monotonic()
        elapsed = time.monotonic() - self._start
        if self.tty:
            filled = int(30 * fraction)
            bar = '#' * filled + '.' * (30 - filled)
            self.stream.write(f'\r{stage:<28} [{bar}] {100 * fraction:5.1f}% {elapsed:6.1f} s')
            self.stream.flush()
        else:
            decile = int(10 * fraction)
            if decile > self._last_decile:
                self._last_decile = decile
                self.stream.write(f'{stage}: {100 * fraction:.0f}% ({elapsed:.1f} s)\n')
                self.stream.flush()

    def _finish_line(self) -> None:
        if self.tty and self._stage is not None:
            self.stream.write('\n')
            self.stream.flush()

    def close(self) -> None:
        """End the current line."""
        if self.enabled:
            self._finish_line()
        self._stage = None
