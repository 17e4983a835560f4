"""Studies on real Dask components (all on 127.0.0.1, started and stopped by these tests):
an external `dask scheduler` with `dask worker` processes, the embedded LocalCluster, a
worker killed mid-study, and `resloc sweep` / `resloc reproduce` killed and resumed."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import psutil
import pytest

from resloc.experiments.executor import THREAD_ENV, Study
from resloc.experiments.store import ResultStore
from resloc.experiments.sweep import METRICS, parse_sweep, run_sweep

BIN = Path(sys.executable).parent


@pytest.fixture(autouse=True, scope="module")
def _kernels_compiled():
    """The kernels compiled into numba's on-disk cache before any worker starts: a worker
    that compiles them cold (about 2 minutes) would outlast the tests' bounded waits."""
    from resloc.experiments.backends import warm_up_kernels

    warm_up_kernels()


SPEC = {
    "sweep": {
        "name": "cluster sweep",
        "grid": {"detector.rho": [0.3, 0.8], "trigger.alpha": [0.1, 0.3]},
        "filters": ["ckf", "ekf"],
    },
    "run": {"steps": 30, "trials": 3},
    "team": {"robots": 4},
    "sdz": [{"center": [0.45, -0.55], "radius": 0.4}],
}
SWEEP_FILE = """
[sweep]
name = "killed and resumed"
filters = ["ckf"]

[sweep.grid]
detector.rho = [0.2, 0.5, 1.0]
trigger.alpha = [0.1, 0.3]

[run]
steps = 300
trials = 4

[team]
robots = 6

[[sdz]]
center = [0.45, -0.55]
radius = 0.4
"""
CELLS = 3 * 2 * 4 * 2  # points x seeds x (ckf + dead reckoning)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(**extra) -> dict:
    return {**os.environ, **THREAD_ENV, **extra}


