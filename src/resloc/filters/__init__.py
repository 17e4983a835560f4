"""Gaussian filters with one interface: CKF, UKF (sigma-point rules) and EKF (linearization).

A filter object is an immutable *strategy* that says how a Gaussian is pushed through the
motion model (``predict``) and through the relative measurement (``relative_moments``);
the Kalman correction itself (:func:`kalman_update`) is shared by all three.
"""

from resloc.filters.base import FilterKind, GaussianFilter, Moments, make_filter
from resloc.filters.ekf import ExtendedFilter
from resloc.filters.sigma_points import (
    SigmaPointFilter,
    SigmaPointRule,
    cubature_rule,
    merwe_scaled_rule,
)
from resloc.filters.update import (
    covariance_is_pd,
    innovation,
    kalman_gain,
    kalman_update,
    repair_covariance,
)

__all__ = [
    "ExtendedFilter",
    "FilterKind",
    "GaussianFilter",
    "Moments",
    "SigmaPointFilter",
    "SigmaPointRule",
    "covariance_is_pd",
    "cubature_rule",
    "innovation",
    "kalman_gain",
    "kalman_update",
    "make_filter",
    "merwe_scaled_rule",
    "repair_covariance",
]
