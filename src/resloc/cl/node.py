"""A stateful robot node: one robot's estimator process on top of the functional CL step.

A :class:`RobotNode` holds what one robot knows (its estimate ``x: (1, 3)``, ``P: (1, 3,
3)`` and its per-link memory) and runs :func:`~resloc.cl.step.predict` and
:func:`~resloc.cl.step.correct` with batch size 1: the very functions the batched simulator
runs over every robot of every trial at once. A team of nodes fed the same data gives the
batched engine's estimates (tested to 1e-9).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from resloc.cl.detection_witness_frames import (
    PENDING,
    PENDING_WIDTH,
    delivered_store,
    put_store,
)
from resloc.cl.factorized import FactorizedCovariance
from resloc.cl.fusion_methods import FusionStrategy, fusion_strategy
from resloc.cl.gauge import GaugeCovariance
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams
from resloc.cl.step import correct, predict
from resloc.errors import ConfigError
from resloc.filters.base import GaussianFilter

__all__ = ["RobotNode"]


class RobotNode:
    """One robot's cooperative-localization process (Algorithm 1, batch size 1).

    Parameters
    ----------
    robot_id : int
        This robot's id (as its neighbours know it).
    filt : GaussianFilter
        Its filter strategy (``make_filter("ckf")`` etc.).
    params : CLParams
        Its estimator parameters (scalars; a per-robot array must have shape (1,)).
    x0 : array-like, shape (3,)
        Initial estimate ``[x, y, theta]``.
    P0 : array-like, shape (3, 3)
        Initial covariance.
    n_ids : int
        Size of the id space of neighbours (ids are ``0 .. n_ids - 1``); sizes the link
        memory's keys.
    team_size : int, optional
        Needed with ``params.fusion = "gauge"``: the team size N (the gauge covariance is
        ``N`` times a consensus average; :mod:`resloc.cl.gauge`).

    Raises
    ------
    ConfigError
        When the fusion method does not run in one robot's process (the reason is the
        strategy's :attr:`~resloc.cl.fusion_methods.FusionStrategy.node_refusal`).

    Attributes
    ----------
    x : ndarray, shape (1, 3)
    P : ndarray, shape (1, 3, 3)
    memory : LinkMemory
        What this robot remembers per neighbour (used by ``last_sent`` / ``cached``).

    Gauge fusion (``params.fusion = "gauge"``) adds two exchanges per step after
    :meth:`correct`: the acknowledgements (:meth:`gauge_acks` to send, :meth:`gauge_close`
    with those received) and consensus rounds (:meth:`gauge_message`, :meth:`gauge_mix`);
    :attr:`covariance` is then the consistent covariance ``P + J G J^T``.

    Split covariance intersection (``params.fusion = "split_ci"``): a transmission also
    carries :attr:`independent` (given to the receiver's :meth:`correct` as ``P_nb_ind``),
    and after :meth:`correct` each neighbour in :meth:`delivery_acks` is told that its
    estimate was fused (:meth:`delivery_close` with the number of such acknowledgements).

    Factorized cross-covariances (``params.fusion = "factorized"``, needs ``team_size``;
    teammate ids modulo the team size index the factors): a transmission to neighbour i
    also carries :meth:`factor_for` ``(i)`` (given to i's :meth:`correct` as ``factor_nb``);
    after :meth:`correct`, the partners of the step are the robots in
    :meth:`delivery_acks` and those whose acknowledgement said they fused this robot's
    estimate; each sends this robot its :meth:`factor_message` for it, and
    :meth:`factor_close` ends the step with them.
    """

    def __init__(
        self,
        robot_id: int,
        filt: GaussianFilter,
        params: CLParams,
        x0: np.ndarray,
        P0: np.ndarray,
        n_ids: int = 1 << 20,
        team_size: int | None = None,
    ) -> None:
        self.robot_id = int(robot_id)
        self.filt = filt
        self.params = params
        self.fusion: FusionStrategy = fusion_strategy(params.fusion)
        if self.fusion.node_refusal is not None:
            raise ConfigError(
                f"fusion {params.fusion.value!r} does not run in a robot process: "
                f"{self.fusion.node_refusal}"
            )
        self.x = np.asarray(x0, dtype=float).reshape(1, 3).copy()
        self.P = np.asarray(P0, dtype=float).reshape(1, 3, 3).copy()
        self.memory = LinkMemory(n_ids)
        self.fusion.init(self.memory, self.x, self.P, team_size, local=True)
        self._delivered_from = np.empty(0, dtype=np.int64)
        # Witness notes (params.witness): the receivers' statistic in team ids (this robot's
        # row only) and the notes of this robot's last correction, not yet delivered.
        self._witness = LinkMemory(n_ids)
        self._outvoted = LinkMemory(n_ids)  # its PENDING: the notes on this robot (o, 0)
        self._own_notes = (np.empty(0, np.int64), np.empty((0, PENDING_WIDTH - 1)))

    @property
    def gauge(self) -> GaugeCovariance | None:
        """The gauge bookkeeping (``fusion = "gauge"``), else None."""
        return self.memory.joint if isinstance(self.memory.joint, GaugeCovariance) else None

    @property
    def covariance(self) -> np.ndarray:
        """This robot's consistent covariance, shape (3, 3): ``P`` (naive fusion's) plus the
        team's gauge part with gauge fusion."""
        return self.fusion.reported(self.memory, self.x, self.P)[0].copy()

    def gauge_acks(self) -> list[tuple[int, np.ndarray]]:
        """After :meth:`correct`: ``(j, ack)`` for each neighbour j whose estimate this robot
        fused this step; deliver ``ack`` (3x3) to robot j's :meth:`gauge_close`."""
        j, ack = self.gauge.acks()
        return [(int(a), b) for a, b in zip(j, ack, strict=True)]

    def gauge_close(self, received: list[np.ndarray]) -> None:
        """Close the step's gauge bookkeeping with the acknowledgements received."""
        self.gauge.close(np.asarray(received, dtype=float).reshape(-1, 3, 3))

    def gauge_message(self) -> np.ndarray:
        """One consensus exchange's payload, shape (2, 3, 3)."""
        return self.gauge.message()[0]

    def gauge_mix(self, received: list[np.ndarray], degrees: list[int]) -> None:
        """One consensus exchange with this step's communication neighbours: their
        :meth:`gauge_message` and their numbers of neighbours."""
        self.gauge.mix_local(
            len(received),
            np.asarray(received, dtype=float).reshape(-1, 2, 3, 3),
            np.asarray(degrees, dtype=float),
        )

    @property
    def independent(self) -> np.ndarray | None:
        """The independent part of ``P``, shape (3, 3), with ``split_ci`` fusion (what a
        transmission carries besides :attr:`estimate`), else None."""
        ind = self.memory.independent
        return None if ind is None else ind[0].copy()

    def delivery_acks(self) -> list[int]:
        """After :meth:`correct` with ``split_ci``: the neighbours whose estimates this robot
        fused; tell each (its :meth:`delivery_close`)."""
        return [int(j) for j in self._delivered_from]

    def factor_for(self, j: int) -> np.ndarray:
        """With ``factorized`` fusion: the factor this robot keeps for neighbour ``j``, shape
        (3, 3), which its transmission to j carries."""
        return self._factors().factor_for(j)

    def factor_message(self, partner: int) -> np.ndarray:
        """With ``factorized`` fusion, after :meth:`correct`: this robot's message to a partner
        of the step, shape (4, 3, 3)."""
        return self._factors().pair_message(partner)

    def factor_close(self, messages: dict[int, np.ndarray | None]) -> None:
        """With ``factorized`` fusion: end of the step with ``{partner id: its
        factor_message(this robot)}`` from every partner (a partner with a lower id than
        this robot's needs not send it: the lower id keeps the pair's cross-covariance, the
        higher the identity; give None)."""
        self._factors().close_pairs(self.robot_id, messages)

    def _factors(self) -> FactorizedCovariance:
        if not isinstance(self.memory.joint, FactorizedCovariance):
            raise ConfigError(f"fusion {self.params.fusion.value!r} keeps no factors")
        return self.memory.joint

    def delivery_close(self, received: int) -> None:
        """With ``split_ci``: ``received`` neighbours fused this robot's estimate this step,
        so its independent part is now held by them too and becomes dependent."""
        if received and self.memory.independent is not None:
            self.memory.independent[:] = 0.0

    def witness_notes(self) -> tuple[np.ndarray, np.ndarray]:
        """With ``params.witness``: the notes of this robot's last :meth:`correct` (none if
        it had no link), which its next transmission carries: the observed robots' ids
        ``(K,)`` and per note ``u`` (2), ``Q`` (4), ``P_pos`` (4) as rows ``(K, 10)`` (the
        layout of :data:`~resloc.cl.detection_witness_frames.PENDING`)."""
        j, rows = self._own_notes
        return j.copy(), rows.copy()

    def receive_witness(self, senders: np.ndarray, notes: list[tuple[np.ndarray, np.ndarray]]):
        """With ``params.witness``, every step before :meth:`correct` (whether or not it
        runs): the notes of the step before that arrived with this step's frames, from the
        neighbours ``senders (S,)`` this robot measured this step and heard (``notes[s]``:
        sender s's :meth:`witness_notes`). Updates this robot's statistic on every robot
        the notes are on, as the simulator's receiver (its own notes included; a robot it
        received nothing on decays by ``k``); the next :meth:`correct` judges with it. With
        ``params.outvoted`` the notes on this robot among them are its correction's too."""
        n = self._witness.n_nodes
        me = self.robot_id
        obs = [np.full(len(self._own_notes[0]), me, np.int64)]
        on, rows = [self._own_notes[0]], [self._own_notes[1]]
        for s, (j, r) in zip(senders, notes, strict=True):
            obs.append(np.full(len(j), int(s), np.int64))
            on.append(np.asarray(j, np.int64))
            rows.append(np.asarray(r, float).reshape(-1, PENDING_WIDTH - 1))
        obs, on = np.concatenate(obs), np.concatenate(on)
        rows = np.column_stack([np.concatenate(rows), np.ones(len(obs))])
        pending = LinkStatistic(n, width=PENDING_WIDTH)
        pending.set(obs, on, rows)
        if self.params.outvoted:  # the notes on this robot, as its correction's row 0
            on_me = on == me
            notes_on_me = LinkStatistic(self.memory.n_nodes, width=PENDING_WIDTH)
            notes_on_me.set(obs[on_me], np.zeros(int(on_me.sum()), np.int64), rows[on_me])
            stored = self._outvoted.stage_statistic(PENDING, width=PENDING_WIDTH)
            stored.keys, stored.values = notes_on_me.keys, notes_on_me.values
            self.memory.outvoted_view = self._outvoted
        stored = self._witness.stage_statistic(PENDING, width=PENDING_WIDTH)
        stored.keys, stored.values = pending.keys, pending.values
        senders = np.asarray(senders, np.int64)
        heard = np.ones(len(senders), bool)
        store = delivered_store(
            self.params, self._witness, np.full(len(senders), me), senders, heard
        )
        # this robot's row (the others' notes also count as their own receivers' there)
        row = store.keys // n == me
        kept = LinkStatistic(n)
        kept.keys, kept.values = store.keys[row], store.values[row]
        put_store(self._witness, kept)
        # the correction's receiver is its batch row 0
        mine = LinkStatistic(self.memory.n_nodes)
        mine.set(np.zeros(len(kept.keys), np.int64), kept.keys % n, kept.values)
        self.memory.delivered_witness = mine
        self._own_notes = (np.empty(0, np.int64), np.empty((0, PENDING_WIDTH - 1)))

    @property
    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x, P)`` of shapes (3,), (3, 3): what a transmission of this robot carries."""
        return self.x[0].copy(), self.P[0].copy()

    def predict(self, u: np.ndarray, dt: float) -> None:
        """Time update from measured odometry ``u = (v, omega)``, shape (2,)."""
        u = np.asarray(u, dtype=float).reshape(1, 2)
        x_before = self.x
        self.x, self.P = predict(self.filt, self.x, self.P, u, dt, self.params)
        self.P = self.fusion.predict(self.memory, x_before, u, dt, self.params, self.P)

    def correct(
        self,
        j: np.ndarray,
        z: np.ndarray,
        x_nb: np.ndarray,
        P_nb: np.ndarray,
        channel_ok: np.ndarray,
        risk_s: float,
        risk_c: float,
        lambda2: float,
        P_nb_ind: np.ndarray | None = None,
        factor_nb: np.ndarray | None = None,
        z_reciprocal: np.ndarray | None = None,
    ) -> LinkOutcome:
        """Correction from this step's relative measurements of neighbours ``j``.

        Links are fused in ascending ``j`` (the sequential order of the batched step);
        the outcome is returned in the order given.

        Parameters
        ----------
        j : ndarray of int, shape (E,)
            Ids of the observed neighbours.
        z : ndarray, shape (E, 2)
            Measured ``[range, bearing]``.
        x_nb : ndarray, shape (E, 3)
            Each neighbour's current predicted estimate (what its transmission carries).
        P_nb : ndarray, shape (E, 3, 3)
        channel_ok : ndarray of bool, shape (E,)
            Whether a transmission from each neighbour would get through.
        risk_s, risk_c : float
            ``Ds(i)``, ``Dc(i)`` of this robot.
        lambda2 : float
            Algebraic connectivity this robot sees.
        P_nb_ind : ndarray, shape (E, 3, 3), optional
            The neighbours' transmitted independent parts (``split_ci``: their
            :attr:`independent`).
        factor_nb : ndarray, shape (E, 3, 3), optional
            The factors the neighbours keep for this robot (``factorized``: their
            :meth:`factor_for` ``(robot_id)``).
        z_reciprocal : ndarray, shape (E, 2), optional
            Each neighbour's own reading of this robot this step (range, bearing; ``nan``:
            none), sent with its estimate: zone-aware trust (``params.zone_trust``) fuses
            it as a position fix while this robot is inside a mapped danger zone.

        Returns
        -------
        LinkOutcome
            Per-link decisions, in the order of ``j``.
        """
        j = np.asarray(j, dtype=np.int64).reshape(-1)
        if factor_nb is not None:
            self._factors().receive(j, np.asarray(factor_nb, dtype=float).reshape(-1, 3, 3))
        order = np.argsort(j, kind="stable")
        links = LinkBatch(
            i=np.zeros(len(j), dtype=np.int64),
            j=j[order],
            z=np.asarray(z, dtype=float).reshape(-1, 2)[order],
            x_nb=np.asarray(x_nb, dtype=float).reshape(-1, 3)[order],
            P_nb=np.asarray(P_nb, dtype=float).reshape(-1, 3, 3)[order],
            channel_ok=np.asarray(channel_ok, dtype=bool).reshape(-1)[order],
            risk_s=np.array([risk_s], dtype=float),
            risk_c=np.array([risk_c], dtype=float),
            lambda2=np.array([lambda2], dtype=float),
            P_nb_ind=None
            if P_nb_ind is None
            else np.asarray(P_nb_ind, dtype=float).reshape(-1, 3, 3)[order],
            z_reciprocal=np.full((len(j), 2), np.nan)
            if z_reciprocal is None
            else np.asarray(z_reciprocal, dtype=float).reshape(-1, 2)[order],
        )
        self.x, self.P, out = correct(self.filt, self.x, self.P, links, self.params, self.memory)
        self._delivered_from = links.j[out.delivered]
        if self.params.witness:  # the notes recorded at the step's end (batch row 0)
            pending = self.memory.stage_statistic(PENDING, width=PENDING_WIDTH)
            sent = pending.values[:, -1] > 0.0
            self._own_notes = (pending.keys[sent] % self.memory.n_nodes, pending.values[sent, :-1])
        if np.array_equal(order, np.arange(len(j))):
            return out
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        per_link = {
            f.name: getattr(out, f.name)[back]
            for f in dataclasses.fields(out)
            if isinstance(getattr(out, f.name), np.ndarray)
            and getattr(out, f.name).shape[:1] == (len(j),)
        }
        return dataclasses.replace(out, **per_link)
