"""Attackers that are not measurement lies: compromised robots' estimates, and replay."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.detection_lockout import discarded_shares
from resloc.cl.detection_startup import applied_startup_factors, floored_claims
from resloc.cl.detection_zone import reciprocal_rows
from resloc.world.adversary import ReplayBuffer
from resloc.world.attackers.base import SensingLie, Strategy
from resloc.world.attackers.oracle import fix_context, largest_accepted_along
from resloc.world.attackers.outvoted import shielding_notes, widened
from resloc.world.attackers.sensing import measurement_difference
from resloc.world.attackers.witness import WITNESS_BUDGETS, lying_notes, within_witness

__all__ = ["OWN_ESTIMATES", "SHIELDS", "CompromisedRobot", "Replay", "shifted_prediction"]

#: When the compromised robots' notes shield their honest victims, by the defence's params.
SHIELDS = {
    "auto": lambda params: bool(params.outvoted),
    "on": lambda params: True,
    "off": lambda params: False,
}

#: What a compromised robot does with its own estimate: ``"localized"``, it keeps fusing
#: what it sees (its estimate is as good as its neighbours' lies let it be);
#: ``"dead_reckoning"``, it fuses nothing (its own estimate, and what it broadcasts, drift
#: with its odometry). The robot is the attacker's: its own estimate is whatever the
#: attacker makes it, so a metric that counts it (the paper's MSLE over every robot) can be
#: driven as high as the attacker likes by any defence; ``"dead_reckoning"`` measures that.
OWN_ESTIMATES = ("localized", "dead_reckoning")

#: Robots compromised first, second, ... (spread over the default 17-robot lattice).
COMPROMISED_ORDER = (5, 10, 15, 2, 8, 13)


def shifted_prediction(z_hat: np.ndarray, shift_body: np.ndarray) -> np.ndarray:
    """The victim's predicted range and bearing of a neighbour whose broadcast position is
    moved by ``shift_body`` (the victim's own frame).

    Parameters
    ----------
    z_hat : ndarray, shape (E, 2)
        Predicted ``[range, bearing]`` from the honest broadcast.
    shift_body : ndarray, shape (..., E, 2)

    Returns
    -------
    ndarray, shape (..., E, 2)
        Exact (no linearization): the relative position ``r (cos b, sin b)`` plus the
        shift, back to range and bearing.
    """
    rel = z_hat[:, 0:1] * np.column_stack([np.cos(z_hat[:, 1]), np.sin(z_hat[:, 1])])
    q = rel + shift_body
    return np.stack([np.hypot(q[..., 0], q[..., 1]), np.arctan2(q[..., 1], q[..., 0])], -1)


class CompromisedRobot(Strategy):
    """Compromised robots that broadcast false estimates of themselves.

    Robots ``COMPROMISED_ORDER[:robots]`` (in every team) keep localizing honestly and
    their sensors, like every other sensor, stay honest; what they *send* is false. To each
    neighbour i the estimate is moved by the largest shift along world ``+x`` (``reach`` m
    at most per step) that i's detector accepts in its current state (gate and sequence
    tests: the acceptance oracle, :func:`largest_accepted_along`; estimate messages are
    per link, so each neighbour gets its own lie). The shift is taken on top of the honest
    estimate, so it compounds: a victim that follows the lie is next asked to accept a
    further shift from where it now is, and the robots it is fused with follow it. ``+x``
    is a gauge direction: a common translation that relative measurements between the
    other robots cannot see. With ``claimed_cov < 1`` the covariance sent is scaled down
    too (the victims give the false estimate more weight; they cannot check it).

    Against the witness stage the lies are then scaled to keep every honest receiver's
    statistic on the liar under its threshold
    (:func:`~resloc.world.attackers.witness.within_witness`): ``budget`` says how
    (``"spared"``, the default: the links whose notes nobody reads or the statistic can drop
    keep their whole lie, the rest share one factor; ``"common"``: one factor on every lie),
    ``give_up`` how many receivers per liar it lets convict it. Against a start-up floor
    (:mod:`resloc.cl.detection_startup`) ``harder`` lets a liar spend that budget: in a
    round where one of its victims' covariances is raised by the floor (by at least
    ``harder``), its lies are the largest the victims' detectors accept (:meth:`spends`).
    Against the lock-out floor (:mod:`resloc.cl.detection_lockout`) ``under`` keeps each
    victim under it: a victim whose discarded share has reached ``under`` is sent the
    honest estimate until its share falls back (:meth:`spared_victims`).

    The victim's innovation is computed exactly for the false position (the relative
    position ``r (cos b, sin b)`` plus the shift in the victim's frame, back to range and
    bearing) and injected through the link batch's ``tamper`` hook, which is where the
    victim's own prediction and innovation covariance are available to the oracle; the
    gain's linearization point stays at the honest estimate (a second-order difference).
    This is the threat the paper's sensing model leaves out: the lie arrives through the
    radio, outside every sensing danger zone.
    """

    name: ClassVar[str] = "compromised"
    template: ClassVar[str] = (
        "{robots:g} compromised robot(s) broadcast false estimates of themselves: to each "
        "neighbour the largest shift along world +x (at most {reach:g} m a step, "
        "compounding) its detector accepts, claimed covariance x{claimed_cov:g}; every "
        "sensor honest (against the witness stage: budget {budget}, giving up {give_up:g} "
        "receiver(s)); their own estimates {own}"
    )
    #: ``shield``: whether the liars' notes shield their honest victims (the response to the
    #: outvoted stage, :mod:`resloc.world.attackers.outvoted`): ``"auto"`` against that
    #: stage only, ``"on"``, ``"off"`` (neither is stronger on every seed: the worst case
    #: is taken over both). ``quiet``: the liars send their honest estimates for the first
    #: this many steps (the answer to a start-up defence, :mod:`resloc.cl.detection_startup`:
    #: lie only once it has ended). ``harder``: while the start-up stage raises the
    #: covariance of one of a liar's victims of the round by a factor of at least this
    #: (and above 1; 0: never), that liar's lies of the round are the largest the victims'
    #: detectors accept, not cut by the witness budget (:meth:`spends`). ``under``: no
    #: lie to a victim whose lock-out share (:mod:`resloc.cl.detection_lockout`) has
    #: reached this (0: off; the answer to that stage: keep every victim's share under
    #: its threshold, so that its floor never rises). ``own``: what the liars do with their
    #: own estimates (:data:`OWN_ESTIMATES`).
    defaults: ClassVar[dict] = {
        "robots": 1,
        "reach": 2.0,
        "claimed_cov": 1.0,
        "budget": "spared",
        "give_up": 0,
        "shield": "auto",
        "quiet": 0,
        "harder": 0.0,
        "under": 0.0,
        "own": "localized",
    }
    grid: ClassVar[tuple] = (
        {"robots": 1},
        {"robots": 1, "claimed_cov": 0.01},
        {"robots": 3, "claimed_cov": 0.01},
    )

    def __init__(self, **params) -> None:
        super().__init__(**params)
        if str(self.shield) not in SHIELDS:
            raise ValueError(
                f"attacker 'compromised', parameter shield: {self.shield!r} is not one of "
                f"{', '.join(SHIELDS)}"
            )
        if self.budget not in WITNESS_BUDGETS:
            raise ValueError(
                f"attacker 'compromised', parameter budget: {self.budget!r} is not one of "
                f"{', '.join(WITNESS_BUDGETS)}"
            )
        if self.own not in OWN_ESTIMATES:
            raise ValueError(
                f"attacker 'compromised', parameter own: {self.own!r} is not one of "
                f"{', '.join(OWN_ESTIMATES)}"
            )
        if not 0.0 <= self.under <= 1.0:
            raise ValueError(
                f"attacker 'compromised', parameter under: {self.under:g} is not a share "
                "between 0 (off) and 1"
            )
        if self.harder != 0.0 and not self.harder >= 1.0:
            raise ValueError(
                f"attacker 'compromised', parameter harder: {self.harder:g} is neither 0 "
                "(off) nor a start-up factor of at least 1"
            )

    def spared_victims(self, victims: np.ndarray, shares: np.ndarray) -> np.ndarray:
        """Which of the round's rows (``victims``: batch ids, shape (n,)) get the honest
        estimate: those whose victim's lock-out share (``shares (B,)``, the stage's
        :func:`~resloc.cl.detection_lockout.discarded_shares`) has reached ``under``.

        Why: the stage raises a victim's covariance only once its share passes its
        threshold; a liar that stops pulling a victim as its share nears the threshold
        keeps it in the partial lock-out the stage does not see (its honest neighbours,
        now discarded less as it drifts back, bring the share down, and the lies resume).
        """
        if self.under <= 0.0:
            return np.zeros(len(victims), bool)
        return shares[victims] >= self.under

    def spends(self, victims: np.ndarray, liars: np.ndarray, factors: np.ndarray) -> np.ndarray:
        """Which of the round's rows (``victims``, ``liars``: batch ids, shape (n,)) are sent
        whole, past the witness budget: those of a liar one of whose victims of the round
        has its covariance raised by the start-up stage (``factors (B,)``, the stage's
        :func:`~resloc.cl.detection_startup.applied_startup_factors` this step) by at least
        ``harder`` (and by more than 1).

        Why the liar and not the link: one lie past the budget makes its notes convict the
        liar at its receivers whatever its other links carry, so the budget of the liar's
        other lies of the round buys nothing. Why it can pay: the witness budget binds most
        while the floors are high (the victims' gates are wide, their gains large; it cut
        10-23% of the lies in steps 3-10 on a held-out seed, nothing after, ``docs/attack/
        startup.md`` section 6), and a pull taken then lasts; a convicted liar is discarded
        by its receivers until its statistic falls back under the threshold (a few steps to
        tens), later lies it gives up.
        """
        if self.harder <= 0.0:
            return np.zeros(len(victims), bool)
        raised = factors[victims]
        floored = (raised > 1.0) & (raised >= self.harder)
        ids, slot = np.unique(liars, return_inverse=True)
        return np.bincount(slot, floored, len(ids))[slot] > 0

    def targets(self, robots: int) -> np.ndarray:
        """The compromised robots' ids in a team of ``robots``."""
        ids = [t for t in COMPROMISED_ORDER if t < robots][: int(self.robots)]
        return np.array(ids, dtype=int)

    def owned(self, robots: int) -> np.ndarray:
        return self.targets(robots)

    def mark(self, sdz_attacked, step):
        return np.isin(step.j % step.robots, self.targets(step.robots))

    def attack(self, links, step, params, memory):
        from_liar = np.isin(links.j % step.robots, self.targets(step.robots))
        if memory is not None:  # the liars run their own software: no floor on themselves
            memory.exempt = np.isin(
                np.arange(memory.n_nodes) % step.robots, self.targets(step.robots)
            )
        if self.own == "dead_reckoning":  # a liar's own readings: none fused (no estimate)
            to_liar = np.isin(links.i % step.robots, self.targets(step.robots))
            links = dataclasses.replace(links, channel_ok=links.channel_ok & ~to_liar)
        if not from_liar.any() or step.k < int(self.quiet):
            return dataclasses.replace(links, tamper=None)
        is_liar = np.isin(np.arange(len(step.pose)) % step.robots, self.targets(step.robots))
        P_nb = links.P_nb
        if self.claimed_cov != 1.0:
            P_nb = P_nb.copy()
            P_nb[from_liar] *= float(self.claimed_cov)
        # The shift in each victim's frame (the attacker knows the victims' headings).
        heading = step.pose[links.i, 2]
        cos, sin = np.cos(heading), np.sin(heading)
        shift_body = float(self.reach) * np.column_stack([cos, -sin])  # R(-theta) (1, 0)
        z_all = links.z
        # The lie is in the broadcast estimate; the victim's reading is honest. The hook
        # injects it as the equivalent reading, so with the reciprocal range check on, the
        # liar also reports its own reading of each victim moved by the same range (it is
        # compromised: it sends what it likes; ``tamper.reported``, applied to the partner
        # readings only: its own update fuses its honest reading), which leaves the pair's
        # difference honest, as it physically is; the oracle judges with every other stage.
        reports_own = bool(params.reciprocal)
        judged = dataclasses.replace(params, reciprocal=False) if reports_own else params
        injected = np.zeros(len(z_all))  # the range each victim's row carries of the lie

        def reported(z_reciprocal: np.ndarray) -> np.ndarray:
            """The partner readings as the robots receive them: with the reciprocal check on,
            the liar reports its reading of each victim moved by the range injected on that
            victim's row; and the liar itself receives each victim's physical (honest)
            reading of it, range and bearing (the lie is in its broadcast, not in the
            victim's sensor: without this the lie, carried as the victim's reading, would be
            fed back into the liar's own estimate wherever zone trust makes it fuse its
            partners' readings of it)."""
            out = np.array(z_reciprocal, float)
            reverse = reciprocal_rows(links.i, links.j)
            if reports_own:
                rows = np.flatnonzero(injected)
                out[rows, 0] += injected[rows]
            rows = np.flatnonzero(from_liar & (reverse >= 0))
            out[reverse[rows]] = z_all[rows]
            return out

        def tamper(rows: np.ndarray, z_hat: np.ndarray, S: np.ndarray) -> np.ndarray:
            out = z_all[rows].copy()
            hit = np.flatnonzero(from_liar[rows])
            if not hit.size:
                return out
            r = rows[hit]
            zh, z = z_hat[hit], out[hit]

            def path(frac: np.ndarray) -> np.ndarray:
                lied = shifted_prediction(zh, frac[..., None] * shift_body[r][None])
                cand = z[None] - (lied - zh[None])  # innovation z - h(x_i, x_j + shift)
                cand[..., 1] = wrap_angle(cand[..., 1])
                return cand

            # the claims as the victims fuse them (raised during their start-up floor)
            fused_claims = floored_claims(params, memory, links.i, P_nb)
            context = fix_context(links, r, judged, fused_claims, memory)
            a = largest_accepted_along(
                path, zh, S[hit], links.i[r], links.j[r], judged, memory, context=context
            )
            if params.witness and memory is not None and links.neighbours is not None:
                # The notes on each liar must keep it under every honest receiver's
                # witness test once they arrive (its fellows' notes lying for it), unless
                # it spends them on floored victims (``harder``).
                source = links.neighbours
                whole = a
                a = within_witness(
                    a,
                    path,
                    r,
                    z_all if len(rows) == len(z_all) else _with_rows(z_all, rows, out),
                    source.x[links.i],
                    widened(source.P, memory, params)[links.i],
                    links.x_nb,
                    fused_claims,
                    links.i,
                    links.j,
                    links.channel_ok,
                    is_liar,
                    params,
                    memory,
                    budget=str(self.budget),
                    give_up=int(self.give_up),
                )
                if self.harder > 0.0 and params.startup_steps > 0:
                    factors = applied_startup_factors(memory, len(source.x))
                    a = np.where(self.spends(links.i[r], links.j[r], factors), whole, a)
            if self.under > 0.0 and params.lockout_share > 0.0 and memory is not None:
                shares = discarded_shares(memory, len(step.pose))
                a = np.where(self.spared_victims(links.i[r], shares), 0.0, a)
            out[hit] = path(a[None])[0]
            injected[r] = out[hit, 0] - z[:, 0]
            return out

        if reports_own or params.zone_trust:  # what the partners' readings carry
            tamper.reported = reported
        if params.witness:  # the liars' own notes on their neighbours lie too
            tamper.notes = lambda notes: lying_notes(notes, is_liar, params)
        if params.witness and SHIELDS[str(self.shield)](params):  # and shield their victims
            tamper.notes = lambda notes: shielding_notes(notes, is_liar, params)
        return dataclasses.replace(links, P_nb=P_nb, tamper=tamper)


