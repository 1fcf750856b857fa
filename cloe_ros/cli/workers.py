"""The worker processes of a command with ``--jobs`` (``cloe infer BAG...``, ``cloe evaluate
corpus``): how many (:func:`worker_count`), and a pool of them that Ctrl-C stops cleanly
(:func:`pool`)."""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager

from cloe_ros.cli.errors import CliError
from cloe_ros.interrupts import uninterrupted


def worker_count(jobs: int, tasks: int) -> int:
    """``--jobs`` checked (0: one per core), and never more workers than ``tasks``."""
    if jobs < 0:
        raise CliError(f'--jobs must be >= 0 (0: one per core), got {jobs}')
    return max(1, min(jobs or os.cpu_count() or 1, tasks))


def _worker_start(initializer: Callable | None, initargs: tuple) -> None:
    """A worker of :func:`pool`: Ctrl-C is the parent's (it was blocked when the worker was
    forked: ignored, then unblocked), then ``initializer(*initargs)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if initializer is not None:
        initializer(*initargs)


@contextmanager
def pool(
    fn: Callable,
    work: Sequence,
    jobs: int,
    initializer: Callable | None = None,
    initargs: tuple = (),
    stop: Callable[[], None] | None = None,
) -> Iterator[list[Future]]:
    """``fn(job)`` for every job of ``work`` in ``jobs`` worker processes: yields the futures,
    in ``work``'s order, and shuts the pool down when the block ends.

    Ctrl-C is the parent's: the workers ignore it. One that comes while the pool starts and
    takes the work is held until it has taken all of it, then raised (cut short there, the pool
    would keep workers that no shutdown reaches, and the command would wait for them at exit).
    On Ctrl-C in the block: ``stop()`` (default: the workers are terminated; a job that must
    clean up after itself passes its own, e.g. setting an event its workers watch), the jobs not
    started are cancelled, the workers are waited for, with Ctrl-C ignored meanwhile
    (:func:`~cloe_ros.interrupts.uninterrupted`), and the KeyboardInterrupt goes on."""
    before = set(multiprocessing.active_children())
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    executor = None
    try:
        executor = ProcessPoolExecutor(max_workers=jobs, initializer=_worker_start,
                                       initargs=(initializer, initargs))  # fmt: skip
        futures = [executor.submit(fn, job) for job in work]
    except BaseException:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        raise
    # (every worker is started while the work is submitted: all at the first submit with fork)
    workers = set(multiprocessing.active_children()) - before
    try:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)  # (a Ctrl-C held is raised here)
        yield futures
    except KeyboardInterrupt:
        with uninterrupted():
            executor.shutdown(wait=False, cancel_futures=True)
            if stop is not None:
                stop()
            else:
                for process in workers:
                    process.terminate()
            executor.shutdown(wait=True)
            for process in workers:
                process.join()
        raise
    finally:
        with uninterrupted():
            executor.shutdown(wait=True)
