# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The median absolute deviation as a normal sigma: the one formula behind every robust scale.

``ellipsoid.robust_sigma`` builds on it (a floor, residuals about zero); the compensation fit,
the input sanity checks and the benchmarks call it directly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

MAD_TO_SIGMA = 1.4826
"""A normal distribution's sigma over its median absolute deviation (1 / 0.6745)."""


def mad_sigma(values: ArrayLike, *, about_median: bool = True) -> float:
    """``1.4826 x median |values - median(values)|``: the normal sigma a median absolute
    deviation stands for, over every element (NaN for none).

    ``about_median=False`` measures the deviations about zero instead (``median |values|``): for
    values whose expected value *is* zero, such as residuals, where a shifted median is itself an
    error.
    """
    values = np.asarray(values)
    deviations = values - np.median(values) if about_median else values
    return MAD_TO_SIGMA * float(np.median(np.abs(deviations)))


__all__ = ['MAD_TO_SIGMA', 'mad_sigma']
