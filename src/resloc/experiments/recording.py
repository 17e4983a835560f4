"""The replayable record of one team: what the exports (TUM, ROS 2 bag, Foxglove, the browser
viewer) need from a run, kept in ``recording.npz`` beside the run's other outputs.

A :class:`Recording` holds, for trial 0 of a simulation or for an MRCLAM replay, the true
poses, every estimator's poses and covariances at every step, every sensed link with what
happened to it (attacked, detected, triggered, delivered, fused) and the danger zones.
Only numpy is needed; the file is ``numpy.savez_compressed`` with poses as float32 (0.5 um
resolution at 10 m), covariances as float32 (6 unique entries) and the per-link outcomes
packed into one byte.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from resloc.errors import DataError
from resloc.signals import held

__all__ = [
    "LINK_FLAGS",
    "RECORDING_FILE",
    "LinkLog",
    "Recording",
    "ZoneDisc",
    "link_columns",
    "pack_outcomes",
    "recording_from_mrclam",
    "recording_from_run",
]

#: File name of the recording inside a run directory.
RECORDING_FILE = "recording.npz"
#: Format version written into the file (bumped when a key changes meaning).
FORMAT_VERSION = 1
#: Per-link, per-estimator outcomes, in bit order.
LINK_FLAGS = ("detected", "triggered", "delivered", "fused")
_TRIU = np.triu_indices(3)
_BIT_WEIGHTS = (1 << np.arange(8)).astype(np.uint8)
#: Columns of a link log shared by every estimator of a run (the world's links).
LINK_COLUMNS = ("step", "i", "j", "attacked")


def pack_outcomes(*flags: np.ndarray) -> np.ndarray:
    """One byte per link holding the :data:`LINK_FLAGS` (in that order), shape (M,)."""
    if not flags:
        return np.zeros(0, np.uint8)
    stacked = np.asarray(flags, dtype=bool).reshape(len(flags), -1)
    if len(flags) > 8:
        raise ValueError(f"at most 8 flags fit in a byte, got {len(flags)}")
    # Bit b of a link's byte is row b: the rows weighted by 2^b and summed (distinct bits,
    # so no carry), what packbits along the flags gives, without its strided walk.
    return _BIT_WEIGHTS[: len(flags)] @ stacked.view(np.uint8)


def link_columns(rows: list[tuple]) -> dict[str, np.ndarray]:
    """The :data:`LINK_COLUMNS` of a run from per-step ``(step, i, j, attacked)`` rows."""
    if not rows:
        empty = (np.int32, np.int32, np.int32, bool)
        return {k: np.zeros(0, t) for k, t in zip(LINK_COLUMNS, empty, strict=True)}
    columns = zip(*rows, strict=True)
    return {k: np.concatenate(col) for k, col in zip(LINK_COLUMNS, columns, strict=True)}


class LinkLog(Mapping):
    """Every sensed link of one team over a run, with one estimator's outcome on each.

    ``log["step"]``, ``log["i"]``, ``log["j"]``, ``log["attacked"]`` are the world's links
    (the same arrays for every estimator of a run); ``log["triggered"]`` and the other
    :data:`LINK_FLAGS` are unpacked from one byte per link on access. Each shape (M,).
    """

    def __init__(self, shared: dict[str, np.ndarray], packed: np.ndarray):
        self.shared = shared
        self.packed = packed

    def __getitem__(self, key: str) -> np.ndarray:
        if key in self.shared:
            return self.shared[key]
        return (self.packed >> LINK_FLAGS.index(key)) & 1 == 1

    def __iter__(self) -> Iterator[str]:
        return iter((*LINK_COLUMNS, *LINK_FLAGS))

    def __len__(self) -> int:
        return len(LINK_COLUMNS) + len(LINK_FLAGS)


@dataclass(frozen=True)
class ZoneDisc:
    """A danger zone as drawn: ``kind`` ``"sdz"`` (sensing) or ``"cdz"`` (communication)."""

    kind: str
    center: tuple[float, float]
    radius: float


@dataclass
class Recording:
    """One team's run, step by step.

    Attributes
    ----------
    name : str
        Scenario or dataset name.
    source : str
        ``"run"`` (simulation, trial 0) or ``"mrclam"``.
    t0 : float
        Absolute time of ``time[0]`` (s since the Unix epoch; 0 for a simulation).
    time : ndarray, shape (K,)
        Seconds since ``t0`` of each recorded step.
    robots : list of str, length N
        Robot names (``robot1`` ...), used as ROS namespaces.
    truth : ndarray, shape (K, N, 3)
        True poses ``(x, y, theta)``.
    valid : ndarray of bool, shape (K, N)
        Where the truth exists (MRCLAM has gaps).
    estimates : dict of str to ndarray, each shape (K, N, 3)
        Estimated poses per estimator (``ckf``, ``ukf``, ``ekf``, ``dr``).
    covariances : dict of str to ndarray, each shape (K, N, 3, 3)
        Empty for run directories written before recordings existed.
    links : dict of str to ndarray, each shape (M,), or None
        Every sensed link: ``step`` (index into ``time``), observer ``i``, target ``j`` (a
        robot index, or ``N + landmark index``) and ``attacked``, sorted by ``step``. None when
        not recorded.
    outcomes : dict of str to dict of str to ndarray of bool, each shape (M,)
        Per estimator, the :data:`LINK_FLAGS` of every link (rows as in ``links``).
    zones : list of ZoneDisc
    landmarks : ndarray, shape (L, 2)
    meta : dict
        Free-form description (dt, seed, the writer's version).
    """

    name: str
    source: str
    t0: float
    time: np.ndarray
    robots: list[str]
    truth: np.ndarray
    valid: np.ndarray
    estimates: dict[str, np.ndarray]
    covariances: dict[str, np.ndarray] = field(default_factory=dict)
    links: dict[str, np.ndarray] | None = None
    outcomes: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    zones: list[ZoneDisc] = field(default_factory=list)
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    meta: dict = field(default_factory=dict)

    @property
    def n_robots(self) -> int:
        return len(self.robots)

    @property
    def filters(self) -> list[str]:
        """Estimators other than dead reckoning, in recorded order."""
        return [n for n in self.estimates if n != "dr"]

    def step_links(self, k: int) -> slice:
        """Rows of ``links`` at step ``k`` (links are sorted by step)."""
        step = self.links["step"]
        return slice(
            int(np.searchsorted(step, k, side="left")), int(np.searchsorted(step, k, "right"))
        )

    # ------------------------------------------------------------------ file
    def save(self, path: Path) -> Path:
        """Write ``path`` (``numpy.savez_compressed``)."""
        arrays: dict[str, np.ndarray] = {
            "time": np.asarray(self.time, float),
            "truth": np.asarray(self.truth, np.float32),
            "valid": np.asarray(self.valid, bool),
            "landmarks": np.asarray(self.landmarks, float).reshape(-1, 2),
        }
        meta = {
            "format": FORMAT_VERSION,
            "name": self.name,
            "source": self.source,
            "t0": self.t0,
            "robots": list(self.robots),
            "estimators": list(self.estimates),
            "covariances": list(self.covariances),
            "zones": [
                {"kind": z.kind, "center": list(map(float, z.center)), "radius": float(z.radius)}
                for z in self.zones
            ],
            "meta": self.meta,
        }
        arrays["meta"] = np.array(json.dumps(meta))
        for name, track in self.estimates.items():
            arrays[f"track__{name}"] = np.asarray(track, np.float32)
        for name, cov in self.covariances.items():
            arrays[f"cov__{name}"] = np.asarray(cov, np.float32)[..., _TRIU[0], _TRIU[1]]
        if self.links is not None:
            for key in ("step", "i", "j"):
                arrays[f"link__{key}"] = np.asarray(self.links[key], np.int32)
            arrays["link__attacked"] = np.asarray(self.links["attacked"], bool)
            for name, flags in self.outcomes.items():
                arrays[f"outcome__{name}"] = pack_outcomes(*(flags[k] for k in LINK_FLAGS))
        path = Path(path)
        with held():  # an interrupted savez leaves a ZipFile that prints a traceback
            np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load(cls, path: Path) -> Recording:
        """Read a file written by :meth:`save` (a clear :class:`DataError` otherwise)."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
            meta = json.loads(str(data["meta"]))
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(
                f"{path}: not a resloc recording ({exc}); re-run to rewrite it"
            ) from None
        if meta.get("format") != FORMAT_VERSION:
            raise DataError(
                f"{path}: recording format {meta.get('format')} is not {FORMAT_VERSION}; "
                "re-run with this version of resloc"
            )
        covariances = {}
        for name in meta["covariances"]:
            flat = data[f"cov__{name}"].astype(float)
            full = np.empty((*flat.shape[:-1], 3, 3))
            full[..., _TRIU[0], _TRIU[1]] = flat
            full[..., _TRIU[1], _TRIU[0]] = flat
            covariances[name] = full
        links, outcomes = None, {}
        if "link__step" in data:
            links = {k: data[f"link__{k}"] for k in ("step", "i", "j", "attacked")}
            for name in meta["estimators"]:
                packed = data.get(f"outcome__{name}")
                if packed is None:
                    continue
                outcomes[name] = {
                    key: (packed >> bit) & 1 == 1 for bit, key in enumerate(LINK_FLAGS)
                }
        return cls(
            name=meta["name"],
            source=meta["source"],
            t0=float(meta["t0"]),
            time=data["time"],
            robots=list(meta["robots"]),
            truth=data["truth"].astype(float),
            valid=data["valid"],
            estimates={n: data[f"track__{n}"].astype(float) for n in meta["estimators"]},
            covariances=covariances,
            links=links,
            outcomes=outcomes,
            zones=[ZoneDisc(z["kind"], tuple(z["center"]), z["radius"]) for z in meta["zones"]],
            landmarks=data["landmarks"],
            meta=meta.get("meta", {}),
        )


def recording_from_run(result) -> Recording:
    """The recording of trial 0 of a :class:`~resloc.experiments.runner.RunResult`."""
    sc = result.scenario
    truth = np.asarray(result.truth)
    K, N = truth.shape[:2]
    estimates = {n: e.track for n, e in result.estimators.items()}
    covariances = {n: e.cov for n, e in result.estimators.items() if e.cov is not None}
    logged = [e.links for e in result.estimators.values() if e.links is not None]
    links, outcomes = None, {}
    if logged:
        links = {k: logged[0][k] for k in LINK_COLUMNS}
        M = len(links["step"])
        for name, e in result.estimators.items():
            if e.links is None:  # dead reckoning: no link used
                outcomes[name] = {k: np.zeros(M, bool) for k in LINK_FLAGS}
            else:
                outcomes[name] = {k: e.links[k] for k in LINK_FLAGS}
    zones = [ZoneDisc("sdz", tuple(z.center), z.radius) for z in sc.world.sdz] + [
        ZoneDisc("cdz", tuple(z.center), z.radius) for z in sc.world.cdz
    ]
    dt = float(result.time[0]) if len(result.time) else 0.0
    return Recording(
        name=sc.run.name,
        source="run",
        t0=0.0,
        time=dt * np.arange(K),
        robots=[f"robot{r + 1}" for r in range(N)],
        truth=truth,
        valid=np.ones((K, N), bool),
        estimates=estimates,
        covariances=covariances,
        links=links,
        outcomes=outcomes,
        zones=zones,
        meta={"dt": dt, "seed": sc.run.seed, "trial": 0},
    )


def recording_from_mrclam(result) -> Recording:
    """The recording of a :class:`~resloc.experiments.mrclam.MRCLAMResult`."""
    m = result.measurements
    links = None
    outcomes = {}
    if m:
        links = {k: np.asarray(m[k]) for k in ("step", "i", "j", "attacked")}
        outcomes = {
            n: {k: np.asarray(e.links[k], bool) for k in LINK_FLAGS}
            for n, e in result.estimators.items()
        }
    zones = [
        ZoneDisc(kind, tuple(z.center), z.radius)
        for kind in ("sdz", "cdz")
        for z in result.zones.get(kind, [])
    ]
    return Recording(
        name=str(result.info.get("dataset", "mrclam")),
        source="mrclam",
        t0=float(result.info.get("t0_unix", 0.0)),
        time=np.asarray(result.time, float),
        robots=[f"robot{int(s)}" for s in result.robots],
        truth=np.asarray(result.truth),
        valid=np.asarray(result.valid, bool),
        estimates={n: e.track for n, e in result.estimators.items()},
        covariances={n: e.cov for n, e in result.estimators.items() if e.cov is not None},
        links=links,
        outcomes=outcomes,
        zones=zones,
        landmarks=np.asarray(result.landmark_xy, float),
        meta={"dt": result.config.dt, "seed": result.config.seed},
    )
