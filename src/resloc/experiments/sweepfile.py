"""Sweep files: a scenario file plus a ``[sweep]`` table naming what varies.

One parameter (the original form, e.g. ``examples/paper/*.toml``)::

    [sweep]
    name = "Fig. 5b: detection threshold"
    parameter = "detector.rho"          # a dotted key of the scenario schema
    values = [0.2, 0.3, 0.5, 1.0]
    filters = ["ckf"]                   # optional: run.filters for every point
    metric = "msle_mean"                # optional: the scalar summarized per point
    base = "default"                    # optional: "default" (the embedded scenario) or a
                                        # scenario file relative to this one

Several parameters, as a grid (every combination) and/or zipped (element-wise)::

    [sweep.grid]
    detector.rho = [0.2, 0.5, 1.0]
    trigger.alpha = [0.1, 0.3]          # 3 x 2 = 6 points

    [sweep.zip]
    "sdz.radius" = [0.2, 0.4]           # equal lengths; with a grid: grid x zip rows
    "cdz.radius" = [0.3, 0.5]

Every point runs ``run.trials`` seeds (``--seeds``) and every filter. Without ``base`` the
sections apply over the schema defaults, exactly as in a scenario file (so a sweep file
without ``[[sdz]]``/``[[cdz]]`` has no danger zones). A parameter is any dotted key of a
scenario file (``detector.rho``, ``trigger.alpha``, ``team.robots``, ``attack.links``), or
``zones.<key>`` (every SDZ and CDZ, e.g. ``zones.radius``), ``sdz.<key>`` / ``cdz.<key>``
(every zone of one kind).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from resloc.errors import ConfigError
from resloc.experiments.config import Scenario, default_scenario
from resloc.experiments.config_dump import scenario_to_dict, toml_value
from resloc.experiments.config_parse import load_scenario, parse_scenario, read_toml, set_dotted
from resloc.experiments.store import canonical_json

__all__ = [
    "METRICS",
    "SweepSpec",
    "apply_parameter",
    "dump_minimal",
    "dump_sweep",
    "load_sweep",
    "parse_sweep",
]

#: Per-seed scalars a sweep can summarize (see ``EstimatorResult.per_trial``).
METRICS = ("msle_mean", "msle_final", "rmse_mean", "rmse_final", "nees_mean", "comm_rate")
_SWEEP_KEYS = ("name", "parameter", "values", "grid", "zip", "filters", "metric", "base")
#: Parameters that a sweep may not vary (they are the seeds, or have their own key).
_RESERVED = {
    "run.trials": "seeds are the Monte Carlo dimension; use --seeds",
    "run.seed": "seeds are the Monte Carlo dimension; use --seeds",
    "run.filters": "use sweep.filters",
}


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: a base scenario and the points where parameters change.

    Attributes
    ----------
    name : str
    parameter : str or tuple of str
        One dotted key (see module doc), or several.
    values : tuple
        One entry per point: the value (one parameter) or a tuple of values, one per
        parameter (several).
    base : Scenario
        The scenario every point starts from (``filters`` already applied).
    metric : str
        One of :data:`METRICS`.
    """

    name: str
    parameter: str | tuple[str, ...]
    values: tuple
    base: Scenario
    metric: str = "msle_mean"

    @property
    def parameters(self) -> tuple[str, ...]:
        """The varied dotted keys."""
        return (self.parameter,) if isinstance(self.parameter, str) else tuple(self.parameter)

    def assignments(self, value: Any) -> dict[str, Any]:
        """``{parameter: value}`` of one point (``value`` an entry of ``values``)."""
        if isinstance(self.parameter, str):
            return {self.parameter: value}
        return dict(zip(self.parameter, value, strict=True))

    def label(self, value: Any) -> str:
        """A point as text: ``0.2`` (one parameter) or ``rho=0.2, alpha=0.1``."""
        if isinstance(self.parameter, str):
            return _fmt_value(value)
        short = [k.rsplit(".", 1)[-1] for k in self.parameter]
        names = [k if short.count(s) > 1 else s for k, s in zip(self.parameter, short, strict=True)]
        return ", ".join(f"{n}={_fmt_value(v)}" for n, v in zip(names, value, strict=True))

    @property
    def axis_label(self) -> str:
        """The x-axis title of the plots."""
        return self.parameter if isinstance(self.parameter, str) else ", ".join(self.parameter)

    def scenario(self, value: Any) -> Scenario:
        """The point ``value`` (validated)."""
        out = self.base
        for key, v in self.assignments(value).items():
            out = apply_parameter(out, key, v)
        return out

    def scenarios(self, seeds: int | None = None, steps: int | None = None) -> list[Scenario]:
        """Every point, with ``run.trials = seeds`` and ``run.steps = steps`` when given."""
        spec = self.with_run(seeds, steps)
        return [spec.scenario(v) for v in spec.values]

    def with_run(self, seeds: int | None = None, steps: int | None = None) -> SweepSpec:
        """Copy with the seed count (``run.trials``) and/or ``run.steps`` replaced."""
        changes: dict[str, Any] = {}
        if seeds is not None:
            changes["run.trials"] = int(seeds)
        if steps is not None:
            changes["run.steps"] = int(steps)
        if not changes:
            return self
        return SweepSpec(
            self.name, self.parameter, self.values, self.base.replace(**changes), self.metric
        )

    @property
    def numeric(self) -> bool:
        """True for one parameter with numbers only (plots use a numeric axis)."""
        return isinstance(self.parameter, str) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in self.values
        )


