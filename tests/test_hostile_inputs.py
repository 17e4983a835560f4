"""Property-based tests (Hypothesis) over the scenario schema and the MRCLAM row grammar.

Every generated input either runs (tiny sizes) or is refused with one line naming the field
(or file:line): never another exception, never a hang (each example has a deadline), never
a row dropped without being counted. Derandomized: the same examples on every run.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.datasets.mrclam import load_mrclam
from resloc.errors import ConfigError, DataError
from resloc.experiments.config import SCENARIO_TABLES
from resloc.experiments.config_dump import toml_value as _toml_value
from resloc.experiments.config_parse import parse_scenario
from resloc.experiments.mrclam import MRCLAMConfig, run_mrclam
from resloc.experiments.runner import run_scenario
from resloc.world.spec import ZoneSpec

SETTINGS = settings(
    max_examples=60,
    deadline=3000,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

# ---------------------------------------------------------------------------- scenarios
HOSTILE_FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e-7, 1e300, -1e300, 3.0, -3.0, 0.5, 1.0]),
)
HOSTILE_INTS = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70), st.sampled_from([0, 1, 2, 3, 1000])
)
HOSTILE_STRINGS = st.one_of(
    st.text(max_size=12),
    st.sampled_from(["arc", "ckf", "ukf", "nis", "gauge", "$\\alpha$", "a\nb", "consensus"]),
)
SCALARS = st.one_of(HOSTILE_FLOATS, HOSTILE_INTS, st.booleans(), HOSTILE_STRINGS)
VALUES = st.one_of(
    SCALARS,
    st.lists(SCALARS, max_size=4),
    st.lists(st.lists(HOSTILE_FLOATS, max_size=3), max_size=4),
    st.dictionaries(st.text(max_size=4), SCALARS, max_size=2),
)
KEYS = {s: [f.name for f in dataclasses.fields(c)] for s, (c, _) in SCENARIO_TABLES.items()}
KEYS["sdz"] = [f.name for f in dataclasses.fields(ZoneSpec)]
# Sizes stay tiny so that every accepted scenario runs in milliseconds.
SIZES = {"run": ("steps", "trials"), "team": ("robots",)}


@st.composite
def scenario_dicts(draw) -> dict:
    data: dict = {}
    for section in draw(st.lists(st.sampled_from(sorted(KEYS)), max_size=4, unique=True)):
        keys = draw(st.lists(st.sampled_from([*KEYS[section], "bogus"]), max_size=4, unique=True))
        table = {k: draw(VALUES) for k in keys if k not in SIZES.get(section, ())}
        data[section] = [table] if section == "sdz" else table
    run = data.setdefault("run", {})
    run["steps"] = draw(st.integers(1, 4))
    run["trials"] = draw(st.integers(1, 2))
    data.setdefault("team", {})["robots"] = draw(st.integers(2, 4))
    return data


def _named_field(message: str, data: dict) -> bool:
    return any(section in message for section in data)


@SETTINGS
@given(data=scenario_dicts())
def test_every_generated_scenario_runs_or_names_its_field(data):
    try:
        scenario = parse_scenario(data, source="gen.toml")
    except ConfigError as exc:
        text = str(exc)
        assert "\n" not in text and text.startswith("gen.toml: ")
        assert _named_field(text, data), text
        event("refused")
        return
    try:
        result = run_scenario(scenario)
    except ConfigError as exc:  # e.g. the memory estimate
        assert "\n" not in str(exc)
        event("refused before running")
        return
    event(
        "ran"
        + (" (a filter diverged)" if any(e.diverged for e in result.estimators.values()) else "")
    )
    # It ran: every estimator either finished or reports where it diverged.
    for est in result.estimators.values():
        finite = np.isfinite(est.track).all()
        assert finite or est.diverged is not None, est.name


def _toml(data: dict) -> str | None:
    lines = []
    for section, table in data.items():
        rows = table if isinstance(table, list) else [table]
        for row in rows:
            lines.append(f"[[{section}]]" if isinstance(table, list) else f"[{section}]")
            for key, value in row.items():
                try:
                    lines.append(f"{key} = {_toml_value(value)}")
                except TypeError:  # a dict value: not expressible inline by this writer
                    return None
    text = "\n".join(lines) + "\n"
    return None if "nan" in text else text  # TOML nan is fine, but keep the CLI examples few


@settings(SETTINGS, max_examples=15)
@given(data=scenario_dicts())
def test_the_command_line_never_shows_a_traceback(data, tmp_path_factory):
    text = _toml(data)
    if text is None:
        return
    root = tmp_path_factory.mktemp("cli")
    path = root / "gen.toml"
    path.write_text(text, encoding="utf-8")
    out = root / "out"
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(out), "--no-plots"])
    assert res.exit_code in (0, 2), res.output
    event(f"exit {res.exit_code}")
    assert "Traceback" not in res.output
    if res.exit_code == 2:
        errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error: ")]
        assert len(errors) == 1 and str(path) in errors[0], res.stderr
        assert not out.exists()
    else:
        assert (out / "summary.json").exists()


# ---------------------------------------------------------------------------- MRCLAM rows
T0 = 1248444175.0
HEADERS = {
    "Groundtruth": "# Time [s]    x [m]    y [m]    orientation [rad]\n",
    "Odometry": "# Time [s]    forward velocity [m/s]    angular velocity [rad/s]\n",
    "Measurement": "# Time [s]    Subject #    range [m]    bearing [rad]\n",
}


def _write_dataset(root: Path) -> Path:
    """A two-robot, two-landmark dataset of ~1 s, valid and sorted."""
    folder = root / "MRCLAM_Tiny"
    folder.mkdir()
    (folder / "Barcodes.dat").write_text("# Subject #    Barcode #\n1 11\n2 12\n3 13\n4 14\n")
    (folder / "Landmark_Groundtruth.dat").write_text(
        "# Subject #    x [m]    y [m]    x std-dev [m]    y std-dev [m]\n"
        "3 2.0 0.0 0.001 0.001\n4 0.0 2.0 0.001 0.001\n"
    )
    for r in (1, 2):
        gt = [
            f"{T0 + 0.01 * k:.3f} {0.1 * r + 0.001 * k:.4f} {0.2 * r:.4f} 0.0" for k in range(100)
        ]
        odo = [f"{T0 + 0.015 * k:.3f} 0.1 0.0" for k in range(66)]
        meas = [f"{T0 + 0.1 * k + 0.05:.3f} {13 if k % 2 else 14} 2.0 0.1" for k in range(9)]
        for kind, rows in (("Groundtruth", gt), ("Odometry", odo), ("Measurement", meas)):
            (folder / f"Robot{r}_{kind}.dat").write_text(HEADERS[kind] + "\n".join(rows) + "\n")
    return folder


BAD_TOKENS = ["1_000", "inf", "-inf", "nan", "NaN", "0x10", "1e999", "1e300", "--1", "1.2.3", "x"]
KINDS = ["Groundtruth", "Odometry", "Measurement"]


@st.composite
def good_rows(draw, kind: str) -> str:
    t = f"{T0 + draw(st.floats(0.0, 1.2)):.3f}"
    if kind == "Groundtruth":
        vals = [draw(st.floats(-5, 5)), draw(st.floats(-5, 5)), draw(st.floats(-3.1, 3.1))]
    elif kind == "Odometry":
        vals = [draw(st.floats(-0.5, 0.5)), draw(st.floats(-1, 1))]
    else:
        barcode = draw(st.sampled_from([11, 12, 13, 14, 99]))  # 99: unknown, counted
        return f"{t} {barcode} {draw(st.floats(0.1, 8)):.3f} {draw(st.floats(-1, 1)):.3f}"
    return " ".join([t, *(f"{v:.4f}" for v in vals)])


@st.composite
def edits(draw):
    """(kind, robot, [(position, line, is_bad)]) for one file."""
    kind = draw(st.sampled_from(KINDS))
    robot = draw(st.sampled_from([1, 2]))
    out = []
    for _ in range(draw(st.integers(1, 6))):
        pos = draw(st.integers(0, 60))
        choice = draw(st.sampled_from(["good", "good", "duplicate", "comment", "bad", "columns"]))
        if choice == "good":
            out.append((pos, draw(good_rows(kind)), False))
        elif choice == "duplicate":
            out.append((pos, "DUPLICATE", False))
        elif choice == "comment":
            out.append((pos, draw(st.sampled_from(["# note", "", "   "])), False))
        elif choice == "bad":
            row = draw(good_rows(kind)).split()
            row[draw(st.integers(0, len(row) - 1))] = draw(st.sampled_from(BAD_TOKENS))
            out.append((pos, " ".join(row), True))
        else:
            row = draw(good_rows(kind)).split()
            out.append((pos, " ".join([*row, "1.0"] if draw(st.booleans()) else row[:-1]), True))
    return kind, robot, out


@SETTINGS
@given(edit=edits())
def test_every_generated_row_is_kept_counted_or_named(edit, tmp_path_factory):
    root = tmp_path_factory.mktemp("mrclam")
    folder = _write_dataset(root)
    kind, robot, changes = edit
    path = folder / f"Robot{robot}_{kind}.dat"
    lines = path.read_text().splitlines()
    data_lines = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    for pos, line, _bad in changes:
        if line == "DUPLICATE":
            line = data_lines[pos % len(data_lines)]
        lines.insert(min(pos, len(lines)), line)
    path.write_text("\n".join(lines) + "\n")
    # Which line is the first bad one, by construction.
    bad_lines = {line for _, line, bad in changes if bad}
    first_bad = next((k + 1 for k, ln in enumerate(lines) if ln in bad_lines), None)
    try:
        data = load_mrclam(folder)
    except DataError as exc:
        text = str(exc)
        assert "\n" not in text
        if first_bad is not None:
            assert f"{path}:{first_bad}:" in text, (text, first_bad)
            event("refused at file:line")
        else:  # a generated good row may repeat a time with other values: conflicting only
            pytest.fail(f"valid rows refused: {text}")
        return
    assert first_bad is None, "a bad row was accepted"
    # Never a silent drop: every data row is kept or counted.
    written = [ln for ln in lines if ln.strip() and not ln.strip().startswith("#")]
    log = data.robots[robot - 1]
    kept = {"Groundtruth": log.groundtruth, "Odometry": log.odometry}.get(kind, log.measurements)
    counts = data.skipped_by_file.get(path.name, {})
    dropped = sum(v for k, v in counts.items() if k != "out_of_order")
    assert len(kept) + dropped == len(written), (len(kept), counts, len(written))
    assert np.all(np.diff(kept[:, 0]) >= 0)
    event("loaded, " + ("rows dropped and counted" if dropped else "nothing dropped"))
    # And it runs.
    result = run_mrclam(data, MRCLAMConfig(filters=("ekf",)))
    assert math.isfinite(result.info["replayed_s"])


def test_strict_refuses_what_the_default_counts(tmp_path):
    folder = _write_dataset(tmp_path)
    path = folder / "Robot1_Odometry.dat"
    path.write_text(path.read_text() + f"{T0 + 0.3:.3f} 0.1 0.0\n")  # out of order
    assert load_mrclam(folder).skipped["out_of_order"] == 1
    with pytest.raises(DataError, match=r"Robot1_Odometry\.dat:68: .*--strict"):
        load_mrclam(folder, strict=True)
    shutil.rmtree(folder)
