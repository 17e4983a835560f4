"""Scenario parsing: TOML data validated strictly into a
:class:`~resloc.experiments.config.Scenario`.

An unknown key, a wrong type or an out-of-range value raises
:class:`~resloc.errors.ConfigError` with one line naming the field, the value and the fix.
"""

from __future__ import annotations

import enum
import math
import tomllib
import typing
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

from resloc.cl.detection import OPTION_CHECKS
from resloc.cl.fusion import FusionMethod
from resloc.cl.fusion_methods import fusion_strategy
from resloc.errors import ConfigError
from resloc.experiments.config import (
    SCENARIO_TABLES,
    ZONE_TABLES,
    DetectorSpec,
    EstimatorSpec,
    RunSpec,
    Scenario,
    TriggerSpec,
)
from resloc.filters.base import FilterKind
from resloc.validation import check_one_line_name
from resloc.world.control import LeaderPath
from resloc.world.spec import (
    ARENA_MAX,
    STD_MIN,
    AttackSpec,
    TeamSpec,
    WorldSpec,
    ZoneSpec,
)

__all__ = [
    "build",
    "load_scenario",
    "parse_scenario",
    "read_toml",
    "set_dotted",
]

_LIST_LENGTHS = {
    "motion.odometry_std": 2,
    "motion.process_floor_std": 3,
    "attack.bias": 2,
    "attack.stealth_direction": 2,
    "detector.zone_trust_shift": 2,
    "center": 2,
}


def _type_name(v: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array"}.get(
        type(v), type(v).__name__
    )


def _check_number(path: str, value: Any, meta: dict, want: type) -> float | int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        what = "an integer" if want is int else "a number"
        raise ConfigError(f"{path}: expected {what}, got {_type_name(value)} {value!r}")
    if want is int and not isinstance(value, int):
        raise ConfigError(f"{path}: expected an integer, got {value!r}")
    if isinstance(value, float) and math.isnan(value):
        raise ConfigError(f"{path}: NaN is not allowed")
    if isinstance(value, float) and math.isinf(value):
        raise ConfigError(f"{path}: {value!r} is not allowed; give a finite number")
    why = ""
    if meta.get("min") == STD_MIN:
        why = f" (a zero noise std makes the covariance singular; {STD_MIN:g} is almost noiseless)"
    if "min" in meta and value < meta["min"]:
        raise ConfigError(
            f"{path}: {value!r} is below the minimum {meta['min']}; use >= {meta['min']}{why}"
        )
    if "max" in meta and value > meta["max"]:
        raise ConfigError(
            f"{path}: {value!r} is above the maximum {meta['max']}; use <= {meta['max']}"
        )
    if "gt" in meta and not value > meta["gt"]:
        raise ConfigError(f"{path}: {value!r} must be greater than {meta['gt']}")
    return want(value)


