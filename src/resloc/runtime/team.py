"""What the whole team agrees on before a run: size, step, filter and estimator parameters.

Every process (world, radio, robots, recorder) builds the same :class:`TeamSetup` from the
same files (:func:`team_setup`): the scenario of ``resloc run`` or an MRCLAM replay's
configuration. Nothing here runs a filter.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resloc.cl.fusion_methods import FusionStrategy, fusion_strategy
from resloc.cl.params import CLParams, NeighbourEstimate
from resloc.errors import ConfigError
from resloc.experiments.config import RiskSource, Scenario
from resloc.experiments.config_parse import load_scenario
from resloc.filters.base import FilterKind, GaussianFilter, make_filter
from resloc.runtime.options import SwarmOptions
from resloc.world.attacks import AttackKind

__all__ = ["TeamSetup", "check_supported", "team_setup"]

#: End-of-step exchanges (``FusionStrategy.node_exchanges``) the runtime carries.
RUNTIME_EXCHANGES = frozenset({"acks", "consensus", "delivery_acks", "factors"})


def runtime_refusal(strategy: FusionStrategy) -> str | None:
    """Why robot processes over the runtime do not run this fusion method, or None."""
    if strategy.node_refusal is not None:
        return strategy.node_refusal
    missing = set(strategy.node_exchanges) - RUNTIME_EXCHANGES
    if missing:
        return f"its {', '.join(sorted(missing))} messages are not carried by the runtime yet"
    return None


@dataclass
class TeamSetup:
    """The team-wide constants of a run.

    Attributes
    ----------
    robots : int
    dt : float
    steps : int
    params : CLParams
    filter_name : str
    gauge_rounds : int
        Consensus exchanges per step with gauge fusion (0 otherwise).
    scenario : Scenario or None
        The simulated world's scenario (None for a replay).
    mrclam : MRCLAMConfig or None
    """

    robots: int
    dt: float
    steps: int
    params: CLParams
    filter_name: str
    gauge_rounds: int
    scenario: Scenario | None = None
    mrclam: object | None = None

    def link_params(self, z: np.ndarray) -> list[tuple[np.ndarray, CLParams]]:
        """This step's links ``z: (E, 2)`` grouped by the parameters they are fused with
        (one group; a replay groups them by range-noise level, as ``resloc mrclam``)."""
        if self.mrclam is not None:
            from resloc.runtime.replay import replay_link_params

            return replay_link_params(self, z)
        return [(np.arange(len(z)), self.params)]

    def make_filter(self) -> GaussianFilter:
        if self.scenario is None:
            return make_filter(FilterKind(self.filter_name))
        e = self.scenario.estimator
        return make_filter(FilterKind(self.filter_name), e.ukf_alpha, e.ukf_beta, e.ukf_kappa)

    @property
    def gauge(self) -> bool:
        """The method exchanges gauge acknowledgements and consensus messages."""
        return "consensus" in fusion_strategy(self.params.fusion).node_exchanges

    @property
    def risk_zones(self) -> tuple | None:
        """``(SDZ, CDZ)`` risk fields a robot evaluates at its own predicted estimate
        (``trigger.risk_source = "estimated"``: the zone map is known, the true position is
        not), or None: the world sends the risks at the true position."""
        if self.scenario is None or self.scenario.trigger.risk_source is not RiskSource.ESTIMATED:
            return None
        from resloc.world.world import zone_field

        return zone_field(self.scenario.world.sdz), zone_field(self.scenario.world.cdz)

    @property
    def split(self) -> bool:
        """Split covariance intersection: estimates carry the sender's independent part and
        a robot tells each neighbour it fused (an ACK frame without gauge blocks)."""
        return "delivery_acks" in fusion_strategy(self.params.fusion).node_exchanges

    @property
    def factors(self) -> bool:
        """Factorized fusion: estimates carry the factors their sender keeps for the robots
        it measured; after the correction a robot tells each higher id it fused so (an ACK
        frame of ids), then each robot sends its lower partners its pair messages (an ACK
        frame of round 1)."""
        return "factors" in fusion_strategy(self.params.fusion).node_exchanges

    @property
    def team_size(self) -> int | None:
        """The team size a robot's node needs (gauge and factorized fusion), else None."""
        return self.robots if self.gauge or self.factors else None

    @property
    def acks(self) -> bool:
        """The step has an acknowledgement phase (gauge, split CI or factorized)."""
        return self.gauge or self.split or self.factors

    @property
    def readings(self) -> bool:
        """Estimates carry their sender's readings of this step (the receiver's row is the
        reverse link's measurement, ``RobotNode.correct``'s ``z_reciprocal``)."""
        return bool(self.params.zone_trust or self.params.reciprocal)

    @property
    def witness(self) -> bool:
        """Estimates carry their sender's witness notes of the step before
        (``RobotNode.witness_notes``; the receiver's ``RobotNode.receive_witness``)."""
        return bool(self.params.witness)

    @property
    def pull(self) -> bool:
        """Estimates are pulled on trigger (``neighbour_estimate = "cached"``), not broadcast
        every step (``"current"``: the trigger needs j's current estimate)."""
        return self.params.neighbour_estimate is NeighbourEstimate.CACHED


