"""The algorithms: their names, and the estimator of each behind one constructor.

The names need no import of the estimators (which bring the compiled kernels, or numba), so that
the command line can offer them without that cost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cloe_ros.settings import ALGORITHMS

if TYPE_CHECKING:
    from cloe_ros.core.cloe_iv import CloeIvEstimator
    from cloe_ros.core.estimator import CloeEstimator, EstimatorConfig

__all__ = ['ALGORITHMS', 'PAPER_ALGORITHMS', 'load_estimator', 'make_estimator']

#: Algorithms implemented exactly as the paper states them (``ALGORITHMS``, a setting's choices,
#: adds CLOE-SM with the IV identifier of cloe_ros.core.cloe_iv).
PAPER_ALGORITHMS = ('cloe', 'cloe_sm')


def load_estimator(algorithm: str) -> None:
    """Import the estimator of ``algorithm`` and the compiled kernels its steps call (loaded, or
    compiled where no cache has them yet), so that no message waits on that: an engine calls it
    when it is made and when its algorithm changes, a node before it subscribes. (Cheap once
    loaded: the modules are then in ``sys.modules``.)"""
    from cloe_ros.core import estimator  # noqa: F401 (cloe and cloe_sm)

    if algorithm == 'cloe_iv':
        from cloe_ros.core import cloe_iv  # noqa: F401


def make_estimator(
    config: EstimatorConfig, zeta0: np.ndarray, r0: np.ndarray, h: float
) -> CloeEstimator | CloeIvEstimator:
    """The estimator for ``config.algorithm``, started at ``zeta0`` (N, 12) with the reference
    ``r0`` (N, 4), stepping ``h`` s."""
    if config.algorithm == 'cloe_iv':
        from cloe_ros.core.cloe_iv import CloeIvEstimator

        return CloeIvEstimator(config, zeta0, r0, h)
    from cloe_ros.core.estimator import CloeEstimator

    return CloeEstimator(config, zeta0)
