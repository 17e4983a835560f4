"""The adversary suite: the strongest attackers we can write, one registry.

Every attacker knows the defence it faces completely (the victim's parameters, predictions,
innovation covariances and sequence-test state) and uses the whole acceptance region of the
victim's detector (:mod:`resloc.world.attackers.oracle`), except the outside reviewer's
attacker, which by design knows only the gate. ``docs/beyond.md`` ("The adversary suite")
describes each strategy and the threat model.

Each strategy has parameters (bias size, on/off period, ramp time, replay delay, number of
compromised robots...) and a small grid of them (``grid``) that the study searches against
every defence, reporting the worst point (:func:`variants`).

Adding an attacker is one class (the :class:`~resloc.world.attackers.base.Attacker`
protocol) and one line in :data:`ATTACKERS`.
"""

from __future__ import annotations

from resloc.world.attackers.base import Attacker, AttackStep, SensingLie
from resloc.world.attackers.estimates import CompromisedRobot, Replay
from resloc.world.attackers.oracle import accepted, largest_accepted, largest_accepted_along
from resloc.world.attackers.reciprocal import TwoEnded
from resloc.world.attackers.sensing import (
    BearingBias,
    CommonTranslation,
    CoordinatedDisplacement,
    ForceTrigger,
    OnOffBias,
    RampBias,
    RangeBias,
    ReviewerGateOnly,
    StarveTrigger,
)

__all__ = [
    "ATTACKERS",
    "AttackStep",
    "Attacker",
    "SensingLie",
    "accepted",
    "attacker",
    "largest_accepted",
    "largest_accepted_along",
    "make_attacker",
    "variants",
]

#: Every strategy of the suite, by name, with its default parameters.
ATTACKERS: dict[str, Attacker] = {
    a.name: a
    for a in (
        RangeBias(),
        BearingBias(),
        CommonTranslation(),
        OnOffBias(),
        RampBias(),
        StarveTrigger(),
        ForceTrigger(),
        CoordinatedDisplacement(),
        CompromisedRobot(),
        Replay(),
        ReviewerGateOnly(),
        TwoEnded(),
    )
}


def attacker(name: str) -> Attacker:
    """The strategy called ``name``; ``KeyError`` naming the known ones otherwise."""
    try:
        return ATTACKERS[name]
    except KeyError:
        raise KeyError(f"unknown attacker {name!r}; known: {', '.join(ATTACKERS)}") from None


def make_attacker(name: str, **params) -> Attacker:
    """Strategy ``name`` with ``params`` (the rest at their defaults); ``KeyError`` for an
    unknown name, ``ValueError`` for an unknown parameter."""
    return type(attacker(name))(**params)


def variants(name: str) -> list[Attacker]:
    """Every point of strategy ``name``'s parameter grid (what the study searches)."""
    return type(attacker(name)).variants()
