"""The pull protocol of ``estimator.neighbour_estimate = "cached"``: estimates only on trigger.

With cached neighbour estimates, robot i decides the detector and the event trigger of link
``(i, j)`` on the last estimate of j it actually received (before the first one, the link
counts as triggered). It needs j's *current* estimate only when the trigger fires, so it asks
for it: a small REQUEST on the link, and j answers with a REPLY carrying its predicted
estimate of the step. Nothing else crosses the wire for the link.

:func:`pull_correction` is robot i's correction as a generator over request rounds. It runs
the node's own ``correct`` (the library's detector, trigger and fusion; nothing here is an
equation) on one link at a time in ascending ``j`` (the sequential update: a link's decision
depends on the fusions before it), or on all links at once with ``update_mode = "summed"``
(every decision on the predicted estimate). Per group of links:

1. the links without a cached estimate are requested in the first round (their detector
   needs j's estimate; the simulator counts them as triggered);
2. the others are decided locally: a speculative ``correct`` with the cached estimates and
   ``channel_ok = False``. Untriggered links keep that result (with
   ``update_without_transmission`` it fused the cache: no message). If a link triggered, the
   node is rolled back to before the group and its neighbour is requested;
3. ``yield`` the ids to request; receive ``{j: (x, P)}`` of the replies that arrived;
4. ``correct`` the group with the replies (``channel_ok = True``) and, for links whose reply
   did not arrive, the cached estimate with ``channel_ok = False`` (triggered, not
   delivered: the simulator's jammed transmission); a link never heard from is skipped.

The generator returns a :class:`PullOutcome`. A run of it equals the simulator's cached
correction when a reply arrives iff the simulator's ``channel_ok`` of the link (the radio's
rule; tested to 1e-9).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np

from resloc.cl.links import LinkOutcome
from resloc.cl.node import RobotNode
from resloc.cl.params import CLParams, UpdateMode

__all__ = ["PullOutcome", "pull_correction"]

#: ``{neighbour id: (x (3,), P (3, 3))}`` of the replies that arrived in a round.
Replies = dict[int, tuple[np.ndarray, np.ndarray]]


@dataclass
class PullOutcome:
    """Per-link results of one robot's pulled correction, in the order of its links.

    Attributes
    ----------
    outcomes : list of (rows, LinkOutcome)
        Each ``correct`` that counts, with the link rows it ran on.
    requested : ndarray of bool, shape (E,)
        Links whose neighbour was asked for its estimate.
    answered : ndarray of bool, shape (E,)
    rounds : int
        Request rounds this robot needed.
    not_asked : int
        Links that fired after the single realtime round (``single_round``).
    """

    outcomes: list = field(default_factory=list)
    requested: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    answered: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rounds: int = 0
    not_asked: int = 0


def _checkpoint(node: RobotNode) -> tuple:
    return node.x.copy(), node.P.copy(), copy.deepcopy(node.memory)


def _rollback(node: RobotNode, saved: tuple) -> None:
    node.x, node.P, node.memory = saved


def pull_correction(
    node: RobotNode,
    j: np.ndarray,
    z: np.ndarray,
    risks: tuple[float, float, float],
    groups: list[tuple[np.ndarray, CLParams]],
    single_round: bool = False,
) -> Generator[list[int], Replies, PullOutcome]:
    """Robot ``node``'s correction with pulled estimates, one request round per ``yield``.

    Parameters
    ----------
    node : RobotNode
        Predicted; its ``memory`` holds the cached estimates (``neighbour_estimate =
        "cached"``).
    j : ndarray of int, shape (E,)
        This step's observed neighbours.
    z : ndarray, shape (E, 2)
    risks : (risk_s, risk_c, lambda2)
    groups : list of (rows, CLParams)
        The links grouped by the parameters they are fused with (``TeamSetup.link_params``).
    single_round : bool
        Realtime: one request round per step. The links to request are decided up front on
        the predicted estimate (the never-heard ones and those whose trigger fires before any
        fusion); a link that fires only after earlier fusions is not requested
        (``not_asked``: triggered, not delivered), a requested one that no longer fires
        leaves its reply unused. Sequential round trips would not fit in a step.

    Yields
    ------
    list of int
        Neighbour ids to request this round (non-empty).

    Receives
    --------
    Replies
        The replies that arrived (a lost or late one is simply absent).
    """
    j = np.asarray(j, dtype=np.int64).reshape(-1)
    E = len(j)
    result = PullOutcome(requested=np.zeros(E, bool), answered=np.zeros(E, bool))
    replies: Replies = {}
    asked: set[int] = set()
    zeros = np.zeros(E, dtype=np.int64)
    known, _ = node.memory.lookup(zeros, j)
    # Links never heard from: their detector needs j's estimate, so ask at once.
    first = sorted({int(v) for v in j[~known]})
    base = node.params
    if single_round and known.any():
        saved = _checkpoint(node)
        for rows, params in groups:
            rows = rows[known[rows]]
            if len(rows):
                node.params = params
                _, pos = node.memory.lookup(zeros[rows], j[rows])
                run = _corrector(node, j, z, risks)
                out = run(rows, node.memory.x[pos], node.memory.P[pos], False)
                first = sorted(set(first) | {int(v) for v in j[rows[out.triggered]]})
        _rollback(node, saved)
    if single_round:
        return (yield from _one_round(node, j, z, risks, groups, first, result))
    for rows, params in groups:
        rows = rows[np.argsort(j[rows], kind="stable")]
        summed = params.update_mode is UpdateMode.SUMMED
        for g in [rows] if summed else [rows[k : k + 1] for k in range(len(rows))]:
            node.params = params
            run: Callable = _corrector(node, j, z, risks)
            have, pos = node.memory.lookup(zeros[g], j[g])
            need = {int(v) for v in j[g][~have]}
            local = g[have]
            if len(local):
                saved = _checkpoint(node)
                out = run(local, node.memory.x[pos[have]], node.memory.P[pos[have]], False)
                if out.triggered.any():
                    need |= {int(v) for v in j[local[out.triggered]]}
                    _rollback(node, saved)
                elif not need:
                    result.outcomes.append((local, out))
                    continue
                else:
                    _rollback(node, saved)
            new = sorted((need | set(first)) - asked)
            first = []
            if new:
                asked |= set(new)
                result.requested[np.isin(j, new)] = True
                result.rounds += 1
                got = yield new
                replies.update({int(k): v for k, v in (got or {}).items() if int(k) in asked})
            got_reply = np.array([int(v) in replies for v in j[g]], dtype=bool)
            result.answered[g[got_reply]] = True
            keep = have | got_reply  # a link never heard from cannot be evaluated
            if keep.any():
                gk = g[keep]
                x_nb, P_nb = _neighbour_estimates(node, j[gk], replies)
                result.outcomes.append((gk, run(gk, x_nb, P_nb, got_reply[keep])))
    node.params = base
    return result


def _neighbour_estimates(node: RobotNode, j: np.ndarray, replies: Replies):
    """``x_nb: (E, 3)``, ``P_nb: (E, 3, 3)`` for links to ``j``: the reply where one
    arrived, else the cached estimate (what ``correct`` decides on; not fused)."""
    x_nb = np.zeros((len(j), 3))
    P_nb = np.zeros((len(j), 3, 3))
    have, pos = node.memory.lookup(np.zeros(len(j), np.int64), j)
    for e, nb in enumerate(j):
        if int(nb) in replies:
            x_nb[e], P_nb[e] = replies[int(nb)]
        elif have[e]:
            x_nb[e], P_nb[e] = node.memory.x[pos[e]], node.memory.P[pos[e]]
    return x_nb, P_nb


def _one_round(
    node: RobotNode,
    j: np.ndarray,
    z: np.ndarray,
    risks: tuple,
    groups: list,
    first: list[int],
    result: PullOutcome,
) -> Generator[list[int], Replies, PullOutcome]:
    """Realtime: ask ``first`` once, then one ``correct`` per parameter group with what
    arrived (links decided in sequence on the cache; a reply is fused where it fired)."""
    replies: Replies = {}
    if first:
        result.requested[np.isin(j, first)] = True
        result.rounds = 1
        got = yield first
        replies = {int(k): v for k, v in (got or {}).items() if int(k) in first}
    zeros = np.zeros(len(j), dtype=np.int64)
    base = node.params
    for rows, params in groups:
        rows = rows[np.argsort(j[rows], kind="stable")]
        node.params = params
        got_reply = np.array([int(v) in replies for v in j[rows]], dtype=bool)
        result.answered[rows[got_reply]] = True
        have, _ = node.memory.lookup(zeros[rows], j[rows])
        keep = have | got_reply  # a link never heard from cannot be evaluated
        if keep.any():
            gk = rows[keep]
            x_nb, P_nb = _neighbour_estimates(node, j[gk], replies)
            out = _corrector(node, j, z, risks)(gk, x_nb, P_nb, got_reply[keep])
            result.outcomes.append((gk, out))
            result.not_asked += int((out.triggered & ~np.isin(j[gk], first)).sum())
    node.params = base
    return result


def _corrector(node: RobotNode, j: np.ndarray, z: np.ndarray, risks: tuple) -> Callable:
    risk_s, risk_c, lambda2 = risks

    def run(rows: np.ndarray, x_nb: np.ndarray, P_nb: np.ndarray, ok) -> LinkOutcome:
        channel = np.broadcast_to(np.asarray(ok, dtype=bool), (len(rows),)).copy()
        return node.correct(j[rows], z[rows], x_nb, P_nb, channel, risk_s, risk_c, lambda2)

    return run
