"""resloc: resilient, distributed multi-robot cooperative localization.

Layers, lowest first (a lower layer never imports a higher one):

``angles``/``linalg`` -> ``models`` (motion, measurement) -> ``filters`` (CKF/UKF/EKF)
-> ``cl`` (detector, trigger, fusion strategies, per-robot estimator step, robot node)
-> ``world`` (robots, zones, attacks, network) -> ``experiments`` (scenarios, metrics, runs,
reports) -> ``cli``.

The public API (:mod:`resloc.api`) is available here too: ``resloc.run_scenario``,
``resloc.RobotNode``, ... It is imported on first use, so ``import resloc`` stays light.
"""

__version__ = "0.1.0"

from resloc.errors import ConfigError, DataError, NumericalError, ResLocError


def __getattr__(name: str):
    """Load :mod:`resloc.api` on the first access to one of its names."""
    import importlib

    api = importlib.import_module("resloc.api")
    if name in api.__all__:
        return getattr(api, name)
    if name in globals():  # a subpackage that loading the API imported
        return globals()[name]
    raise AttributeError(f"module 'resloc' has no attribute {name!r}")


def __dir__() -> list[str]:
    import importlib

    return sorted(set(globals()) | set(importlib.import_module("resloc.api").__all__))


__all__ = ["ConfigError", "DataError", "NumericalError", "ResLocError", "__version__"]
