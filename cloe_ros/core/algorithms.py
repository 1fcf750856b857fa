"""The estimator of each algorithm, behind one constructor."""

from __future__ import annotations

import numpy as np

from cloe_ros.core.cloe_iv import CloeIvEstimator
from cloe_ros.core.estimator import ALGORITHMS, CloeEstimator, EstimatorConfig

__all__ = ['ALGORITHMS', 'make_estimator']


def make_estimator(
    config: EstimatorConfig, zeta0: np.ndarray, r0: np.ndarray, h: float
) -> CloeEstimator | CloeIvEstimator:
    """The estimator for ``config.algorithm``, started at ``zeta0`` (N, 12) with the reference
    ``r0`` (N, 4), stepping ``h`` s."""
    if config.algorithm == 'cloe_iv':
        return CloeIvEstimator(config, zeta0, r0, h)
    return CloeEstimator(config, zeta0)
