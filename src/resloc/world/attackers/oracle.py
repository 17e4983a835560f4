"""The attacker's copy of the victim's detector: which falsified measurements it accepts.

Every attacker of the suite knows the defence it faces completely: the victim's parameters
(:class:`~resloc.cl.params.CLParams`), its predicted measurements and innovation
covariances, and the state of every sequence test (the victim's
:class:`~resloc.cl.memory.LinkMemory`). :func:`largest_accepted` runs the victim's own
detector (:func:`resloc.cl.detection.detect`, whatever stages the defence switches on,
including stages added later) on a throw-away copy of that state, so no attacker re-derives a
test and none is limited to a margin of a threshold: it uses the whole acceptance region.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from resloc.cl.detection import DETECTOR_STAGES, Evidence, active_stages, detect
from resloc.cl.detection_landmark import landmark_claims
from resloc.cl.detection_reciprocal import ReciprocalContext
from resloc.cl.detection_redundancy import FixContext
from resloc.cl.detection_redundancy_fixes import capped_claims
from resloc.cl.detector import innovation_norm
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.filters.update import innovation

__all__ = [
    "CONTEXT_STAGES",
    "ROW_WISE_STAGES",
    "StepContext",
    "accepted",
    "fix_context",
    "largest_accepted",
    "largest_accepted_along",
    "scratch_memory",
]

#: Grid points of each pass; three passes resolve the accepted fraction to ``1 / 32^3`` of
#: the lie (a lie of metres is placed to a tenth of a millimetre).
GRID = 33
PASSES = 3
#: Joint bisection steps of the rows a coupled stage rejects (resolution ``2^-6`` of the
#: row-wise bound).
BISECTIONS = 6
#: Stages whose verdict on a row depends only on that row and the state before the round
#: (the gate, the per-link CUSUMs, recovery's re-admission test, the witness verdict on the
#: neighbour, read from the state the notes of the steps before left): candidates may be
#: stacked. (What a lie adds to the witness test is judged by the compromised robots'
#: :func:`~resloc.world.attackers.witness.within_witness`.)
ROW_WISE_STAGES = frozenset({"gate", "cusum", "mean_cusum", "recovery", "witness"})
#: Stages whose verdict on a row also reads the step's other rows (through a
#: :class:`~resloc.cl.detection_redundancy.FixContext`, which judges each stacked candidate
#: set in its own copy of the victims' links: stackable, and exact for lies told together).
CONTEXT_STAGES = frozenset({"redundancy", "redundancy_sequence", "reciprocal"})


@dataclass
class StepContext:
    """The victims' other links this step, for every active stage that reads them: the
    redundancy stages' :class:`~resloc.cl.detection_redundancy.FixContext` and the
    reciprocal check's :class:`~resloc.cl.detection_reciprocal.ReciprocalContext` (either
    None when its stage is off)."""

    fix: FixContext | None = None
    reciprocal: ReciprocalContext | None = None

    def fields(self, candidates: np.ndarray) -> dict[str, np.ndarray]:
        """Evidence fields for the stacked ``candidates``, shape (G, n, 2)."""
        out: dict[str, np.ndarray] = {}
        for part in (self.fix, self.reciprocal):
            if part is not None:
                out.update(part.fields(candidates))
        return out


def fix_context(
    links: LinkBatch,
    rows: np.ndarray,
    params: CLParams,
    P_nb: np.ndarray | None = None,
    memory: LinkMemory | None = None,
    z: np.ndarray | None = None,
) -> StepContext | None:
    """What the attacker's copy of the detector needs of the step's other links to judge
    candidates on ``rows`` (indices into ``links``), or None when no active stage reads them.

    The victims' predicted estimates are read from the batch (``links.neighbours``: the
    simulator's links reference the batch's predicted arrays; the attacker knows them).
    ``P_nb``: the covariances the victims receive, when the attacker changes them;
    ``memory``: the victims' (the links a sequence test holds out enter no reference);
    ``z``: the step's readings as the attacker leaves them outside ``rows`` (default
    ``links.z``: what the reciprocal check compares a lone candidate with).
    """
    names = {s.name for s in active_stages(params)} & CONTEXT_STAGES
    if not names:
        return None
    if links.neighbours is None:
        raise ValueError(
            "the redundancy and reciprocal stages' oracle needs the victims' estimates: "
            "build the links with LinkBatch.from_predicted"
        )
    source = links.neighbours
    z = np.asarray(links.z if z is None else z, float)
    P_nb = links.P_nb if P_nb is None else P_nb
    if params.zone_landmarks:
        # The victim's step caps the claims (with the cap in fusion), then inflates those
        # of the neighbours inside the map, before every test.
        if params.redundancy_cap_fusion:
            P_nb = capped_claims(P_nb, np.asarray(links.i))
        P_nb = landmark_claims(params, links.x_nb, P_nb, np.asarray(links.i))
    x_obs = source.x[links.i]
    fix = None
    if names & {"redundancy", "redundancy_sequence"}:
        fix = FixContext(
            z,
            x_obs,
            source.P[links.i],
            links.x_nb,
            P_nb,
            np.asarray(links.i),
            params,
            np.asarray(rows),
            np.asarray(links.j),
            memory,
        )
    reciprocal = None
    if "reciprocal" in names:
        reciprocal = ReciprocalContext(
            z,
            np.asarray(links.i),
            np.asarray(links.j),
            params,
            np.asarray(rows),
            memory,
            x_obs,
            links.x_nb,
        )
    return StepContext(fix, reciprocal)


def _scratch(value):
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, dict):  # e.g. the stages' own statistics, by stage name
        return {k: _scratch(v) for k, v in value.items()}
    try:
        fields = vars(value)
    except TypeError:  # no attributes: a scalar, a tuple, None
        return copy.copy(value)
    out = copy.copy(value)
    for name, inner in fields.items():
        if isinstance(inner, np.ndarray):
            setattr(out, name, inner.copy())
    return out


def scratch_memory(memory: LinkMemory | None) -> LinkMemory | None:
    """A copy of the victim's memory the detector may update: arrays and the arrays of
    its per-link statistics copied (fusion bookkeeping shared: no detector stage touches
    it, and copying it would cost O(N^2))."""
    if memory is None:
        return None
    out = copy.copy(memory)
    for name, value in vars(memory).items():
        if name != "joint":
            setattr(out, name, _scratch(value))
    return out


def accepted(
    z: np.ndarray,
    z_hat: np.ndarray,
    S: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    gate_only: bool = False,
    row_wise_only: bool = False,
    context: StepContext | FixContext | None = None,
) -> np.ndarray:
    """Whether the victim's detector, in its current state, accepts measurements ``z``.

    Rows are judged as one round of the victim's correction (the per-link tests see their
    own link's state only; a row may repeat a link: each copy is judged against the state
    before this round).

    Parameters
    ----------
    z, z_hat : ndarray, shape (E, 2)
        Candidate and predicted measurements.
    S : ndarray, shape (E, 2, 2)
    i, j : ndarray of int, shape (E,)
    params : CLParams
    memory : LinkMemory or None
        The victim's memory (not modified).
    gate_only : bool
        Judge by the per-measurement gate alone (an attacker that knows nothing else).
    row_wise_only : bool
        Run only the stages that judge each row alone (:data:`ROW_WISE_STAGES`, and
        :data:`CONTEXT_STAGES` with the context's other rows held): then rows may be any
        stack of candidates.
    context : FixContext, optional
        The victims' other links this step, for a stage that reads them (the redundancy
        check; required when it is active). ``z`` is then a stack of candidate sets for
        ``context.rows``, each judged with the victims' other links at their values.

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    nu = innovation(z, z_hat)
    norm = innovation_norm(nu, S, params.detector_norm, params.noise_std)
    extra = {}
    if context is not None and any(s.name in CONTEXT_STAGES for s in active_stages(params)):
        extra = context.fields(z)
    evidence = Evidence(nu, S, norm, i, j, np.zeros(len(z), bool), **extra)
    if gate_only:
        gate = DETECTOR_STAGES[0]
        return ~gate.discard(evidence, params, None) if gate.active(params) else ~evidence.gated
    if not row_wise_only:
        return ~detect(evidence, params, scratch_memory(memory))
    # detect()'s loop, restricted to the row-wise stages.
    memory = scratch_memory(memory)
    detected = np.zeros(len(z), dtype=bool)
    for stage in active_stages(params):
        if stage.name not in ROW_WISE_STAGES | CONTEXT_STAGES:
            continue
        if stage.overrides:
            evidence.detected = detected
            detected = stage.discard(evidence, params, memory)
        else:
            detected = detected | stage.discard(evidence, params, memory)
    return ~detected


