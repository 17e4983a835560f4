"""One validation layer for every number that enters resloc from outside.

Scenario files, sweep files, command-line options and dataset rows all pass through the
helpers below, so that the same rules hold everywhere:

* every number is finite (``inf`` and ``nan`` are rejected; no field of resloc means
  "unbounded" by ``inf``) and inside a physical range stated next to the field;
* integers stay inside TOML's signed 64-bit range, so that anything resloc accepts it can
  also write back into a ``scenario.toml`` that reloads;
* before a large allocation, the memory it needs is estimated and compared with the memory
  the machine has available (:func:`check_memory`), so that an oversized run fails in one
  line before it starts instead of with a ``MemoryError`` (or the OOM killer) minutes later;
* free text that is written into files or figures (a run name) is one printable line.

Every failure is a :class:`~resloc.errors.ConfigError` (or, for data files,
:class:`~resloc.errors.DataError`) with one line that names the field (or ``file:line``),
the value and the fix. This module sits at the bottom of the layers (beside
:mod:`resloc.errors`) so that the dataset readers, the world and the experiments can all
use it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from resloc.errors import ConfigError

__all__ = [
    "INT64_MAX",
    "MEMORY_FRACTION",
    "available_memory",
    "cap_workers",
    "check_finite",
    "check_memory",
    "check_one_line_name",
    "check_seed",
    "format_bytes",
]

#: Largest integer a TOML file can hold (signed 64 bit); seeds and counts stay below it.
INT64_MAX = 2**63 - 1
#: Share of the available memory one command may plan to use (the rest is headroom for
#: the interpreter, temporaries inside numpy and the other processes on the machine).
MEMORY_FRACTION = 0.7
#: Longest run name: it becomes part of file contents and figure titles.
NAME_MAX_LENGTH = 200


def check_finite(
    path: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    unit: str = "",
) -> float:
    """Return ``value`` as a float if it is finite and inside ``[lo, hi]``.

    Parameters
    ----------
    path : str
        The field's name as the user wrote it (``sensing.radius``, ``--dt``).
    value : float
    lo, hi : float, optional
        Inclusive bounds (``lo`` exclusive with ``lo_open``).
    unit : str
        Appended to the bounds in the message (``" m"``).

    Raises
    ------
    ConfigError
        One line naming ``path``, the value and the accepted range.
    """
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{path}: {value!r} is not a finite number; give a finite value")
    if lo is not None and (v <= lo if lo_open else v < lo):
        op = ">" if lo_open else ">="
        raise ConfigError(f"{path}: {value!r} is out of range; use {op} {lo:g}{unit}")
    if hi is not None and v > hi:
        raise ConfigError(f"{path}: {value!r} is out of range; use <= {hi:g}{unit}")
    return v


def check_seed(path: str, seed: int) -> int:
    """A seed must be a non-negative integer that TOML can store (< 2**63)."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"{path}: expected a non-negative integer, got {seed!r}")
    if not 0 <= seed <= INT64_MAX:
        raise ConfigError(
            f"{path}: {seed} is outside 0 .. {INT64_MAX} (a seed must fit TOML's 64-bit "
            "integers so that the written scenario.toml reloads)"
        )
    return seed


def check_one_line_name(path: str, name: str) -> str:
    """A name written into files and figure titles: one printable line, bounded length."""
    if not isinstance(name, str):
        raise ConfigError(f"{path}: expected a string, got {name!r}")
    if not name.strip():
        raise ConfigError(f"{path}: empty; give a short name such as 'arc-turn'")
    if len(name) > NAME_MAX_LENGTH:
        raise ConfigError(f"{path}: {len(name)} characters; use at most {NAME_MAX_LENGTH}")
    bad = next((c for c in name if not c.isprintable()), None)
    if bad is not None:
        raise ConfigError(
            f"{path}: contains the control character {bad!r}; use one line of printable text"
        )
    return name


# ---------------------------------------------------------------------------- memory
def available_memory() -> int | None:
    """Bytes this process can still allocate: ``MemAvailable`` of ``/proc/meminfo``, lowered
    by a cgroup (container) limit when one is set. ``None`` where neither is readable."""
    avail = None
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        avail = None
    limit = _cgroup_headroom()
    if limit is not None:
        avail = limit if avail is None else min(avail, limit)
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, AttributeError):
            return None
    return avail


def _cgroup_headroom() -> int | None:
    """cgroup v2 ``memory.max - memory.current`` of this process's group, if limited."""
    base = Path("/sys/fs/cgroup")
    try:
        limit = (base / "memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int((base / "memory.current").read_text().strip())
        return max(int(limit) - used, 0)
    except (OSError, ValueError):
        return None


def format_bytes(n: float) -> str:
    """``1.5 GiB``-style size."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


def check_memory(needed: float, what: str, fix: str, available: int | None = None) -> None:
    """Refuse a computation whose estimated memory exceeds what the machine has.

    Parameters
    ----------
    needed : float
        Estimated peak bytes.
    what : str
        What needs it, for the message (``run.trials x team.robots = 5000000 robots``).
    fix : str
        How to make it smaller (``lower run.steps or team.robots``).
    available : int, optional
        Bytes available (default: :func:`available_memory`).

    Raises
    ------
    ConfigError
        ``{what}: needs about X GiB, more than the Y GiB this machine has available; {fix}``.
    """
    avail = available_memory() if available is None else available
    if avail is None:
        return
    budget = MEMORY_FRACTION * avail
    if not math.isfinite(needed) or needed > budget:
        raise ConfigError(
            f"{what}: needs about {format_bytes(needed)} of memory, more than the "
            f"{format_bytes(budget)} this machine can give it ({format_bytes(avail)} "
            f"available); {fix}"
        )


def cap_workers(requested: int, cells: int, cores: int | None = None) -> int:
    """Worker processes to start: no more than the cells to compute nor the usable cores.

    Parameters
    ----------
    requested : int
        ``--jobs`` (>= 1).
    cells : int
        Independent pieces of work.
    cores : int, optional
        CPUs this process may use (default: its affinity mask).
    """
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - not on Linux
            cores = os.cpu_count() or 1
    return max(1, min(int(requested), int(cells), int(cores)))
