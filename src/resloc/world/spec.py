"""The world's parameters (also the scenario-file sections ``team``, ``motion``,
``sensing``, ``attack``, ``sdz`` and ``cdz``).

Field metadata carries validation bounds used by :mod:`resloc.experiments.config`:
``min``/``max`` (inclusive), ``gt`` (strictly greater), ``doc``. Every number must also be
finite. The upper bounds are physical (an arena of kilometres, speeds of a robot), so that
no value that passes validation overflows the simulation.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from resloc.schema import option
from resloc.world.attacks import AttackKind, LinkScope, StealthKnowledge
from resloc.world.zones import RiskProfile

__all__ = [
    "STD_MIN",
    "AttackSpec",
    "ChannelRule",
    "FormationFrame",
    "MotionSpec",
    "SensingSpec",
    "TeamSpec",
    "WorldSpec",
    "ZoneSpec",
]


#: Smallest noise standard deviation: a zero std makes a covariance singular (NaN NEES,
#: covariance repairs). 1e-6 stands for "almost noiseless".
STD_MIN = 1e-6
#: Largest length (m) of a spacing, offset or noise std; an arena is at most ARENA_MAX.
LENGTH_MAX = 100.0
ARENA_MAX = 1e4
#: Largest speed (m/s, rad/s) or speed noise.
SPEED_MAX = 100.0


class FormationFrame(enum.StrEnum):
    """Frame of the followers' formation offsets: fixed in the world, or turning with the
    leader's path heading."""

    WORLD = "world"
    LEADER = "leader"


class ChannelRule(enum.StrEnum):
    """Whose CDZ risk jams a transmission on link (i, j): the receiver i's (``receiver``,
    the paper's ``Dc(i)``) or either end's (``either``: ``1 - (1 - Dc(i))(1 - Dc(j))``)."""

    RECEIVER = "receiver"
    EITHER = "either"


@dataclass(frozen=True)
class TeamSpec:
    """The team: a leader plus followers on a square lattice behind it."""

    robots: int = option(17, "number of robots (1 leader + followers)", min=1, max=200000)
    spacing: float = option(0.25, "lattice spacing of the followers (m)", gt=0.0, max=LENGTH_MAX)
    leader_gap: float = option(
        0.25,
        "distance from the leader to the first follower column (m)",
        min=0.0,
        max=LENGTH_MAX,
    )
    init_pos_std: float = option(
        0.05, "std of the initial position estimate error (m)", min=STD_MIN, max=LENGTH_MAX
    )
    init_heading_std: float = option(
        0.05, "std of the initial heading estimate error (rad)", min=STD_MIN, max=math.pi
    )


@dataclass(frozen=True)
class MotionSpec:
    """Leader path, follower control and odometry (Robotarium-like unicycles)."""

    dt: float = option(0.033, "time step (s)", min=1e-4, max=10.0)
    v_max: float = option(0.2, "linear speed limit (m/s)", gt=0.0, max=SPEED_MAX)
    omega_max: float = option(3.6, "angular speed limit (rad/s)", gt=0.0, max=SPEED_MAX)
    leader_speed: float = option(0.12, "leader's speed along its path (m/s)", gt=0.0, max=SPEED_MAX)
    waypoints: list = option(
        [[-0.4, -0.9], [0.4, -0.9], "arc", [0.4, 0.5], [-0.4, 0.5]],
        "leader path: [x, y] points; the string 'arc' between two points makes a "
        "half-circle turn (left) joining them",
    )
    formation: FormationFrame = option(FormationFrame.WORLD, "frame of the formation offsets")
    gain: float = option(1.5, "proportional gain of position tracking (1/s)", gt=0.0, max=1e3)
    projection: float = option(
        0.05, "look-ahead distance of the unicycle mapping (m)", gt=0.0, max=LENGTH_MAX
    )
    odometry_std: list = option(
        [0.01, 0.05], "std of measured [v (m/s), omega (rad/s)]", min=0.0, max=SPEED_MAX
    )
    process_floor_std: list = option(
        [0.001, 0.001, 0.001],
        "additive process-noise floor for [x, y, theta] per sqrt(s)",
        min=STD_MIN,
        max=LENGTH_MAX,
    )


@dataclass(frozen=True)
class SensingSpec:
    """Range/bearing sensing and the communication range."""

    radius: float = option(1.0, "sensing radius R (m)", gt=0.0, max=ARENA_MAX)
    comm_radius: float = option(1.0, "communication radius (m)", gt=0.0, max=ARENA_MAX)
    range_std: float = option(0.005, "range noise std (m)", min=STD_MIN, max=LENGTH_MAX)
    bearing_std: float = option(0.05, "bearing noise std (rad)", min=STD_MIN, max=math.pi)


@dataclass(frozen=True)
class AttackSpec:
    """How SDZs falsify measurements and CDZs jam links."""

    kind: AttackKind = option(AttackKind.RANDOM, "injected error: fixed bias or random in +-bias")
    bias: list = option(
        [0.4, 0.8], "injection magnitude [range (m), bearing (rad)]", min=0.0, max=LENGTH_MAX
    )
    links: LinkScope = option(LinkScope.FULL, "which links an SDZ can falsify: full or partial")
    link_fraction: float = option(
        0.5, "share of attackable links when links = 'partial'", min=0.0, max=1.0
    )
    channel: ChannelRule = option(ChannelRule.RECEIVER, "whose CDZ risk jams a link")
    stealth_margin: float = option(
        0.9,
        "stealthy: drive each detector statistic to this fraction of its threshold",
        gt=0.0,
        max=1.0,
    )
    stealth_direction: list = option(
        [1.0, 0.0],
        "stealthy: injection direction [range, bearing] (range by default)",
        min=-1e3,
        max=1e3,
    )
    stealth_knowledge: StealthKnowledge = option(
        StealthKnowledge.FULL, "stealthy: evade every test (full) or only the gate (gate)"
    )
    replay_delay: int = option(
        60, "replay: age of the replayed measurement (steps)", min=1, max=1_000_000
    )


@dataclass(frozen=True)
class ZoneSpec:
    """One danger zone (a ``[[sdz]]`` or ``[[cdz]]`` table)."""

    center: list = option([0.0, 0.0], "zone centre [x, y] (m)", min=-ARENA_MAX, max=ARENA_MAX)
    radius: float = option(0.4, "zone radius (m)", gt=0.0, max=ARENA_MAX)
    peak: float = option(1.0, "risk at the centre (probability)", min=0.0, max=1.0)
    profile: RiskProfile = option(RiskProfile.LINEAR, "risk profile from centre to edge")
    tau: float = option(0.0, "zone threshold tau: risk below it counts as 0", min=0.0, max=1.0)


@dataclass(frozen=True)
class WorldSpec:
    """Everything the simulated world needs."""

    team: TeamSpec = field(default_factory=TeamSpec)
    motion: MotionSpec = field(default_factory=MotionSpec)
    sensing: SensingSpec = field(default_factory=SensingSpec)
    attack: AttackSpec = field(default_factory=AttackSpec)
    sdz: tuple[ZoneSpec, ...] = ()
    cdz: tuple[ZoneSpec, ...] = ()
