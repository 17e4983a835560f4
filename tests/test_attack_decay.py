"""The compromised robots' answer to a decaying start-up floor: lying harder while it is high.

``harder`` (:class:`~resloc.world.attackers.estimates.CompromisedRobot`): while the
start-up stage raises the covariance of one of a liar's victims of the round by at least
that factor, the liar's lies of the round are the largest the victims' detectors accept,
not cut by the witness budget (``docs/attack/startup.md`` section 6).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import resloc.world.attackers.estimates as estimates
from resloc.cl.detection_startup import applied_startup_factors
from resloc.world.attackers import make_attacker

DEFENCE = "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay"


def test_spending_is_per_liar_and_needs_a_raised_floor_of_at_least_harder():
    adv = make_attacker("compromised", robots=3, harder=2.0)
    factors = np.array([1.0, 3.0, 1.5, 1.0, 2.0])
    victims = np.array([0, 1, 2, 3, 4, 0])
    liars = np.array([7, 7, 8, 9, 9, 8])
    # liar 7 has victim 1 (x3): both its rows; liar 8's victims are at x1.5 and x1: none;
    # liar 9 has victim 4 at exactly x2: both its rows.
    assert adv.spends(victims, liars, factors).tolist() == [True, True, False, True, True, False]
    at_one = make_attacker("compromised", harder=1.0)
    assert not at_one.spends(np.array([0, 3]), np.array([7, 7]), factors).any()  # none raised
    assert at_one.spends(np.array([2]), np.array([7]), factors).all()
    assert not make_attacker("compromised").spends(victims, liars, factors * 10).any()


@pytest.mark.parametrize("value", [0.5, -1.0])
def test_a_harder_below_one_is_a_one_line_error(value):
    with pytest.raises(ValueError, match="parameter harder") as err:
        make_attacker("compromised", harder=value)
    assert "\n" not in str(err.value)
    assert make_attacker("compromised").harder == 0.0


def _lies(monkeypatch, harder: float, steps: int = 12):
    """A short run against the decaying floor with the witness budget cutting every lie to
    nothing: per tamper call and liar, the step, whether a lie was sent on its rows, whether
    the victims' detectors accept any (the oracle's largest fraction), and the largest
    start-up factor among its victims of the round."""
    from resloc.cl.backend import use_backend
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import defence_overrides
    from resloc.experiments.runner import run_scenario

    budgets = []

    def nothing(a, *args, **kwargs):  # a budget that allows no lie at all
        budgets.append(len(a))
        return np.zeros_like(a)

    monkeypatch.setattr(estimates, "within_witness", nothing)
    accepted = []
    oracle = estimates.largest_accepted_along

    def largest(*args, **kwargs):
        accepted.append(oracle(*args, **kwargs))
        return accepted[-1]

    monkeypatch.setattr(estimates, "largest_accepted_along", largest)
    calls = []
    attack = estimates.CompromisedRobot.attack

    def logged(self, links, step, params, memory):
        out = attack(self, links, step, params, memory)
        if out.tamper is None:
            return out
        inner = out.tamper

        def tamper(rows, z_hat, S):
            accepted.clear()
            z = inner(rows, z_hat, S)
            liar = np.isin(links.j[rows] % step.robots, self.targets(step.robots))
            f = applied_startup_factors(memory, len(step.pose))
            sent = np.abs(z - links.z[rows]).max(axis=1) > 1e-9  # (path(0): rounding)
            whole = np.zeros(len(rows))
            if accepted:
                whole[liar] = accepted[-1]
            for b in np.unique(links.j[rows][liar]):
                mine = liar & (links.j[rows] == b)
                victims = links.i[rows][mine]
                calls.append((step.k, sent[mine].any(), whole[mine].max() > 0, f[victims].max()))
            return z

        for attr in ("reported", "notes"):
            if hasattr(inner, attr):
                setattr(tamper, attr, getattr(inner, attr))
        return dataclasses.replace(out, tamper=tamper)

    monkeypatch.setattr(estimates.CompromisedRobot, "attack", logged)
    adv = make_attacker("compromised", robots=3, claimed_cov=0.01, harder=harder)
    sc = default_scenario().replace(
        **defence_overrides(DEFENCE),
        **{"run.steps": steps, "run.filters": ["ckf"], "run.dead_reckoning": False},
    )
    with use_backend("numpy"):
        run_scenario(sc.replace(**adv.overrides), adversary=adv)
    assert budgets  # the budget was asked
    return calls


def test_lying_harder_sends_the_lies_the_budget_cuts_while_a_floor_is_raised(monkeypatch):
    """With a budget that allows nothing, the attacker without ``harder`` sends no lie; with
    ``harder = 1`` a liar sends its lies exactly in the rounds where one of its victims'
    covariances is raised by the floor and the victims' detectors accept some lie (a liar
    its receivers convicted after a few such rounds is accepted nowhere for a while), and
    nothing in the rounds without a raised floor (the first steps: the initial covariance
    is above the floor)."""
    assert not any(sent for _, sent, _, _ in _lies(monkeypatch, 0.0))
    calls = _lies(monkeypatch, 1.0)
    floored = [(sent, ok) for _, sent, ok, f in calls if f > 1.0]
    free = [sent for _, sent, _, f in calls if f <= 1.0]
    assert free and sum(sent for sent, _ in floored) >= 5  # both kinds of round occur
    assert all(sent == ok for sent, ok in floored)
    assert not any(free)
