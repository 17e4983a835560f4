"""Where study tasks run: in this process, or on Dask distributed (an embedded
``LocalCluster`` or an existing scheduler). :func:`open_backend` chooses, once, for every
study; :func:`prepare_worker` is the one place where a worker process is set up.

The embedded cluster: ``jobs`` worker processes with one thread each, every socket on
127.0.0.1, the Bokeh dashboard off (Dask's default binds 0.0.0.0:8787). A worker that dies
mid-task has its tasks rescheduled by the scheduler; a task that keeps killing workers
(``KilledWorker``) is submitted again up to :data:`RESUBMIT` times.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

from resloc.errors import ConfigError, ResLocError

if TYPE_CHECKING:
    from resloc.experiments.executor import Task

__all__ = [
    "RESUBMIT",
    "THREAD_ENV",
    "ClusterLostError",
    "dask_available",
    "default_jobs",
    "open_backend",
    "prepare_worker",
    "run_task",
    "warm_up_kernels",
]


#: Environment of worker processes: one BLAS/OpenMP/numba thread each (the parallelism is
#: across processes).
THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}
#: How many times a task whose worker died is submitted again.
RESUBMIT = 3
_INSTALL_HINT = "pip install 'resloc[cluster]'"

ProgressFn = Callable[[float, float], None]


def default_jobs() -> int:
    """Worker processes by default: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


_PREPARED = False


def prepare_worker() -> None:
    """Set up a worker process once: one BLAS/OpenMP thread (when ``threadpoolctl`` is
    available; worker processes also start with :data:`THREAD_ENV`) and the compiled
    kernels loaded (from numba's on-disk cache when the client warmed them up)."""
    global _PREPARED
    if _PREPARED:
        return
    _PREPARED = True
    for k, v in THREAD_ENV.items():
        os.environ.setdefault(k, v)
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    warm_up_kernels()


def warm_up_kernels(paper: bool = True, options: bool = True) -> None:
    """Compile the optional numba kernels once (here), so that workers load them from the
    on-disk cache instead of compiling them again in parallel (``paper``, ``options``: the
    link loops' forms, :func:`resloc.cl.kernels.warm_up`)."""
    try:
        from resloc.cl import kernels
    except ImportError:  # pragma: no cover - numba is optional
        return
    warm = getattr(kernels, "warm_up", None)
    if warm is not None and warm(paper, options):
        from resloc.world import kernels as world_kernels  # the world step's twin

        world_kernels.warm_up()


def run_task(fn: Callable[..., Sequence[Any]], args: tuple, in_worker: bool = True):
    """Run one task where it lands: ``("ok", results)`` or ``("error", text, traceback)``.

    Exceptions are returned, not raised, so that a deterministic failure is reported once
    (not retried by the scheduler) and looks the same on every backend.
    """
    if in_worker:
        prepare_worker()
    try:
        results = list(fn(*args))
    except Exception as exc:  # every failure of user work is reported
        return ("error", f"{type(exc).__name__}: {exc}", traceback.format_exc())
    return ("ok", results)


class _Backend:
    """Runs tasks; yields ``(task, outcome)`` as they finish (``outcome`` from
    :func:`run_task`)."""

    name = ""
    workers = 1
    resubmitted = 0

    def run(self, tasks: list[Task]) -> Iterator[tuple[Task, tuple]]:
        raise NotImplementedError


class _SerialBackend(_Backend):
    """Every task in this process, in order."""

    name = "serial"

    def run(self, tasks: list[Task]) -> Iterator[tuple[Task, tuple]]:
        for task in tasks:
            yield task, run_task(task.fn, task.args, in_worker=False)


class ClusterLostError(ResLocError):
    """Every worker of an existing Dask cluster left and none came back in time."""


