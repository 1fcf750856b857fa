"""The algorithms: their names, and the estimator of each behind one constructor.

The names need no import of the estimators (which bring scipy), so that the command line can offer
them without that cost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cloe_ros.settings import ALGORITHMS

if TYPE_CHECKING:
    from cloe_ros.core.cloe_iv import CloeIvEstimator
    from cloe_ros.core.estimator import CloeEstimator, EstimatorConfig

__all__ = ['ALGORITHMS', 'PAPER_ALGORITHMS', 'make_estimator']

#: Algorithms implemented exactly as the paper states them (``ALGORITHMS``, a setting's choices,
#: adds CLOE-SM with the IV identifier of cloe_ros.core.cloe_iv).
PAPER_ALGORITHMS = ('cloe', 'cloe_sm')


def make_estimator(
    config: EstimatorConfig, zeta0: np.ndarray, r0: np.ndarray, h: float
) -> CloeEstimator | CloeIvEstimator:
    """The estimator for ``config.algorithm``, started at ``zeta0`` (N, 12) with the reference
    ``r0`` (N, 4), stepping ``h`` s."""
    from cloe_ros.core.cloe_iv import CloeIvEstimator
    from cloe_ros.core.estimator import CloeEstimator

    if config.algorithm == 'cloe_iv':
        return CloeIvEstimator(config, zeta0, r0, h)
    return CloeEstimator(config, zeta0)