def check_supported(scenario: Scenario) -> None:
    """Refuse scenario options the runtime does not run, naming the field (ConfigError)."""
    if scenario.run.trials != 1:
        raise ConfigError(
            f"run.trials: {scenario.run.trials}; a swarm is one team, set run.trials = 1"
        )
    refusal = runtime_refusal(fusion_strategy(scenario.estimator.fusion))
    if refusal is not None:
        raise ConfigError(
            f"estimator.fusion: {scenario.estimator.fusion.value!r} is not run by robot "
            f"processes ({refusal}); use naive, gauge, ci, split_ci or factorized"
        )
    if scenario.trigger.lambda2 == "distributed":
        raise ConfigError(
            "trigger.lambda2: 'distributed' is not run by the runtime yet; use component or global"
        )
    pulled = scenario.estimator.neighbour_estimate is NeighbourEstimate.CACHED
    for name in ("zone_trust", "reciprocal", "witness"):
        if pulled and getattr(scenario.detector, name):
            raise ConfigError(
                f"detector.{name}: pulled estimates (estimator.neighbour_estimate = 'cached') "
                "do not carry the sender's readings or notes; use 'current' with it in a swarm"
            )
    if scenario.world.attack.kind is AttackKind.STEALTHY:
        raise ConfigError(
            "attack.kind: 'stealthy' needs the victim's filter inside the world; "
            "use random, fixed, gaussian or replay"
        )


def team_setup(options: SwarmOptions) -> TeamSetup:
    """The team's constants from the run's files (scenario or MRCLAM replay)."""
    if options.replay:
        from resloc.experiments.mrclam import MRCLAMConfig

        cfg = MRCLAMConfig(
            filters=(options.filter,),
            dt=options.replay_dt,
            duration=options.replay_seconds or None,
            landmarks=False,
        )
        robots, steps = options.robots, options.replay_steps
        if not robots:  # the supervisor: read the dataset once and tell the others
            from resloc.runtime.replay import load_replay

            rp = load_replay(
                options.replay, TeamSetup(0, cfg.dt, 0, cfg.cl_params(), "", 0, None, cfg)
            )
            robots, steps = rp.dataset.n_robots, rp.steps
        return TeamSetup(
            robots=robots,
            dt=cfg.dt,
            steps=steps,
            params=cfg.cl_params(),
            filter_name=options.filter,
            gauge_rounds=0,
            mrclam=cfg,
        )
    scenario = load_scenario(Path(options.scenario))
    check_supported(scenario)
    params = scenario.cl_params()
    gauge = "consensus" in fusion_strategy(params.fusion).node_exchanges
    return TeamSetup(
        robots=scenario.world.team.robots,
        dt=scenario.world.motion.dt,
        steps=scenario.run.steps,
        params=params,
        filter_name=options.filter,
        gauge_rounds=scenario.estimator.gauge_rounds if gauge else 0,
        scenario=scenario,
    )