class _DaskBackend(_Backend):
    """Tasks on a Dask ``Client`` (embedded ``LocalCluster`` or an existing scheduler).

    ``workerless_limit`` (seconds, external clusters): the scheduler keeps the tasks of a
    cluster whose every worker died waiting for a worker forever; after this long without
    one the study stops with :class:`ClusterLostError` (its finished cells are in the
    store). ``None``: wait (the embedded cluster's nanny restarts its own workers).
    """

    name = "dask"
    #: Seconds between looks at the cluster's workers while nothing finishes.
    POLL = 0.05

    def __init__(self, client, workers: int, workerless_limit: float | None = None) -> None:
        self.client = client
        self.workers = workers
        self.workerless_limit = workerless_limit
        self.address = getattr(client.scheduler, "address", "the cluster")

    def _finished(self, pending) -> Iterator[Any]:
        """The futures of ``pending`` as they finish; raises :class:`ClusterLostError`
        when the cluster has had no worker for ``workerless_limit`` seconds."""
        if self.workerless_limit is None:
            yield from pending
            return
        workerless_since: float | None = None
        next_look = 0.0
        while not pending.is_empty():
            if pending.has_ready():
                yield from pending.next_batch(block=False)
                workerless_since = None
                continue
            time.sleep(self.POLL)
            now = time.monotonic()
            if now < next_look:
                continue
            next_look = now + 1.0
            if self.client.nthreads():
                workerless_since = None
            elif workerless_since is None:
                workerless_since = now
            elif now - workerless_since >= self.workerless_limit:
                raise ClusterLostError(
                    f"--scheduler {self.address}: no worker for {self.workerless_limit:g} s "
                    f"({pending.count()} tasks not run); start `dask worker "
                    f"{self.address}` and run the same command again (finished cells are "
                    "in the store)"
                )

    def _gather(self, fut) -> tuple | None:
        """A finished future's result, or None when it could not be fetched within the
        workerless limit: its worker died after finishing it, so dask reschedules the task
        and ``result()`` would wait for a worker forever, out of the watchdog's sight."""
        if self.workerless_limit is None:
            return fut.result()
        try:
            return fut.result(timeout=max(self.workerless_limit, 1.0))
        except TimeoutError:
            return None

    def run(self, tasks: list[Task]) -> Iterator[tuple[Task, tuple]]:
        from distributed import as_completed

        run_id = uuid.uuid4().hex[:8]
        attempts: dict[int, int] = {}

        def submit(n: int):
            attempts[n] = attempts.get(n, 0) + 1
            return self.client.submit(
                run_task,
                tasks[n].fn,
                tasks[n].args,
                key=f"resloc-{run_id}-{n}-{attempts[n]}",
                pure=False,
                priority=-n,
            )

        futures = {submit(n): n for n in range(len(tasks))}
        pending = as_completed(list(futures), loop=self.client.loop)
        try:
            for fut in self._finished(pending):
                n = futures.pop(fut)
                if fut.status == "error":
                    exc = fut.exception()
                    tb = "".join(traceback.format_tb(fut.traceback()))
                    if type(exc).__name__ == "KilledWorker" and attempts[n] <= RESUBMIT:
                        self.resubmitted += 1
                        new = submit(n)
                        futures[new] = n
                        pending.add(new)
                        continue
                    outcome: tuple = ("error", f"{type(exc).__name__}: {exc}", tb)
                elif fut.status == "cancelled":
                    outcome = ("error", "CancelledError: the cluster cancelled the task", "")
                else:
                    outcome = self._gather(fut)
                    if outcome is None:  # lost with its worker: dask runs it again
                        futures[fut] = n
                        pending.add(fut)
                        continue
                fut.release()
                yield tasks[n], outcome
        finally:
            for fut in futures:
                fut.cancel()


@contextlib.contextmanager
def _quiet_dask_logs() -> Iterator[None]:
    """Dask logs worker start/stop and closing streams at INFO/WARNING; keep stderr for the
    progress bar and real errors."""
    loggers = [logging.getLogger(n) for n in ("distributed", "tornado", "asyncio")]
    saved = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, level in zip(loggers, saved, strict=True):
            lg.setLevel(level)


def _import_distributed(reason: str):
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"{reason} needs Dask distributed: {_INSTALL_HINT}") from None
    return distributed


