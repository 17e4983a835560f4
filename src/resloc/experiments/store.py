"""A content-addressed result store: every study cell is computed once.

A cell's key is the SHA-256 of a canonical serialization of what determines its result
(:func:`cell_key`): the resolved scenario, the seed (trial index), the filter, the
package version and a fingerprint of the package's source (:func:`source_fingerprint`), so a
code change never returns cells computed by the old code. Its value is written once,
atomically (a temporary file in the same directory, then ``os.replace``), with a SHA-256
checksum of the payload in the header; a truncated or corrupt entry is detected on read,
reported with a warning and recomputed.

Layout: ``<root>/v1/<key[:2]>/<key>.cell``; each file is ``RESLOC-CELL 1 <sha256>\\n``
followed by the pickled result. The store holds pickles: only point ``--store`` at a
directory you trust (the default is ``runs/.store`` beside your results).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import json
import math
import os
import pickle
import secrets
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from resloc import __version__

__all__ = [
    "DEFAULT_STORE",
    "CorruptEntryWarning",
    "ResultStore",
    "canonical_json",
    "cell_key",
    "default_store",
    "source_fingerprint",
]

#: Default store directory (relative to the working directory); ``$RESLOC_STORE`` overrides it.
DEFAULT_STORE = Path("runs") / ".store"
_MAGIC = b"RESLOC-CELL 1 "
_LAYOUT = "v1"


def default_store() -> Path:
    """``$RESLOC_STORE`` if set, else :data:`DEFAULT_STORE`."""
    return Path(os.environ.get("RESLOC_STORE") or DEFAULT_STORE)


class CorruptEntryWarning(UserWarning):
    """A store entry failed its checksum or could not be read; it is recomputed."""


def _canonical(value: Any) -> Any:
    """Plain JSON types with a single spelling for every value (keys sorted on dump)."""
    if isinstance(value, enum.Enum):
        return _canonical(value.value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _canonical(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, np.ndarray):
        return {"ndarray": str(value.dtype), "shape": list(value.shape), "data": value.tolist()}
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        # repr() is the shortest exact spelling; NaN and infinities are not JSON numbers.
        return f if math.isfinite(f) else repr(f)
    if value is None or isinstance(value, str):
        return value
    raise TypeError(f"cannot canonicalize {type(value).__name__} for a store key")


def canonical_json(value: Any) -> str:
    """One JSON text per value: sorted keys, no spaces, floats by ``repr``, enums by value,
    arrays with dtype and shape. Equal inputs give equal text on every machine."""
    return json.dumps(_canonical(value), sort_keys=True, separators=(",", ":"))


def fingerprint_sources(root: Path) -> str:
    """SHA-256 (hex) of every ``*.py`` file under ``root``: relative paths and contents, in
    sorted order (compiled caches are not sources and are left out)."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode("utf-8") + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


@functools.cache
def source_fingerprint() -> str:
    """The installed package's :func:`fingerprint_sources`, once per process (~20 ms).

    The version alone keys cells too coarsely while developing: an edit to the estimator
    without a version bump would read the old code's cells back."""
    return fingerprint_sources(Path(__file__).resolve().parents[1])


def cell_key(kind: str, **parts: Any) -> str:
    """The store key of a cell: SHA-256 (hex) of its kind, parts, the package version and
    the package's source fingerprint."""
    text = canonical_json(
        {"kind": kind, "resloc": __version__, "source": source_fingerprint(), **parts}
    )
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


class ResultStore:
    """Cell results on disk, keyed by :func:`cell_key`.

    Parameters
    ----------
    root : Path, optional
        Store directory (created on the first write; default :func:`default_store`).
    read : bool
        ``False`` ignores existing entries (``--fresh``): every cell is recomputed, and
        written again.
    """

    def __init__(self, root: str | Path | None = None, read: bool = True) -> None:
        self.root = Path(root) if root is not None else default_store()
        self.read = bool(read)

    def path(self, key: str) -> Path:
        """Where ``key``'s entry lives."""
        return self.root / _LAYOUT / key[:2] / f"{key}.cell"

    def get(self, key: str) -> tuple[bool, Any]:
        """``(True, value)`` for a valid entry, ``(False, None)`` when absent, unreadable
        (``read=False``) or corrupt (a :class:`CorruptEntryWarning` is issued)."""
        if not self.read:
            return False, None
        p = self.path(key)
        try:
            blob = p.read_bytes()
        except FileNotFoundError:
            return False, None
        head, sep, payload = blob.partition(b"\n")
        ok = sep and head.startswith(_MAGIC)
        if ok and hashlib.sha256(payload).hexdigest().encode() == head[len(_MAGIC) :]:
            try:
                return True, pickle.loads(payload)
            except Exception:  # checksum matched but the pickle is unusable
                pass
        warnings.warn(
            f"result store: entry {p} is corrupt (checksum mismatch or unreadable); "
            "recomputing the cell",
            CorruptEntryWarning,
            stacklevel=2,
        )
        return False, None

    def put(self, key: str, value: Any) -> Path:
        """Write ``value`` under ``key`` atomically (temp file + fsync + rename)."""
        payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        digest = hashlib.sha256(payload).hexdigest().encode()
        p = self.path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        # The temporary file is named before it is created and created inside the ``try``:
        # an interrupt (Ctrl-C) at any moment after its creation removes it (with
        # ``tempfile.mkstemp`` the file existed before its name was known to this frame).
        tmp = p.parent / f".{key[:12]}.{secrets.token_hex(8)}.tmp"
        try:
            with open(tmp, "xb") as fh:
                fh.write(_MAGIC + digest + b"\n" + payload)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, p)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return p

    def __contains__(self, key: str) -> bool:
        return self.path(key).exists()

    def keys(self) -> list[str]:
        """Every key with an entry (valid or not)."""
        base = self.root / _LAYOUT
        return sorted(p.stem for p in base.glob("*/*.cell")) if base.exists() else []
