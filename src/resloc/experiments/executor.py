"""One parallel executor for every study (``reproduce``, ``compare``, ``sweep``).

A study is a set of *cells* (a resolved scenario, a seed, a filter: whatever determines one
result), computed by *tasks* (one task may compute several cells, e.g. the seeds of one
scenario batched in one simulation). A :class:`Study` reads the cells it already has from a
:class:`~resloc.experiments.store.ResultStore`, runs the tasks for the others on a backend
(:mod:`resloc.experiments.backends`: in this process, an embedded Dask ``LocalCluster`` or an
existing Dask cluster), writes every finished cell to the store as soon as its task returns,
and reports progress over cells.

A failing task does not stop the others: its cells are reported as :class:`CellFailure`
(with the task's context and the traceback). SIGINT/SIGTERM stop the cluster and its
workers and raise :class:`StudyInterrupted` (which says which signal); the finished cells
stay in the store, so running the study again resumes it. An existing cluster left without
workers stops the study after ``cluster_timeout`` seconds
(:class:`~resloc.experiments.backends.ClusterLostError`).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from resloc.experiments.backends import (
    RESUBMIT,
    THREAD_ENV,
    default_jobs,
    open_backend,
    prepare_worker,
)
from resloc.experiments.store import ResultStore

__all__ = [
    "RESUBMIT",
    "THREAD_ENV",
    "CellFailure",
    "Study",
    "StudyFailedError",
    "StudyInterrupted",
    "StudyStats",
    "Task",
    "default_jobs",
    "open_backend",
    "prepare_worker",
]

ProgressFn = Callable[[float, float], None]


@dataclass(frozen=True)
class Task:
    """A unit of work: ``fn(*args)`` returns one result per key of ``keys``, in order.

    Attributes
    ----------
    fn : callable
        A module-level (picklable) function.
    args : tuple
        Its arguments (picklable).
    keys : tuple of str
        Store keys of the cells it computes.
    label : str
        Short human-readable name (progress, failures).
    context : dict
        What a failure report shows about the task (e.g. the scenario as TOML, seeds).
    cost : float
        Relative cost; tasks are submitted most expensive first.
    """

    fn: Callable[..., Sequence[Any]]
    args: tuple
    keys: tuple[str, ...]
    label: str
    context: dict = field(default_factory=dict)
    cost: float = 1.0


@dataclass
class CellFailure:
    """A cell whose task raised: its key, the task, the error and the traceback."""

    key: str
    label: str
    context: dict
    error: str
    traceback: str

    def to_dict(self) -> dict:
        """Plain mapping for JSON."""
        return {
            "key": self.key,
            "label": self.label,
            "context": self.context,
            "error": self.error,
            "traceback": self.traceback,
        }


@dataclass
class StudyStats:
    """What a study did: cells read from the store, computed, failed; backend and workers."""

    cells: int = 0
    from_store: int = 0
    computed: int = 0
    failed: int = 0
    resubmitted: int = 0
    backend: str = "serial"
    workers: int = 1

    def to_dict(self) -> dict:
        """Plain mapping for JSON."""
        return dict(self.__dict__)


class StudyInterrupted(KeyboardInterrupt):
    """SIGINT/SIGTERM during a study; the finished cells are in the store. ``signum``: the
    signal that stopped it."""

    def __init__(
        self, stats: StudyStats, store: ResultStore | None, signum: int = signal.SIGINT
    ) -> None:
        where = f" in {store.root}" if store is not None else ""
        super().__init__(
            f"interrupted: {stats.from_store + stats.computed} of {stats.cells} cells "
            f"finished{where}; run the same command again to resume"
        )
        self.stats = stats
        self.signum = int(signum)


class _SignalInterrupt(KeyboardInterrupt):
    """A signal other than SIGINT, raised as KeyboardInterrupt so that every signal stops
    the cluster the same way; ``signum`` keeps which one it was."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"signal {signum}")
        self.signum = signum


