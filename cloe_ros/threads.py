"""One BLAS thread per process: the package's processes call :func:`limit_blas_threads` first.

The estimator's arrays are small (12 states, 16 parameters, a few hundred samples in a fit), too
small for a BLAS library to gain from threads. OpenBLAS, numpy's BLAS, still hands the larger of
them to its worker threads, which then spin while they wait for more work: offline, ``cloe infer``
on a 140 s flight took 25.6 s of CPU for 16.0 s of wall time, 16.8 s of CPU with one thread in
the same wall time. Beside a DDS process, another test worker, or the other shards of a swarm on
one host, that spinning takes a core from work that needs it.

The nodes (``cloe_ros.ros.common.run_node``) and the ``cloe`` command limit BLAS to one thread
unless the user chose a number (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or
``MKL_NUM_THREADS`` set). The library itself never does: a program that imports ``cloe_ros``
keeps the threads it has.
"""

from __future__ import annotations

import os

#: Environment variables by which a user sets the BLAS threads; any one set is left as it is.
BLAS_THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')


def limit_blas_threads() -> bool:
    """Run BLAS on this process's thread alone, unless the environment sets its threads.

    Libraries loaded already (numpy's) are limited through threadpoolctl; ones loaded later
    (scipy's own OpenBLAS), and the processes this one starts, read ``OPENBLAS_NUM_THREADS``.
    Returns whether the limit was set.
    """
    if any(os.environ.get(name) for name in BLAS_THREAD_VARIABLES):
        return False
    os.environ['OPENBLAS_NUM_THREADS'] = '1'
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api='blas')
    return True