def dask_available() -> bool:
    """True when the ``cluster`` extra (dask distributed) is installed."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


#: Slower housekeeping for the embedded cluster (its workers inherit the config): an idle
#: 2-worker cluster used 0.056 CPU-s per second with Dask's defaults (event-loop tick every
#: 20 ms, system monitor every 0.5 s, memory monitor every 0.1 s), 0.032 with these.
_EMBEDDED_CONFIG = {
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}


@contextlib.contextmanager
def _local_cluster(workers: int) -> Iterator[_DaskBackend]:
    distributed = _import_distributed(f"--jobs {workers}")
    warm_up_kernels()  # compile once here; workers load numba's on-disk cache
    import dask

    with _quiet_dask_logs(), dask.config.set(_EMBEDDED_CONFIG):
        cluster = distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            scheduler_port=0,
            dashboard_address=None,  # its default binds 0.0.0.0:8787
            # The scheduler's HTTP endpoints (health, metrics) would try port 8787 on the
            # host; any free loopback port instead.
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            worker_dashboard_address=None,
            # Workers' own log lines: task errors reach the client with their tracebacks and
            # a dead worker is seen by the scheduler, but a worker whose heartbeat meets the
            # scheduler closing (a Ctrl-C) would print a traceback at ERROR level.
            silence_logs=logging.CRITICAL,
            env=dict(THREAD_ENV),
        )
        try:
            client = distributed.Client(cluster, set_as_default=False)
            try:
                client.register_plugin(_embedded_worker_plugin(distributed), name="resloc")
                yield _DaskBackend(client, workers)
            finally:
                client.close(timeout=10)
        finally:
            cluster.close(timeout=10)


def _embedded_worker_plugin(distributed):
    """A worker plugin for the embedded cluster: its workers ignore SIGINT (a Ctrl-C in the
    terminal reaches the whole process group; the client then stops them in order, without
    a traceback from every worker)."""

    class IgnoreInterrupt(distributed.WorkerPlugin):
        def setup(self, worker) -> None:
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreInterrupt()


def _check_address(address: str) -> None:
    if not address.startswith(("tcp://", "tls://")) or ":" not in address.split("://", 1)[1]:
        raise ConfigError(
            f"--scheduler {address}: expected tcp://HOST:PORT (the address `dask scheduler` prints)"
        )


@contextlib.contextmanager
def _external_cluster(address: str, timeout: float) -> Iterator[_DaskBackend]:
    _check_address(address)
    distributed = _import_distributed(f"--scheduler {address}")
    with _quiet_dask_logs():
        try:
            client = distributed.Client(address, timeout=timeout, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(
                f"--scheduler {address}: cannot connect ({type(exc).__name__}); is "
                "`dask scheduler` running there?"
            ) from None
        try:
            workers = len(client.scheduler_info()["workers"])
            if workers == 0:
                try:
                    client.wait_for_workers(1, timeout=timeout)
                except TimeoutError:
                    raise ClusterLostError(
                        f"--scheduler {address}: no worker joined in {timeout:g} s; start "
                        f"`dask worker {address}` and run the same command again"
                    ) from None
                workers = len(client.scheduler_info()["workers"])
            yield _DaskBackend(client, workers, workerless_limit=timeout)
        finally:
            client.close(timeout=10)


@contextlib.contextmanager
def open_backend(
    jobs: int | None, scheduler: str | None, tasks: int, timeout: float = 30.0
) -> Iterator[_Backend]:
    """The backend for ``tasks`` tasks.

    ``scheduler`` set: that Dask cluster. Otherwise ``jobs`` (default: the CPUs) capped by
    the tasks and the CPUs; one worker runs in this process, more start an embedded
    ``LocalCluster``. Without the ``cluster`` extra, an explicit ``jobs > 1`` is a
    :class:`ConfigError` and the default falls back to serial.
    """
    if scheduler:
        with _external_cluster(scheduler, timeout) as backend:
            yield backend
        return
    explicit = jobs is not None
    workers = max(1, min(int(jobs) if explicit else default_jobs(), tasks, default_jobs()))
    if workers > 1 and not explicit and not dask_available():
        workers = 1  # documented fallback: the default never requires the extra
    if workers == 1:
        yield _SerialBackend()
        return
    with _local_cluster(workers) as backend:
        yield backend