def largest_accepted(
    z: np.ndarray,
    lie: np.ndarray,
    z_hat: np.ndarray,
    S: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    gate_only: bool = False,
    context: StepContext | FixContext | None = None,
) -> np.ndarray:
    """Largest ``a`` in ``[0, 1]`` per row with ``z + a lie`` accepted by the victim.

    :func:`largest_accepted_along` on the straight path ``z + a lie``.

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Honest measurements.
    lie : ndarray, shape (E, 2)
        The full injection per row.
    z_hat, S, i, j, params, memory, gate_only, context
        As :func:`accepted`.

    Returns
    -------
    ndarray, shape (E,)
    """
    z, lie = np.asarray(z, float), np.asarray(lie, float)
    return largest_accepted_along(
        lambda frac: z[None] + frac[..., None] * lie[None],
        z_hat,
        S,
        i,
        j,
        params,
        memory,
        gate_only,
        context,
    )


def largest_accepted_along(
    path: Callable[[np.ndarray], np.ndarray],
    z_hat: np.ndarray,
    S: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    gate_only: bool = False,
    context: StepContext | FixContext | None = None,
) -> np.ndarray:
    """Largest ``a`` in ``[0, 1]`` per row with the measurement ``path(a)`` accepted.

    A grid over ``[0, 1]`` finds the largest accepted grid point (the acceptance region
    need not be an interval along the path: honest noise near the limit puts the start
    near one edge); further grids between it and the next point refine it (resolution
    ``1 / (GRID - 1)^PASSES`` of the path). Where no point is accepted (the honest
    measurement itself fails and so does every lie along the path) the result is 0: the
    measurement is discarded whatever is sent.

    Stages that judge each row alone given the state before the round
    (:data:`ROW_WISE_STAGES`) see every grid point of every row in one stacked call. A stage
    that couples the rows of a round (a per-robot sequence test, any stage added later)
    cannot see stacked copies (it would add them up and the attacker would hold back): the
    grids then use the row-wise stages, and the rows' choices are judged together by the
    whole detector as the victim will judge them, each rejected row bisected down
    (``BISECTIONS`` joint calls) to the largest fraction the round accepts.

    Parameters
    ----------
    path : callable
        ``path(frac)`` with ``frac`` of shape (G, E) returns the candidate measurements,
        shape (G, E, 2); ``path(0)`` is the measurement sent without a lie.
    z_hat, S, i, j, params, memory, gate_only, context
        As :func:`accepted`.

    Returns
    -------
    ndarray, shape (E,)
    """
    E = len(z_hat)
    if E == 0:
        return np.zeros(0)
    coupled = not gate_only and any(s.name not in ROW_WISE_STAGES for s in active_stages(params))

    def judge(frac: np.ndarray) -> np.ndarray:  # (G, E) -> (G, E) accepted, stacked
        cand = np.asarray(path(frac), float)
        G = len(frac)
        return accepted(
            cand.reshape(-1, 2),
            np.tile(z_hat, (G, 1)),
            np.tile(S, (G, 1, 1)),
            np.tile(i, G),
            np.tile(j, G),
            params,
            memory,
            gate_only,
            row_wise_only=coupled,
            context=context,
        ).reshape(G, E)

    lo = np.zeros(E)
    width = np.ones(E)
    any_ok = np.zeros(E, bool)
    rows = np.arange(E)
    for _ in range(PASSES):
        frac = np.minimum(lo[None] + np.linspace(0.0, 1.0, GRID)[:, None] * width[None], 1.0)
        ok = judge(frac)
        found = ok.any(axis=0)
        best = GRID - 1 - np.argmax(ok[::-1], axis=0)
        lo = np.where(found, frac[best, rows], lo)
        any_ok |= found
        width = width / (GRID - 1)
    a = np.where(any_ok, np.minimum(lo, 1.0), 0.0)
    if coupled:
        a = _joint(a, path, z_hat, S, i, j, params, memory, context)
    return a


def _joint(a, path, z_hat, S, i, j, params, memory, context=None) -> np.ndarray:
    """The rows' fractions ``a`` (each accepted by the row-wise stages) judged together by
    the whole detector; each rejected row bisected between 0 and its ``a`` (the others at
    their current choice) until the round passes. Rows still rejected send no lie."""

    def round_ok(frac: np.ndarray) -> np.ndarray:
        return accepted(path(frac[None])[0], z_hat, S, i, j, params, memory, context=context)

    ok = round_ok(a)
    bad = ~ok & (a > 0.0)
    if not bad.any():
        return a
    lo, hi = np.where(bad, 0.0, a), a.copy()
    for _ in range(BISECTIONS):
        trial = np.where(bad, 0.5 * (lo + hi), a)
        ok = round_ok(trial)
        lo = np.where(bad & ok, trial, lo)
        hi = np.where(bad & ~ok, trial, hi)
    a = np.where(bad, lo, a)
    ok = round_ok(a)
    return np.where(~ok & (a > 0.0), 0.0, a)