class StudyFailedError(RuntimeError):
    """Some cells of a study failed; ``failures`` holds each one's context and traceback."""

    def __init__(self, failures: list[CellFailure], stats: StudyStats) -> None:
        first = failures[0]
        super().__init__(
            f"{stats.failed} of {stats.cells} cells failed (the others are in the store); "
            f"first: {first.label}: {first.error}"
        )
        self.failures = failures
        self.stats = stats


@contextlib.contextmanager
def _sigterm_raises_interrupt() -> Iterator[None]:
    """Turn SIGTERM into KeyboardInterrupt (main thread only), so that both signals stop the
    cluster the same way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise _SignalInterrupt(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# --------------------------------------------------------------------------- studies
class Study:
    """Cells of one study: read from the store or computed on the backend.

    Parameters
    ----------
    jobs : int, optional
        Worker processes of the embedded cluster (default: the CPUs).
    scheduler : str, optional
        ``tcp://HOST:PORT`` of an existing Dask scheduler.
    store : ResultStore, optional
        Where cells are read and written (``None``: nothing is kept).
    progress : callable(done, total), optional
        Called with finished cells / all cells.
    cluster_timeout : float
        Seconds to wait for an existing cluster's scheduler and, when every worker is
        gone, for one to (re)join before :class:`~resloc.experiments.backends.ClusterLostError`.
    """

    def __init__(
        self,
        jobs: int | None = None,
        scheduler: str | None = None,
        store: ResultStore | None = None,
        progress: ProgressFn | None = None,
        cluster_timeout: float = 30.0,
    ) -> None:
        self.jobs = jobs
        self.scheduler = scheduler
        self.cluster_timeout = cluster_timeout
        self.store = store
        self.progress = progress
        self.stats = StudyStats()
        self.failures: list[CellFailure] = []

    def lookup(self, key: str) -> tuple[bool, Any]:
        """``(True, value)`` when the store has the cell."""
        if self.store is None:
            return False, None
        return self.store.get(key)

    def run(self, tasks: list[Task], cells: int, from_store: int = 0) -> dict[str, Any]:
        """Run ``tasks`` and return ``{key: result}`` for every cell they computed.

        Parameters
        ----------
        tasks : list of Task
            Only the work still to do (the caller looked its cells up first).
        cells : int
            All cells of the study (progress total).
        from_store : int
            Cells the caller read from the store.

        Raises
        ------
        StudyInterrupted
            On SIGINT/SIGTERM, after the cluster is stopped.
        """
        st = self.stats
        st.cells, st.from_store = cells, from_store
        done = float(from_store)
        self._report(done)
        results: dict[str, Any] = {}
        order = sorted(tasks, key=lambda t: -t.cost)
        try:
            with (
                _sigterm_raises_interrupt(),
                open_backend(
                    self.jobs, self.scheduler, len(order), self.cluster_timeout
                ) as backend,
            ):
                st.backend, st.workers = backend.name, backend.workers
                for task, outcome in backend.run(order):
                    if outcome[0] == "ok":
                        values = outcome[1]
                        if len(values) != len(task.keys):
                            raise RuntimeError(
                                f"task {task.label} returned {len(values)} results for "
                                f"{len(task.keys)} cells"
                            )
                        for key, value in zip(task.keys, values, strict=True):
                            if self.store is not None:
                                self.store.put(key, value)
                            results[key] = value
                            st.computed += 1
                    else:
                        _, error, tb = outcome
                        self.failures += [
                            CellFailure(k, task.label, task.context, error, tb) for k in task.keys
                        ]
                        st.failed += len(task.keys)
                    done += len(task.keys)
                    self._report(done)
                st.resubmitted = backend.resubmitted
        except KeyboardInterrupt as exc:
            signum = getattr(exc, "signum", signal.SIGINT)
            raise StudyInterrupted(st, self.store, signum) from None
        return results

    def _report(self, done: float) -> None:
        if self.progress is not None:
            self.progress(done, float(max(self.stats.cells, 1)))
