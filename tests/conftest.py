"""Shared fixtures for the lower-layer tests (angles, linalg, models, filters, cl)."""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(autouse=True, scope="session")
def _session_result_store(tmp_path_factory):
    """Module-scoped fixtures run before function-scoped ones: without a session-wide store a
    study started by one (a quick report) would write its cells into ./runs/.store."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RESLOC_STORE", str(tmp_path_factory.mktemp("session-store")))
        yield


@pytest.fixture(autouse=True)
def _private_result_store(tmp_path_factory, monkeypatch):
    """Studies run by tests keep their cells in a temporary store, never in ./runs/.store."""
    monkeypatch.setenv("RESLOC_STORE", str(tmp_path_factory.mktemp("store")))


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test (tests never touch the global ``np.random``)."""
    return np.random.default_rng(20240611)


@pytest.fixture
def random_spd() -> Callable[..., np.ndarray]:
    """``random_spd(rng, B, n, scale=1.0, cond=10.0)``: SPD batch ``(B, n, n)``.

    Eigenvalues are drawn in ``[scale / cond, scale]`` with random orthogonal eigenvectors.
    """

    def make(
        rng: np.random.Generator, B: int, n: int, scale: float = 1.0, cond: float = 10.0
    ) -> np.ndarray:
        Qm, _ = np.linalg.qr(rng.normal(size=(B, n, n)))
        w = scale * np.exp(rng.uniform(-np.log(cond), 0.0, size=(B, n)))
        P = np.einsum("bij,bj,bkj->bik", Qm, w, Qm)
        return 0.5 * (P + np.swapaxes(P, -1, -2))

    return make


def pytest_configure(config):
    if (
        os.environ.get("RESLOC_TEST_WARM_SHARES")
        and not os.environ.get("PYTEST_XDIST_WORKER")
        and getattr(config.option, "numprocesses", None)
    ):  # the controller of an xdist run: the workers inherit the variable
        config._resloc_warm_marks = tempfile.mkdtemp(prefix="resloc-warm-")
        os.environ[_WARM_MARKS] = config._resloc_warm_marks
    # A suite started in the background by a non-interactive shell inherits SIGINT ignored
    # (POSIX), and so would every process it starts; the Ctrl-C tests simulate a terminal's
    # foreground job, so give SIGINT Python's usual handler (a child gets it back at exec).
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # Likewise `nohup` starts the suite with SIGHUP ignored; the hang-up tests simulate a
    # closed terminal, so SIGHUP gets its default action back (the commands catch it).
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
        signal.signal(signal.SIGHUP, signal.SIG_DFL)


def pytest_unconfigure(config):
    marks = getattr(config, "_resloc_warm_marks", None)
    if marks is not None:
        shutil.rmtree(marks, ignore_errors=True)
        os.environ.pop(_WARM_MARKS, None)


#: The big compiled forms, in shares for the xdist workers, balanced by their cold compile
#: (measured on a cold cache, 2026-11-28, wall seconds of one worker: the options' form
#: ~190 with its stages, of which its link rounds ~105 and its row-order loop ~87 alone,
#: ~30 shared; the joints' ~104, the paper's ~28, summed ~28, the witness stages ~25). The
#: options' form is compiled in two halves, one per worker, each a tiny correction of its
#: own (``_WARM_PIECES``); the other items are tiny runs of the default scenario. A run of an
#: item waits for the items it needs from the other worker (``_WARM_AFTER``); the joints
#: come after the row-order loop, whose split CI link their form calls too. One share, as
#: it was, put the options' form and the witness on one worker: 240 s against the other's
#: 160 s, the second worker idle for the difference.
_WARM_SHARES = (
    ("paper", "options-rounds", "options", "summed", "witness"),
    ("options-rows", "joints"),
)
_WARM_RUNS = {
    "paper": {},
    "options": {"defence": "full+redundancy+sequence+reciprocal"},
    "joints": {"estimator.fusion": "tracked"},
    "summed": {"estimator.update_mode": "summed"},
    "witness": {"defence": "zone+full+redundancy+sequence+cap+landmarks+witness"},
}
#: Items whose runs load the options' form (the others' runs skip its warm-up).
_WARM_WITH_OPTIONS = ("options", "witness")
_WARM_AFTER = {"options": ("options-rows",)}
#: How long a worker waits for another's item (a cold compile on a loaded machine takes
#: ~4 min; past this it goes on and its tests compile what they reach).
_WARM_WAIT_S = 600.0
_WARM_MARKS = "RESLOC_TEST_WARM_MARKS"
#: A file to which each worker appends its items' wall times, when set (measurement only).
_WARM_LOG = "RESLOC_TEST_WARM_LOG"


