"""Library exceptions. The CLI maps :class:`ResLocError` subclasses to exit code 2."""


class ResLocError(Exception):
    """Base class of every error resloc raises on purpose."""


class ConfigError(ResLocError, ValueError):
    """A scenario / sweep / CLI value is invalid. The message names the field and the fix."""


class DataError(ResLocError, ValueError):
    """A data file (e.g. an MRCLAM file) is malformed. The message names file and line."""


class NumericalError(ResLocError, ArithmeticError):
    """A covariance could not be kept positive definite even with jitter."""