def _stop(procs: list[subprocess.Popen], timeout: float = 15.0) -> None:
    """SIGTERM each process by pid, SIGKILL what is still alive after ``timeout``."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def _start_worker(address: str, name: str, log: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [
            str(BIN / "dask"),
            "worker",
            address,
            "--host",
            "127.0.0.1",
            "--nthreads",
            "1",
            "--nworkers",
            "1",
            "--no-dashboard",
            "--name",
            name,
            "--death-timeout",
            "60",
        ],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        env=_env(),
    )


def _start_scheduler(log: Path) -> tuple[subprocess.Popen, str]:
    """`dask scheduler` on 127.0.0.1 (any free port); the process and its address."""
    port = _free_port()
    sched = subprocess.Popen(
        [
            str(BIN / "dask"),
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--no-dashboard",
            "--dashboard-address",
            "127.0.0.1:0",  # its health/metrics endpoints: loopback, any free port
        ],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        env=_env(),
    )
    return sched, f"tcp://127.0.0.1:{port}"


def _kill_tree(pid: int) -> None:
    """SIGKILL a process and its children, as a crashed host would die."""
    tree = psutil.Process(pid)
    for p in [*tree.children(recursive=True), tree]:
        p.kill()


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1; yields the address."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("dask")
    sched, address = _start_scheduler(logs / "scheduler.log")
    procs = [sched]
    try:
        procs += [_start_worker(address, f"w{k}", logs / f"w{k}.log") for k in range(2)]
        with Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        with contextlib.suppress(Exception):  # ~1 s, where SIGTERM to each takes ~8 s
            with Client(address, timeout=10) as client:
                client.shutdown()
        _stop(procs[::-1])
        assert all(p.poll() is not None for p in procs)


def _per_seed(result) -> dict:
    return {(f, m): result.per_trial(f, m) for f in result.filters for m in METRICS}


def test_same_numbers_serial_embedded_and_external_cluster(scheduler):
    spec = parse_sweep(SPEC)
    serial = run_sweep(spec, study=Study(jobs=1))
    embedded_study = Study(jobs=2)
    embedded = run_sweep(spec, study=embedded_study)
    external_study = Study(scheduler=scheduler)
    external = run_sweep(spec, study=external_study)
    assert (embedded_study.stats.backend, embedded_study.stats.workers) == ("dask", 2)
    assert (external_study.stats.backend, external_study.stats.workers) == ("dask", 2)
    ref = _per_seed(serial)
    for other in (embedded, external):
        assert other.failures == []
        for key, values in _per_seed(other).items():
            np.testing.assert_array_equal(values, ref[key], err_msg=str(key))
        for a, b in zip(serial.runs, other.runs, strict=True):
            np.testing.assert_array_equal(a.estimators["ekf"].track, b.estimators["ekf"].track)
            np.testing.assert_array_equal(a.truth, b.truth)


def test_killed_worker_has_its_cells_retried(scheduler, tmp_path):
    from distributed import Client

    spec = parse_sweep({**SPEC, "run": {"steps": 150, "trials": 4}})
    reference = run_sweep(spec, study=Study(jobs=1))
    doomed = _start_worker(scheduler, "doomed", tmp_path / "doomed.log")
    killed: list[int] = []
    try:
        with Client(scheduler, timeout=30) as observer:
            observer.wait_for_workers(3, timeout=60)
            doomed_addr = next(
                a for a, w in observer.scheduler_info()["workers"].items() if w["name"] == "doomed"
            )

            def kill_when_busy(done: float, total: float) -> None:
                # The first time the doomed worker is running a task, kill it (and its
                # process tree) as a crashed host would die.
                if killed or not observer.processing(workers=[doomed_addr])[doomed_addr]:
                    return
                _kill_tree(doomed.pid)
                killed.append(doomed.pid)

            study = Study(scheduler=scheduler, store=ResultStore(tmp_path), progress=kill_when_busy)
            result = run_sweep(spec, study=study)
    finally:
        _stop([doomed])
    assert killed, "the doomed worker never ran a task"
    assert result.failures == [] and study.stats.computed == study.stats.cells
    for key, values in _per_seed(reference).items():
        np.testing.assert_array_equal(_per_seed(result)[key], values)


def test_cluster_left_without_workers_stops_the_study(tmp_path):
    """Every worker of an existing cluster dies: the study stops within its timeout with
    one error (the scheduler alone would keep the tasks waiting forever), and the cells
    finished before are in the store; a cluster with no worker at all is refused."""
    from distributed import Client

    from resloc.errors import ResLocError
    from resloc.experiments.backends import ClusterLostError

    def overdue(signum, frame):
        raise TimeoutError("the study kept waiting for a worker")

    spec = parse_sweep({**SPEC, "run": {"steps": 150, "trials": 4}})
    sched, address = _start_scheduler(tmp_path / "scheduler.log")
    procs = [sched]
    previous = signal.signal(signal.SIGALRM, overdue)
    signal.alarm(120)  # bounded even when the study would wait forever
    try:
        with pytest.raises(ClusterLostError, match="no worker joined in 2 s"):
            run_sweep(spec, study=Study(scheduler=address, cluster_timeout=2.0))
        worker = _start_worker(address, "only", tmp_path / "only.log")
        procs.append(worker)
        observer = Client(address, timeout=30)
        observer.wait_for_workers(1, timeout=60)
        killed: list[float] = []

        def kill_after_first_cell(done: float, total: float) -> None:
            # Kill once a second result sits finished on the worker, not yet fetched: the
            # study must not wait forever to gather it (dask reschedules it, no worker).
            if done >= 1 and not killed:
                deadline = time.monotonic() + 30
                while time.monotonic() < deadline:
                    if sum(bool(w) for w in observer.who_has().values()) >= 2:
                        break
                    time.sleep(0.05)
                _kill_tree(worker.pid)
                killed.append(time.monotonic())

        store = ResultStore(tmp_path / "store")
        study = Study(
            scheduler=address, store=store, progress=kill_after_first_cell, cluster_timeout=3.0
        )
        try:
            with pytest.raises(ClusterLostError, match="no worker for 3 s") as caught:
                run_sweep(spec, study=study)
        finally:
            observer.close()
        waited = time.monotonic() - killed[0]
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        _stop(procs[::-1])
    assert isinstance(caught.value, ResLocError)  # the CLI: one line, exit 2
    assert f"dask worker {address}" in str(caught.value)
    assert 3.0 <= waited < 30.0
    assert 1 <= study.stats.computed < study.stats.cells
    assert len(_entries(tmp_path / "store")) == study.stats.computed


def _study_processes(mark: str) -> list[psutil.Process]:
    """Live (non-zombie) processes started by a test run tagged with ``mark``."""
    found = []
    for p in psutil.process_iter(["status"]):
        try:
            if p.info["status"] != psutil.STATUS_ZOMBIE and p.environ().get("RESLOC_MARK") == mark:
                found.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return found


def _no_orphans(mark: str, timeout: float = 20.0) -> list[psutil.Process]:
    deadline = time.monotonic() + timeout
    while (left := _study_processes(mark)) and time.monotonic() < deadline:
        time.sleep(0.2)
    for p in left:  # never leave anything behind, even when failing
        p.kill()
    return left


def _entries(store: Path) -> list[Path]:
    return sorted(store.glob("v1/*/*.cell"))


def _start_study(args: list[str], mark: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [str(BIN / "resloc"), *args],
        cwd=cwd,
        env=_env(RESLOC_MARK=mark),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a shell job
    )


def _wait_for_entries(p: subprocess.Popen, store: Path, n: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while len(_entries(store)) < n:
        assert p.poll() is None, p.communicate()[1]
        assert time.monotonic() < deadline, "no cell finished in time"
        time.sleep(0.05)


@pytest.mark.parametrize("how", ["ctrl-c", "sigkill"])
def test_sweep_killed_mid_run_resumes_without_recomputing(tmp_path, how):
    sweep = tmp_path / "s.toml"
    sweep.write_text(SWEEP_FILE)
    store = tmp_path / "store"
    mark = uuid.uuid4().hex
    args = ["sweep", str(sweep), "-j", "2", "--store", str(store), "--no-plots"]
    p = _start_study([*args, "--out", str(tmp_path / "first")], mark, tmp_path)
    _wait_for_entries(p, store, 1)
    if how == "ctrl-c":
        os.killpg(p.pid, signal.SIGINT)  # a terminal's Ctrl-C reaches the whole group
    else:
        p.kill()
    _, err = p.communicate(timeout=60)
    assert _no_orphans(mark) == []
    if how == "ctrl-c":
        assert p.returncode == 130, err
        assert "run the same command again to resume" in err
        assert "Traceback" not in err and "leaked" not in err, err
    else:
        assert p.returncode == -signal.SIGKILL
    assert not (tmp_path / "first").exists()  # nothing half-written
    kept = {e: e.stat().st_mtime_ns for e in _entries(store)}
    assert 0 < len(kept) < CELLS

    p = _start_study([*args, "--out", str(tmp_path / "second")], mark, tmp_path)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert f"cells: {CELLS} ({len(kept)} from the store" in err, err
    assert f"{CELLS - len(kept)} computed" in err, err
    assert {e: e.stat().st_mtime_ns for e in kept} == kept  # read, never rewritten
    assert len(_entries(store)) == CELLS
    rows = (tmp_path / "second" / "cells.csv").read_text().splitlines()
    assert len(rows) == 1 + CELLS and all(",ok," in r for r in rows[1:])
    assert _no_orphans(mark) == []


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_reproduce_quick_stopped_leaves_no_process(tmp_path, how):
    store = tmp_path / "store"
    mark = uuid.uuid4().hex
    out = tmp_path / "rep"
    args = ["reproduce", "--quick", "-j", "2", "--store", str(store), "--out", str(out)]
    p = _start_study(args, mark, tmp_path)
    _wait_for_entries(p, store, 1, timeout=90)
    if how == "ctrl-c":  # the previous process pool ended this in an AttributeError
        os.killpg(p.pid, signal.SIGINT)
    else:
        p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == (130 if how == "ctrl-c" else 143), err
    assert "interrupted:" in err and "Traceback" not in err and "leaked" not in err, err
    assert _no_orphans(mark) == []
    assert not out.exists()
    assert not list(store.glob("v1/*/*.tmp"))  # no half-written entry