def _options_half(rounds: bool) -> None:
    """One half of the options' form (:func:`resloc.cl.kernels.warm_up` does both): its
    link rounds or its row-order loop, by a correction that reaches only that loop."""
    from resloc.cl.kernels import fast_correct
    from resloc.cl.kernels_inputs import pair_warm_up_batch
    from resloc.cl.kernels_rounds import every_stage, rounds_warm_up_batch
    from resloc.cl.params import CLParams
    from resloc.filters.base import make_filter

    with every_stage():
        if rounds:
            fast_correct(make_filter("ckf"), *rounds_warm_up_batch(), CLParams())
        else:
            for kind in ("ckf", "ekf"):
                fast_correct(make_filter(kind), *pair_warm_up_batch(), CLParams())


_WARM_PIECES = {
    "options-rounds": lambda: _options_half(rounds=True),
    "options-rows": lambda: _options_half(rounds=False),
}


def _warm_marks() -> Path | None:
    """The directory where the workers mark their finished shares (made by the controller,
    :func:`pytest_configure`), or None."""
    where = os.environ.get(_WARM_MARKS)
    return Path(where) if where else None


def _run_item(name: str, base) -> None:
    from resloc.experiments import runner
    from resloc.experiments.defences import DEFENCES

    if name in _WARM_PIECES:
        _WARM_PIECES[name]()
        return
    overrides = dict(_WARM_RUNS[name])
    defence = overrides.pop("defence", None)
    if defence is not None:
        overrides.update(DEFENCES[defence])
    warm_up_kernels = runner.warm_up_kernels
    with pytest.MonkeyPatch.context() as patch:
        if name not in _WARM_WITH_OPTIONS:  # its warm-up would compile the options' form
            patch.setattr(
                runner, "warm_up_kernels", lambda paper, options: warm_up_kernels(True, False)
            )
        runner.run_scenario(base.replace(**overrides))


def _run_share(share: tuple[str, ...], marks: Path | None) -> None:
    from resloc.experiments.config import default_scenario

    base = default_scenario().replace(
        **{"run.steps": 3, "run.trials": 1, "run.dead_reckoning": False,
           "run.filters": ["ckf", "ekf"]}
    )  # fmt: skip
    began = time.monotonic()
    for name in share:
        if marks is not None:
            _wait_for_items(marks, _WARM_AFTER.get(name, ()))
        start = time.monotonic()
        try:
            _run_item(name, base)
        except BaseException:
            if marks is not None:  # the others stop waiting for it and the rest of the share
                for left in share[share.index(name) :]:
                    (marks / f"{left}.failed").touch()
            raise
        if marks is not None:
            (marks / name).touch()
        if os.environ.get(_WARM_LOG):  # "worker item start end", seconds from the share's start
            with open(os.environ[_WARM_LOG], "a", encoding="utf-8") as log:
                worker = os.environ.get("PYTEST_XDIST_WORKER", "")
                log.write(f"{worker} {name} {start - began:.1f} {time.monotonic() - began:.1f}\n")


def _wait_for_items(marks: Path, names) -> None:
    deadline = time.monotonic() + _WARM_WAIT_S
    while time.monotonic() < deadline and not all(
        (marks / name).exists() or (marks / f"{name}.failed").exists() for name in names
    ):
        time.sleep(0.2)


def pytest_sessionstart(session):
    """With ``RESLOC_TEST_WARM_SHARES`` set (``make test``), each xdist worker first compiles
    its share of the big forms into numba's on-disk cache, then waits for the others'. On a
    cold cache (a fresh clone, CI) each worker would otherwise compile nearly every form its
    tests reach, the same ones in both (~4 min of CPU each); this way each compiles about
    half and loads the rest. On a warm cache it only loads them (a few seconds)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not os.environ.get("RESLOC_TEST_WARM_SHARES") or not worker or count < 2:
        return
    from resloc.cl.kernels import HAVE_NUMBA

    if not HAVE_NUMBA:
        return
    marks = _warm_marks()
    index = int(worker.removeprefix("gw"))
    for k, share in enumerate(_WARM_SHARES):
        if k % count == index:
            _run_share(share, marks)
    if marks is not None:
        _wait_for_items(marks, [name for share in _WARM_SHARES for name in share])
