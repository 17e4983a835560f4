"""Declared fields of the scenario sections: a default, a doc string, validation bounds.

The bounds (``min``/``max`` inclusive, ``gt`` strictly greater) and the doc are read by
:mod:`resloc.experiments.config` to validate and to write commented TOML.
"""

from __future__ import annotations

from dataclasses import field
from typing import Any

__all__ = ["option"]


def option(default: Any, doc: str, **bounds: Any) -> Any:
    """A scenario option: a dataclass field with a default, a doc string and validation
    bounds."""
    if isinstance(default, list | dict):
        return field(
            default_factory=lambda: type(default)(default), metadata={"doc": doc, **bounds}
        )
    return field(default=default, metadata={"doc": doc, **bounds})
