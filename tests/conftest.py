"""Shared fixtures for the lower-layer tests (angles, linalg, models, filters, cl)."""

from __future__ import annotations

import signal
from collections.abc import Callable

import numpy as np
import pytest


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
