"""resloc: resilient, distributed multi-robot cooperative localization.

Layers, lowest first (a lower layer never imports a higher one):

``angles``/``linalg`` -> ``models`` (motion, measurement) -> ``filters`` (CKF/UKF/EKF)
-> ``cl`` (detector, trigger, per-robot estimator step) -> ``world`` (robots, zones,
attacks, network) -> ``experiments`` (scenarios, metrics, runs, reports) -> ``cli``.
"""

__version__ = "0.1.0"

from resloc.errors import ConfigError, DataError, NumericalError, ResLocError

__all__ = ["ConfigError", "DataError", "NumericalError", "ResLocError", "__version__"]
