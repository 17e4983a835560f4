"""Shared fixtures for the lower-layer tests (angles, linalg, models, filters, cl)."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable

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
    # A suite started in the background by a non-interactive shell inherits SIGINT ignored
    # (POSIX), and so would every process it starts; the Ctrl-C tests simulate a terminal's
    # foreground job, so give SIGINT Python's usual handler (a child gets it back at exec).
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # Likewise `nohup` starts the suite with SIGHUP ignored; the hang-up tests simulate a
    # closed terminal, so SIGHUP gets its default action back (the commands catch it).
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
        signal.signal(signal.SIGHUP, signal.SIG_DFL)


#: The big compiled forms (tiny runs of the default scenario that reach them), in shares
#: for the xdist workers, balanced by their cold compile CPU (docs/performance.md, "Cold
#: compile": the options' form ~96 s, the joints' ~76 s, the paper's ~24 s, summed ~22 s,
#: the witness pass ~8 s).
_WARM_SHARES = (("options", "witness"), ("paper", "joints", "summed"))
_WARM_RUNS = {
    "paper": {},
    "options": {"defence": "full+redundancy+sequence+reciprocal"},
    "joints": {"estimator.fusion": "tracked"},
    "summed": {"estimator.update_mode": "summed"},
    "witness": {"defence": "zone+full+redundancy+sequence+cap+landmarks+witness"},
}


def pytest_sessionstart(session):
    """With ``RESLOC_TEST_WARM_SHARES`` set (``make test``), each xdist worker first compiles
    its share of the big forms into numba's on-disk cache. On a cold cache (a fresh clone,
    CI) each worker would otherwise compile nearly every form its tests reach, the same ones
    in both (~4 min of CPU each); this way each compiles about half and loads the rest. On a
    warm cache it only loads them (a few seconds)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not os.environ.get("RESLOC_TEST_WARM_SHARES") or not worker or count < 2:
        return
    from resloc.cl.kernels import HAVE_NUMBA

    if not HAVE_NUMBA:
        return
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import DEFENCES
    from resloc.experiments.runner import run_scenario

    base = default_scenario().replace(
        **{"run.steps": 3, "run.trials": 1, "run.dead_reckoning": False,
           "run.filters": ["ckf", "ekf"]}
    )  # fmt: skip
    index = int(worker.removeprefix("gw"))
    for k, share in enumerate(_WARM_SHARES):
        if k % count != index:
            continue
        for name in share:
            overrides = dict(_WARM_RUNS[name])
            defence = overrides.pop("defence", None)
            if defence is not None:
                overrides.update(DEFENCES[defence])
            run_scenario(base.replace(**overrides))
