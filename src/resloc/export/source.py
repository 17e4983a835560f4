"""Read a run directory (``resloc run`` / ``resloc mrclam``) into a :class:`Recording`.

Run directories written since recordings exist hold ``recording.npz`` with everything.
Older ones still give trajectories: ``trajectories.csv`` (``resloc run``, every step) or
``timeseries.csv`` (``resloc mrclam``, sampled at 0.2 s); formats that need covariances or
link events then stop with a one-line error saying what is missing.
"""

from __future__ import annotations

import csv
import json
import tomllib
from pathlib import Path

import numpy as np

from resloc.errors import ConfigError, DataError
from resloc.experiments.recording import RECORDING_FILE, Recording, ZoneDisc

__all__ = ["load_run_dir", "require"]

_RERUN = "re-run it with this version of resloc (it writes recording.npz)"


def load_run_dir(run_dir: Path) -> Recording:
    """The recording of ``run_dir`` (see the module docstring for old directories).

    Raises
    ------
    ConfigError
        ``run_dir`` is not a run directory.
    DataError
        Its files are unreadable.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"RUN_DIR {run_dir}: not a directory; pass a resloc run directory")
    if (run_dir / RECORDING_FILE).is_file():
        return Recording.load(run_dir / RECORDING_FILE)
    if (run_dir / "trajectories.csv").is_file() and (run_dir / "scenario.toml").is_file():
        return _from_run_csv(run_dir)
    if (run_dir / "timeseries.csv").is_file() and (run_dir / "per_robot.csv").is_file():
        return _from_mrclam_csv(run_dir)
    raise ConfigError(
        f"RUN_DIR {run_dir}: no {RECORDING_FILE}, trajectories.csv or timeseries.csv; "
        "pass a directory written by resloc run or resloc mrclam"
    )


def require(rec: Recording, fmt: str, covariances: bool = False, links: bool = False) -> None:
    """Stop with one line if ``rec`` lacks what format ``fmt`` needs."""
    missing = []
    if covariances and not rec.covariances:
        missing.append("per-step covariances")
    if links and rec.links is None:
        missing.append("per-link events")
    if missing:
        raise DataError(
            f"--format {fmt}: this run directory has no {' or '.join(missing)} "
            f"(written before {RECORDING_FILE} existed); {_RERUN}"
        )


def _from_run_csv(run_dir: Path) -> Recording:
    """``trajectories.csv`` (step, robot, source, x, y, theta) and the scenario's zones."""
    path = run_dir / "trajectories.csv"
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        sc = tomllib.loads((run_dir / "scenario.toml").read_text(encoding="utf-8"))
        step = np.array([int(r["step"]) for r in rows])
        robot = np.array([int(r["robot"]) for r in rows])
        src = np.array([r["source"] for r in rows])
        xyt = np.array([[float(r["x"]), float(r["y"]), float(r["theta"])] for r in rows])
    except (OSError, KeyError, ValueError, tomllib.TOMLDecodeError) as exc:
        raise DataError(f"{path}: unreadable ({exc}); {_RERUN}") from None
    K, N = step.max() + 1, robot.max() + 1
    tracks = {}
    for name in dict.fromkeys(src.tolist()):
        arr = np.full((K, N, 3), np.nan)
        sel = src == name
        arr[step[sel], robot[sel]] = xyt[sel]
        tracks[name] = arr
    truth = tracks.pop("truth")
    dt = float(sc.get("motion", {}).get("dt", 1.0))
    zones = [
        ZoneDisc(kind, tuple(z["center"]), float(z["radius"]))
        for kind in ("sdz", "cdz")
        for z in sc.get(kind, [])
    ]
    return Recording(
        name=str(sc.get("run", {}).get("name", run_dir.name)),
        source="run",
        t0=0.0,
        time=dt * np.arange(K),
        robots=[f"robot{r + 1}" for r in range(N)],
        truth=truth,
        valid=np.isfinite(truth).all(-1),
        estimates=tracks,
        zones=zones,
        meta={"dt": dt, "from": "trajectories.csv"},
    )


def _from_mrclam_csv(run_dir: Path) -> Recording:
    """``timeseries.csv`` (sampled poses) and the zones of ``summary.json``."""
    path = run_dir / "timeseries.csv"
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader)
            table = np.array([[float(v) for v in row] for row in reader])
        summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, StopIteration) as exc:
        raise DataError(f"{path}: unreadable ({exc}); {_RERUN}") from None
    col = {h: k for k, h in enumerate(header)}
    times = np.unique(table[:, col["time_s"]])
    subjects = np.unique(table[:, col["robot"]]).astype(int)
    k = np.searchsorted(times, table[:, col["time_s"]])
    r = np.searchsorted(subjects, table[:, col["robot"]].astype(int))
    K, N = len(times), len(subjects)

    def grid(names: list[str]) -> np.ndarray:
        out = np.full((K, N, len(names)), np.nan)
        out[k, r] = table[:, [col[n] for n in names]]
        return out

    truth = grid(["x_true", "y_true", "theta_true"])
    valid = grid(["valid"])[..., 0] == 1
    names = [h[2:] for h in header if h.startswith("x_") and h != "x_true"]
    info = summary.get("info", {})
    zones = [
        ZoneDisc(kind, tuple(z["center"]), float(z["radius"]))
        for kind in ("sdz", "cdz")
        for z in info.get("zones", {}).get(kind, [])
    ]
    return Recording(
        name=str(info.get("dataset", run_dir.name)),
        source="mrclam",
        t0=float(info.get("t0_unix", 0.0)),
        time=times,
        robots=[f"robot{s}" for s in subjects],
        truth=truth,
        valid=valid,
        estimates={n: grid([f"x_{n}", f"y_{n}", f"theta_{n}"]) for n in names},
        zones=zones,
        meta={"from": "timeseries.csv"},
    )
