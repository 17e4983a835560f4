"""What every runtime process is told: one JSON file written by the supervisor."""

from __future__ import annotations

import enum
import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

__all__ = ["Mode", "SwarmOptions"]


class Mode(enum.StrEnum):
    """How the world advances."""

    LOCKSTEP = "lockstep"  # the world waits for every live robot's report each step
    REALTIME = "realtime"  # the world steps at dt in wall time; nobody waits


@dataclass
class SwarmOptions:
    """Options shared by the world, radio, robot and recorder processes of one run.

    Attributes
    ----------
    run_id : str
        Key-expression namespace of the run (``resloc/<run_id>/...``).
    connect : list of str
        Zenoh endpoints every process connects to (the router).
    key_file : str
        The team key (HMAC-SHA256).
    scenario : str
        Resolved scenario TOML (simulated world), or "" with ``replay``.
    filter : str
        ``ckf``, ``ukf`` or ``ekf``: every robot's filter.
    mode : Mode
    jam_acks : bool
        The radio jams gauge acknowledgements like any other message (False: delivered
        even inside a CDZ, as the in-process simulator does).
    max_age_steps : int
        Realtime: a neighbour estimate older than this many steps is dropped, not fused.
    max_age_s : float
        Any frame whose timestamp is further than this from the receiver's clock is stale.
    windows : tuple of float
        Realtime: fractions of dt a robot waits for estimates, acknowledgements and each
        consensus round before going on with what arrived.
    reply_window : float
        Realtime, pulled estimates (``neighbour_estimate = "cached"``): a request unanswered
        within this fraction of dt is counted (``requests_unanswered``) and its link skipped
        (triggered, not delivered).
    barrier_timeout_s : float
        Lockstep: how long the world and radio wait for a silent (alive) robot before
        dropping it from the step.
    startup_timeout_s : float
    connect_timeout_s : float
        How long a process tries to link to the router before giving up.
    out : str
        Recorder output directory.
    overwrite : bool
    plots : bool
    checkpoint_s : float
        The recorder rewrites partial results at most this often (so losing it loses
        little).
    rejoin_std : tuple of float
        Position (m) and heading (rad) standard deviation of a re-joining robot's prior.
    replay : str
        MRCLAM dataset folder (replaces the simulated world), or "".
    replay_dt : float
    replay_seconds : float
        Replay only the first seconds (0: all).
    robots : int
        Team size (filled in by the supervisor for a replay).
    replay_steps : int
        Steps of the replay (filled in by the supervisor).
    """

    run_id: str = "team"
    connect: list = field(default_factory=list)
    key_file: str = ""
    scenario: str = ""
    filter: str = "ckf"
    mode: Mode = Mode.LOCKSTEP
    jam_acks: bool = False
    max_age_steps: int = 3
    max_age_s: float = 10.0
    windows: tuple = (0.4, 0.15, 0.1)
    reply_window: float = 0.4
    barrier_timeout_s: float = 30.0
    startup_timeout_s: float = 120.0
    connect_timeout_s: float = 10.0
    out: str = ""
    overwrite: bool = False
    plots: bool = False
    checkpoint_s: float = 5.0
    rejoin_std: tuple = (0.5, 0.5)
    replay: str = ""
    replay_dt: float = 0.1
    replay_seconds: float = 0.0
    robots: int = 0
    replay_steps: int = 0

    def save(self, path: Path) -> Path:
        data = asdict(self)
        data["mode"] = self.mode.value
        Path(path).write_text(json.dumps(data, indent=1), encoding="utf-8")
        return Path(path)

    @classmethod
    def load(cls, path: Path) -> SwarmOptions:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        known = {f.name for f in fields(cls)}
        opts = cls(**{k: v for k, v in data.items() if k in known})
        opts.mode = Mode(opts.mode)
        opts.windows = tuple(opts.windows)
        opts.rejoin_std = tuple(opts.rejoin_std)
        return opts
