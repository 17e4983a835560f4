"""Start-up: the command line imports nothing heavy until a command needs it."""

from __future__ import annotations

import subprocess
import sys

import pytest

#: Packages that cost tenths of a second each to import; the help screens need none of them.
HEAVY = ("numpy", "scipy", "numba", "matplotlib", "zenoh", "dask", "distributed", "pyarrow")

_PROBE = """
import sys
sys.argv = ["resloc", *sys.argv[1:]]
from resloc.cli.app import main
try:
    main()
except SystemExit:
    pass
heavy = sorted({m.split(".")[0] for m in sys.modules} & set(%r))
print("HEAVY=" + ",".join(heavy), file=sys.stderr)
"""


def _heavy_modules_after(*args: str) -> list[str]:
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE % (HEAVY,), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [line for line in proc.stderr.splitlines() if line.startswith("HEAVY=")]
    assert lines, proc.stderr
    assert "--help" not in args or "Usage" in proc.stdout, proc.stdout
    return [m for m in lines[-1].removeprefix("HEAVY=").split(",") if m]


@pytest.mark.parametrize(
    "args",
    [
        ("--help",),
        ("--version",),
        ("run", "--help"),
        ("mrclam", "--help"),
        ("compare", "--help"),
        ("attack", "--help"),
        ("sweep", "--help"),
        ("reproduce", "--help"),
        ("export", "--help"),
        ("swarm", "--help"),
        ("robot", "--help"),
        ("scenario", "show", "--help"),
    ],
    ids=lambda a: " ".join(a),
)
def test_help_imports_nothing_heavy(args):
    assert _heavy_modules_after(*args) == []


def test_probe_sees_heavy_imports():
    """The probe itself works: a command that runs the estimator does import numpy."""
    assert "numpy" in _heavy_modules_after("scenario", "show")


def test_import_time_of_the_command_line_is_small():
    """``-X importtime`` of the CLI module: no heavy package appears in its import tree."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", "import resloc.cli.app"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines() if "|" in line}
    assert "resloc.cli.app" in imported
    assert not {name.split(".")[0] for name in imported} & set(HEAVY)