def build(cls: type, data: Any, path: str) -> Any:
    """Build dataclass ``cls`` from a mapping, validating every key (see module doc)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table, got {_type_name(data)} {data!r}")
    names = {f.name: f for f in fields(cls)}
    for key in data:
        if key not in names:
            known = ", ".join(sorted(names))
            raise ConfigError(f"{path}.{key}: unknown key; known keys here: {known}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _convert(f"{path}.{name}", value, hints[name], names[name].metadata)
    return cls(**kwargs)


def _convert(path: str, value: Any, hint: Any, meta: Any) -> Any:
    meta = dict(meta or {})
    if isinstance(hint, type) and issubclass(hint, enum.Enum | FusionMethod):  # names
        choices = [m.value for m in hint]
        if not isinstance(value, str) or value not in choices:
            raise ConfigError(f"{path}: {value!r} is not one of {', '.join(choices)}")
        return hint(value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if hint in (int, float):
        return _check_number(path, value, meta, hint)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {_type_name(value)} {value!r}")
        return value
    if hint is list:
        if not isinstance(value, list):
            raise ConfigError(f"{path}: expected an array, got {_type_name(value)} {value!r}")
        short = (
            path.split(".", 1)[1] if path.count(".") and path.startswith(("sdz", "cdz")) else path
        )
        want_len = _LIST_LENGTHS.get(short.split("[")[0]) or _LIST_LENGTHS.get(
            path.rsplit(".", 1)[-1]
        )
        if want_len is not None:
            if len(value) != want_len:
                raise ConfigError(f"{path}: expected {want_len} numbers, got {value!r}")
            return [_check_number(f"{path}[{k}]", v, meta, float) for k, v in enumerate(value)]
        return list(value)
    if is_dataclass(hint):
        return build(hint, value, path)
    raise ConfigError(f"{path}: unsupported value {value!r}")  # pragma: no cover


def set_dotted(data: dict, dotted: str, value: Any) -> None:
    """Set ``data["a"]["b"] = value`` for ``dotted = "a.b"`` (creating tables)."""
    keys = dotted.split(".")
    node = data
    for k in keys[:-1]:
        node = node.setdefault(k, {})
        if not isinstance(node, dict):
            raise ConfigError(f"{dotted}: {k!r} is not a table")
    node[keys[-1]] = value


def parse_scenario(data: dict, source: str = "scenario") -> Scenario:
    """Validate a scenario mapping (as read from TOML) into a :class:`Scenario`.

    Raises
    ------
    ConfigError
        With one line naming ``source``, the field and the fix.
    """
    try:
        return _parse(data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _parse(data: dict) -> Scenario:
    if not isinstance(data, dict):
        raise ConfigError("expected a TOML document")
    known = set(SCENARIO_TABLES) | set(ZONE_TABLES)
    for key in data:
        if key not in known:
            raise ConfigError(f"{key}: unknown section; known sections: {', '.join(sorted(known))}")
    parts: dict[str, Any] = {}
    for section, (cls, _) in SCENARIO_TABLES.items():
        parts[section] = build(cls, data.get(section, {}), section)
    zones: dict[str, tuple[ZoneSpec, ...]] = {}
    for section in ZONE_TABLES:
        raw = data.get(section, [])
        if isinstance(raw, dict):
            raw = [raw]
        if not isinstance(raw, list):
            raise ConfigError(f"{section}: expected [[{section}]] tables, got {raw!r}")
        zones[section] = tuple(build(ZoneSpec, z, f"{section}[{k}]") for k, z in enumerate(raw))
    run: RunSpec = parts["run"]
    for k, name in enumerate(run.filters):
        if name not in [f.value for f in FilterKind]:
            raise ConfigError(f"run.filters[{k}]: {name!r} is not one of ckf, ukf, ekf")
    if len(set(run.filters)) != len(run.filters):
        raise ConfigError(f"run.filters: {run.filters!r} lists a filter twice")
    if not run.filters and not run.dead_reckoning:
        raise ConfigError("run.filters: empty and dead_reckoning is false; nothing to run")
    team: TeamSpec = parts["team"]
    if team.robots < 2:
        raise ConfigError(
            f"team.robots: {team.robots} robots cannot localize cooperatively; use >= 2"
        )
    trig: TriggerSpec = parts["trigger"]
    det: DetectorSpec = parts["detector"]
    for stage in OPTION_CHECKS:
        problem = stage.problem(det)
        if problem is not None:
            raise ConfigError(f"detector.{problem}")
    est: EstimatorSpec = parts["estimator"]
    problem = fusion_strategy(est.fusion).problem(est)
    if problem is not None:
        raise ConfigError(f"estimator.fusion: {str(est.fusion)!r} {problem}")
    att: AttackSpec = parts["attack"]
    if not any(abs(v) > 0.0 for v in att.stealth_direction):
        raise ConfigError(
            f"attack.stealth_direction: {att.stealth_direction!r} is zero; give a direction "
            "such as [0.0, 1.0] (bearing)"
        )
    check_one_line_name("run.name", run.name)
    _check_waypoints(parts["motion"].waypoints)
    LeaderPath(parts["motion"].waypoints)  # validates the path
    if run.trials * team.robots > 5_000_000:
        raise ConfigError(
            f"run.trials x team.robots = {run.trials * team.robots} exceeds 5,000,000 robots"
        )
    world = WorldSpec(
        team=team,
        motion=parts["motion"],
        sensing=parts["sensing"],
        attack=parts["attack"],
        sdz=zones["sdz"],
        cdz=zones["cdz"],
    )
    return Scenario(
        run=run,
        world=world,
        estimator=parts["estimator"],
        detector=parts["detector"],
        trigger=trig,
    )


def _check_waypoints(waypoints: list) -> None:
    """Each waypoint is ``"arc"`` or ``[x, y]``: two finite numbers inside the arena."""
    for k, w in enumerate(waypoints):
        path = f"motion.waypoints[{k}]"
        if isinstance(w, str):
            continue  # "arc" and its placement are checked by LeaderPath
        if not isinstance(w, list) or len(w) != 2:
            raise ConfigError(f'{path}: expected [x, y] or "arc", got {w!r}')
        for c, v in enumerate(w):
            _check_number(f"{path}[{c}]", v, {"min": -ARENA_MAX, "max": ARENA_MAX}, float)


def read_toml(path: str | Path, kind: str = "scenario") -> dict:
    """Read a TOML file, mapping every failure to one :class:`ConfigError` line.

    Parameters
    ----------
    path : str or Path
    kind : str
        What the file is, for the message (``scenario``, ``sweep``, ...).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")  # a byte-order mark is not an error
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such {kind} file") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read {kind} file ({exc.__class__.__name__})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file.

    Raises
    ------
    ConfigError
        Missing file, TOML syntax error, or invalid content (one line, names the field).
    """
    return parse_scenario(read_toml(path, "scenario"), source=str(Path(path)))
