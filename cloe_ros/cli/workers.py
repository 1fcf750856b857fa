"""How many worker processes a command with ``--jobs`` runs (``cloe infer BAG...``, ``cloe
evaluate corpus``)."""

from __future__ import annotations

import os

from cloe_ros.cli.errors import CliError


def worker_count(jobs: int, tasks: int) -> int:
    """``--jobs`` checked (0: one per core), and never more workers than ``tasks``."""
    if jobs < 0:
        raise CliError(f'--jobs must be >= 0 (0: one per core), got {jobs}')
    return max(1, min(jobs or os.cpu_count() or 1, tasks))
