"""Scenario writing: a :class:`~resloc.experiments.config.Scenario` as a mapping or as
commented TOML text that loads back to an equal scenario."""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from dataclasses import fields
from typing import Any

from resloc.experiments.config import SCENARIO_TABLES, ZONE_TABLES, Scenario
from resloc.world.spec import ZoneSpec

__all__ = [
    "dump_scenario",
    "scenario_to_dict",
    "toml_value",
]


def _plain(v: Any) -> Any:
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    return v


def scenario_to_dict(s: Scenario) -> dict:
    """The scenario as a TOML-ready mapping (every value explicit)."""
    out: dict[str, Any] = {}
    for section, (_, where) in SCENARIO_TABLES.items():
        obj: Any = s
        for attr in where:
            obj = getattr(obj, attr)
        out[section] = {k: _plain(v) for k, v in dataclasses.asdict(obj).items()}
    for section in ZONE_TABLES:
        zs = getattr(s.world, section)
        if zs:
            out[section] = [{k: _plain(v) for k, v in dataclasses.asdict(z).items()} for z in zs]
    return out


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        # JSON's string escapes (\n, \t, \", \\, \uXXXX) are TOML's basic-string escapes.
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")  # pragma: no cover


def _toml_table(header: str, values: dict, cls: type) -> list[str]:
    docs = {f.name: f.metadata.get("doc", "") for f in fields(cls)}
    lines = [header]
    for key, val in values.items():
        text = f"{key} = {toml_value(val)}"
        doc = docs.get(key, "")
        lines.append(f"{text:<40} # {doc}" if doc else text)
    return lines


def dump_scenario(s: Scenario) -> str:
    """The scenario as commented TOML text (loads back to an equal scenario)."""
    data = scenario_to_dict(s)
    lines: list[str] = []
    for section, (cls, _) in SCENARIO_TABLES.items():
        lines += _toml_table(f"[{section}]", data[section], cls)
        lines.append("")
    for section in ZONE_TABLES:
        for zone in data.get(section, []):
            lines += _toml_table(f"[[{section}]]", zone, ZoneSpec)
            lines.append("")
    return "\n".join(lines)
