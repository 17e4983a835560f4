"""The choice of innovation norm, in a module of its own so that the command line can offer
it without importing the estimator (numpy, scipy, numba)."""

from __future__ import annotations

import enum

__all__ = ["InnovationNorm"]


class InnovationNorm(enum.StrEnum):
    """How the 2-vector ``Lambda = [range error (m), bearing error (rad)]`` becomes a scalar.

    ``euclidean``: the paper's ``||Lambda||`` (adds metres to radians).
    ``scaled``: ``||Lambda / sigma||`` with the measurement noise standard deviations.
    ``nis``: ``sqrt(Lambda^T S^{-1} Lambda)``, the normalized innovation (uses ``P^zz``).
    """

    EUCLIDEAN = "euclidean"
    SCALED = "scaled"
    NIS = "nis"