def _fmt_value(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def apply_parameter(scenario: Scenario, parameter: str, value: Any) -> Scenario:
    """``scenario`` with ``parameter`` set to ``value`` (validated).

    ``zones.<key>`` sets ``key`` in every ``[[sdz]]`` and ``[[cdz]]``; ``sdz.<key>`` and
    ``cdz.<key>`` in every zone of that kind; any other dotted key is a scenario-file key.

    Raises
    ------
    ConfigError
        Unknown key, wrong type or out-of-range value, or zones requested but absent.
    """
    source = f"sweep {parameter} = {value!r}"
    data = scenario_to_dict(scenario)
    head, _, key = parameter.partition(".")
    if head in ("zones", "sdz", "cdz"):
        if not key or "." in key:
            raise ConfigError(
                f"{source}: use zones.<key>, sdz.<key> or cdz.<key> (e.g. zones.radius)"
            )
        kinds = ("sdz", "cdz") if head == "zones" else (head,)
        zones = [z for kind in kinds for z in data.get(kind, [])]
        if not zones:
            raise ConfigError(
                f"{source}: the scenario has no {' or '.join(f'[[{k}]]' for k in kinds)} "
                "zones to change"
            )
        for z in zones:
            z[key] = value
    else:
        set_dotted(data, parameter, value)
    return parse_scenario(data, source=source)


def _merge(base: dict, over: dict) -> dict:
    """Scenario mapping ``over`` applied on ``base`` (tables merged, zone arrays replaced)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = {**out[k], **v}
        else:
            out[k] = v
    return out


def _flatten(table: dict, prefix: str = "") -> dict[str, Any]:
    """``{"detector": {"rho": [..]}}`` and ``{"detector.rho": [..]}`` both give the second
    (TOML reads an unquoted dotted key as nested tables)."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, f"{key}."))
        else:
            out[key] = v
    return out


def _check_parameter(source: str, field: str, parameter: Any) -> str:
    if not isinstance(parameter, str) or not parameter:
        raise ConfigError(
            f'{source}: {field}: expected a dotted key such as "detector.rho", got {parameter!r}'
        )
    if parameter in _RESERVED:
        raise ConfigError(f"{source}: {field}: {parameter} cannot be swept; {_RESERVED[parameter]}")
    return parameter


def _check_values(source: str, field: str, values: Any) -> list:
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{source}: {field}: expected a non-empty array, got {values!r}")
    for k, v in enumerate(values):
        if isinstance(v, list | dict):
            raise ConfigError(
                f"{source}: {field}[{k}]: expected a number, string or boolean, got {v!r}"
            )
    return values


def _axes(source: str, sweep: dict) -> tuple[str | tuple[str, ...], tuple]:
    """The parameter(s) and the points of a ``[sweep]`` table."""
    single = "parameter" in sweep or "values" in sweep
    multi = [k for k in ("grid", "zip") if k in sweep]
    if single and multi:
        raise ConfigError(
            f"{source}: sweep.{multi[0]}: use either parameter/values or grid/zip, not both"
        )
    if not multi:
        parameter = _check_parameter(source, "sweep.parameter", sweep.get("parameter"))
        values = _check_values(source, "sweep.values", sweep.get("values"))
        return parameter, tuple(values)
    columns: dict[str, dict[str, list]] = {}
    for kind in multi:
        table = sweep[kind]
        if not isinstance(table, dict) or not table:
            raise ConfigError(
                f"{source}: sweep.{kind}: expected a table of dotted keys to arrays, "
                f'e.g. "detector.rho" = [0.2, 0.5], got {table!r}'
            )
        columns[kind] = {}
        for key, values in _flatten(table).items():
            field = f"sweep.{kind}.{key}"
            _check_parameter(source, field, key)
            columns[kind][key] = _check_values(source, field, values)
    zipped = columns.get("zip", {})
    lengths = {k: len(v) for k, v in zipped.items()}
    if len(set(lengths.values())) > 1:
        raise ConfigError(
            f"{source}: sweep.zip: arrays of different lengths ("
            + ", ".join(f"{k}: {n}" for k, n in lengths.items())
            + "); zipped arrays need one value per point"
        )
    grid = columns.get("grid", {})
    both = set(grid) & set(zipped)
    if both:
        raise ConfigError(f"{source}: sweep.zip.{sorted(both)[0]}: also in sweep.grid")
    rows_grid = list(itertools.product(*grid.values())) if grid else [()]
    rows_zip = list(zip(*zipped.values(), strict=True)) if zipped else [()]
    points = tuple(g + z for g in rows_grid for z in rows_zip)
    return (*grid, *zipped), points


def parse_sweep(data: dict, source: str = "sweep", base_dir: Path | None = None) -> SweepSpec:
    """Validate a sweep mapping (as read from TOML) into a :class:`SweepSpec`.

    Every value is applied once here, so a bad value fails before any work.

    Raises
    ------
    ConfigError
        One line naming ``source``, the field and the fix.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a TOML document")
    sweep = data.get("sweep")
    if sweep is None:
        raise ConfigError(
            f"{source}: no [sweep] table; a sweep file needs [sweep] with parameter and values "
            "(or [sweep.grid] / [sweep.zip]; for a plain scenario use `resloc run`)"
        )
    if not isinstance(sweep, dict):
        raise ConfigError(f"{source}: sweep: expected a table, got {sweep!r}")
    for key in sweep:
        if key not in _SWEEP_KEYS:
            raise ConfigError(
                f"{source}: sweep.{key}: unknown key; known keys here: {', '.join(_SWEEP_KEYS)}"
            )
    parameter, values = _axes(source, sweep)
    if len({canonical_json(v) for v in values}) != len(values):
        field, what = (
            ("sweep.values", "value") if isinstance(parameter, str) else ("sweep.grid/zip", "point")
        )
        raise ConfigError(f"{source}: {field}: {list(values)!r} lists a {what} twice")
    metric = sweep.get("metric", "msle_mean")
    if metric not in METRICS:
        raise ConfigError(f"{source}: sweep.metric: {metric!r} is not one of {', '.join(METRICS)}")
    default_name = f"sweep of {parameter if isinstance(parameter, str) else ', '.join(parameter)}"
    name = sweep.get("name", default_name)
    if not isinstance(name, str):
        raise ConfigError(f"{source}: sweep.name: expected a string, got {name!r}")

    sections = {k: v for k, v in data.items() if k != "sweep"}
    base_ref = sweep.get("base")
    if base_ref is None:
        base_data: dict = {}
    elif base_ref == "default":
        base_data = scenario_to_dict(default_scenario())
    elif isinstance(base_ref, str):
        p = Path(base_ref)
        if not p.is_absolute() and base_dir is not None:
            p = base_dir / p
        try:
            base_data = scenario_to_dict(load_scenario(p))
        except ConfigError as exc:
            raise ConfigError(f"{source}: sweep.base: {exc}") from None
    else:
        raise ConfigError(
            f'{source}: sweep.base: expected "default" or a scenario file path, got {base_ref!r}'
        )
    filters = sweep.get("filters")
    if filters is not None:
        if not isinstance(filters, list):
            raise ConfigError(f"{source}: sweep.filters: expected an array, got {filters!r}")
        sections = _merge(sections, {"run": {**sections.get("run", {}), "filters": filters}})
    merged = _merge(base_data, sections)
    try:
        base = parse_scenario(merged, source="scenario")
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    spec = SweepSpec(name, parameter, values, base, metric)
    # Each value of each parameter alone (cheap; a grid's combinations are checked when its
    # scenarios are built, still before any work).
    if isinstance(parameter, str):
        checks = [(f"sweep.values[{k}]", parameter, v) for k, v in enumerate(values)]
    else:
        kind = {p: ("grid" if p in _flatten(sweep.get("grid", {})) else "zip") for p in parameter}
        checks = [
            (f"sweep.{kind[p]}.{p}[{k}]", p, v)
            for j, p in enumerate(parameter)
            for k, v in enumerate(dict.fromkeys(pt[j] for pt in values))
        ]
    for field, key, v in checks:
        try:
            apply_parameter(base, key, v)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {field}: {exc}") from None
    return spec


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and validate a sweep TOML file (see module doc).

    Raises
    ------
    ConfigError
        Missing file, TOML syntax error, or invalid content (one line, names the field).
    """
    p = Path(path)
    data = read_toml(p, "sweep")
    return parse_sweep(data, source=str(p), base_dir=p.parent)


def dump_minimal(scenario: Scenario) -> str:
    """TOML of only what differs from the schema defaults (zones in full).

    Loading the text with :func:`~resloc.experiments.config_parse.load_scenario` gives back
    ``scenario``; a short file states exactly what an experiment changes.
    """
    ref = scenario_to_dict(Scenario())
    data = scenario_to_dict(scenario)
    lines: list[str] = []
    for section, values in data.items():
        if section in ("sdz", "cdz"):
            continue
        diff = {k: v for k, v in values.items() if ref[section].get(k) != v}
        if diff:
            lines.append(f"[{section}]")
            lines += [f"{k} = {toml_value(v)}" for k, v in diff.items()]
            lines.append("")
    zone_ref = scenario_to_dict(Scenario(world=_one_zone_world()))["sdz"][0]
    for section in ("sdz", "cdz"):
        for zone in data.get(section, []):
            lines.append(f"[[{section}]]")
            lines += [
                f"{k} = {toml_value(v)}"
                for k, v in zone.items()
                if k in ("center", "radius") or zone_ref.get(k) != v
            ]
            lines.append("")
    return "\n".join(lines)


def _one_zone_world():
    from resloc.world.spec import WorldSpec, ZoneSpec

    return WorldSpec(sdz=(ZoneSpec(),))


def dump_sweep(spec: SweepSpec) -> str:
    """A sweep file for ``spec`` (``[sweep]`` plus the base scenario's non-default values);
    :func:`load_sweep` reads it back to an equal spec. Several parameters are written as
    ``[sweep.zip]`` columns (every point explicit)."""
    head = ["[sweep]", f"name = {toml_value(spec.name)}"]
    if isinstance(spec.parameter, str):
        head += [
            f"parameter = {toml_value(spec.parameter)}",
            f"values = {toml_value(list(spec.values))}",
        ]
    head.append(f"filters = {toml_value(list(spec.base.run.filters))}")
    if spec.metric != "msle_mean":
        head.append(f"metric = {toml_value(spec.metric)}")
    if not isinstance(spec.parameter, str):
        head += ["", "[sweep.zip]"]
        head += [
            f"{toml_value(p)} = {toml_value([pt[j] for pt in spec.values])}"
            for j, p in enumerate(spec.parameter)
        ]
    base = spec.base.replace(**{"run.filters": list(Scenario().run.filters)})
    return "\n".join(head) + "\n\n" + dump_minimal(base)
