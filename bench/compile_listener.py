"""Where a cold test suite spends numba's compile time: a pytest plugin and its summary.

Each compilation's process CPU, exclusive of the kernels it compiles in turn (numba's
``"numba:compile"`` events), charged to the test that triggered it (or to the session
start, where ``make test``'s workers compile their shares). One JSON file per xdist worker.

    rm -rf /tmp/cold && RESLOC_TEST_WARM_SHARES=1 NUMBA_CACHE_DIR=/tmp/cold \\
        PYTHONPATH=bench .venv/bin/python -m pytest -q -n 2 -p compile_listener
    .venv/bin/python bench/compile_listener.py          # the summary

``RESLOC_COMPILE_LOG`` names the directory of the JSON files (default ``runs/compile``).
"""

from __future__ import annotations

import collections
import json
import os
import sys
import time
from pathlib import Path

DIRECTORY = Path(os.environ.get("RESLOC_COMPILE_LOG", "runs/compile"))
SESSION_START = "session start"

_open: list[list] = []  # [name, start CPU, CPU of the compilations inside]
_records: list[dict] = []
_charged_to = [SESSION_START]


def _register() -> None:
    from numba.core import event

    class CompileListener(event.Listener):
        def on_start(self, ev) -> None:
            func = ev.data["dispatcher"].py_func
            _open.append([f"{func.__module__}.{func.__qualname__}", time.process_time(), 0.0])

        def on_end(self, ev) -> None:
            name, start, inner = _open.pop()
            total = time.process_time() - start
            if _open:
                _open[-1][2] += total
            _records.append({"kernel": name, "cpu_s": total - inner, "test": _charged_to[0]})

    event.register("numba:compile", CompileListener())


def pytest_configure(config) -> None:
    _register()


def pytest_runtest_setup(item) -> None:
    _charged_to[0] = item.nodeid


def pytest_sessionfinish(session) -> None:
    DIRECTORY.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (DIRECTORY / f"{worker}.json").write_text(json.dumps(_records), encoding="utf-8")


def summary(directory: Path = DIRECTORY, most: int = 10) -> str:
    """Per worker: the compile CPU, at the session start and in tests, and the tests and
    kernels that cost most."""
    lines = []
    for path in sorted(directory.glob("*.json")):
        records = json.loads(path.read_text(encoding="utf-8"))
        start = sum(r["cpu_s"] for r in records if r["test"] == SESSION_START)
        total = sum(r["cpu_s"] for r in records)
        lines.append(
            f"{path.stem}: {total:.0f} s of compile CPU, {start:.0f} at the session start, "
            f"{total - start:.0f} in tests"
        )
        for key in ("test", "kernel"):
            costs = collections.Counter()
            for r in records:
                costs[r[key]] += r["cpu_s"]
            lines += [f"  {cpu:6.1f} s  {name}" for name, cpu in costs.most_common(most)]
    return "\n".join(lines) if lines else f"no compile log under {directory}"


if __name__ == "__main__":
    print(summary(Path(sys.argv[1]) if len(sys.argv) > 1 else DIRECTORY))