def _with_rows(z_all: np.ndarray, rows: np.ndarray, z_rows: np.ndarray) -> np.ndarray:
    """The step's readings with ``rows`` as sent (the other rows honest)."""
    z = np.array(z_all, float)
    z[rows] = z_rows
    return z


class Replay(SensingLie):
    """Replay: each SDZ link's honest measurement from ``delay`` steps earlier.

    Detector-aware (``raw = 0``): the replayed value is sent as far as the victim's
    detector accepts it (the largest accepted step from the live measurement toward the
    recorded one; all of it when accepted, which is the common case). ``raw = 1`` is the
    world's plain replay (``attack.kind = "replay"``): the recording as is, rejected or not.
    Links without a recording ``delay`` steps back are left honest.
    """

    name: ClassVar[str] = "replay"
    template: ClassVar[str] = (
        "each SDZ link's honest measurement from {delay:g} steps earlier, as far toward it "
        "as the victim's detector accepts (raw = {raw:g}: the recording as is)"
    )
    defaults: ClassVar[dict] = {"delay": 30, "raw": 0}
    grid: ClassVar[tuple] = ({"delay": 5}, {"delay": 30}, {"delay": 150}, {"raw": 1})

    def __init__(self, **params) -> None:
        super().__init__(**params)
        self._buffer: ReplayBuffer | None = None
        self._recorded: tuple[np.ndarray, np.ndarray] | None = None
        self._step = 0

    @property
    def overrides(self) -> dict:
        if self.raw:
            return {"attack.kind": "replay", "attack.replay_delay": int(self.delay)}
        return {"attack.kind": "stealthy"}

    def mark(self, sdz_attacked, step):
        if self.raw:
            return sdz_attacked
        if self._buffer is None or step.k <= self._step:  # a new run
            self._buffer = ReplayBuffer(int(self.delay), len(step.pose))
        self._step = step.k
        self._recorded = self._buffer.replayed(step.i, step.j)
        self._buffer.record(step.i, step.j, step.z)
        return sdz_attacked & self._recorded[0]

    def lie(self, rows, z, z_hat, step):
        return measurement_difference(self._recorded[1][rows], z)

    def attack(self, links, step, params, memory):
        if self.raw:
            return dataclasses.replace(links, tamper=None)
        return super().attack(links, step, params, memory)
