"""Cleanup that a second Ctrl-C must not cut short (:func:`uninterrupted`): a command's process
pool being shut down and its unfinished outputs removed, a node being destroyed (the recorder
closing its bag)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def uninterrupted(*signals: int) -> Iterator[None]:
    """``signals`` (default: SIGINT, Ctrl-C) ignored while the block runs: the cleanup after a
    first one, which a second must not cut short (an output half removed or a bag not closed;
    on Python 3.11 a KeyboardInterrupt in the join of a process pool's thread leaves the pool
    shut down half-way, its workers waiting for work and the command waiting for them, for
    ever). One that comes meanwhile is dropped: the process is stopping already. Signals are the
    main thread's; in another thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = signals or (signal.SIGINT,)
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in signals}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
