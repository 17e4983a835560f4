"""Run a scenario: one world, every estimator in lockstep on the same data.

All estimators see exactly the same truth, odometry, measurements, attacks and channel
outcomes (common random numbers), so their differences are the filters' own.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import numpy as np

from resloc.cl.connectivity import DistributedLambda2
from resloc.cl.fusion_methods import FusionStrategy, fusion_strategy
from resloc.cl.gauge import GaugeSums
from resloc.cl.graph import Lambda2Source
from resloc.cl.params import CLParams
from resloc.experiments.backends import warm_up_kernels
from resloc.experiments.config import RiskSource, Scenario
from resloc.experiments.lockstep import (
    DEAD_RECKONING,
    Estimation,
    EstimatorState,
    LinkGroup,
    Step,
    divergence,
    run_lockstep,
)
from resloc.experiments.metrics import AccuracyRecorder, TruthDistances
from resloc.experiments.outcomes import OutcomeCounter
from resloc.experiments.recording import LinkLog, link_columns
from resloc.experiments.results import SERIES, TOTALS, EstimatorResult, RunResult
from resloc.filters.base import FilterKind, GaussianFilter, make_filter
from resloc.validation import check_memory
from resloc.world.attacks import AttackKind
from resloc.world.world import World

__all__ = [
    "DEAD_RECKONING",
    "EstimatorResult",
    "EstimatorTrack",
    "RunResult",
    "check_run_size",
    "divergence",
    "record_step",
    "run_bytes",
    "run_scenario",
]

#: Bytes per robot kept by each estimator between steps (x, P, link memory).
BYTES_PER_ROBOT_KEPT = 300
#: Bytes per robot of the temporaries of one estimator's step (estimators step one after
#: the other): predicted copies, sigma points, world pose and odometry.
BYTES_PER_ROBOT_STEP = 1_000
#: Bytes per sensing link in one step: the link batch and update temporaries, the k-d tree
#: pairs and the sparse factorisation behind lambda2 of large components.
BYTES_PER_LINK = 2_500
#: Bytes of Python objects (small arrays, tuples, floats) kept per step and estimator.
STEP_OBJECTS = 600
#: Safety factor and fixed overhead (numpy temporaries, per-step Python lists) on top.
RUN_MARGIN = 1.2
RUN_OVERHEAD = 64e6


class EstimatorTrack(EstimatorState):
    """One estimator of a simulated run: its state and everything recorded of trial 0 and
    per trial (``tr.diverged`` set: stopped, its series, track and covariances stay ``nan``
    from that step on)."""

    def __init__(
        self,
        name: str,
        filt: GaussianFilter,
        x0,
        P0,
        steps: int,
        T: int,
        N: int,
        fusion: FusionStrategy | None = None,
        truth: TruthDistances | None = None,
        without: dict[str, np.ndarray] | None = None,
    ):
        super().__init__(name, filt, x0, P0, T * N, fusion)
        self.series = {k: np.full((steps, T), np.nan) for k in SERIES}
        self.totals = {k: np.zeros(T, dtype=np.int64) for k in TOTALS}
        self.raster = np.zeros((steps, N), dtype=np.int8)
        self.track = np.zeros((steps + 1, N, 3))
        self.track[0] = x0[:N]
        self.cov = np.zeros((steps + 1, N, 3, 3), dtype=np.float32)
        self.cov[0] = P0[:N]
        self.link_flags: list[np.ndarray] = []  # trial 0, packed
        self.accuracy = AccuracyRecorder(self.series, self.totals, T, N, truth, without)
        exchanges = () if fusion is None else fusion.node_exchanges
        # gauge acknowledges every fusion with a 3x3 block; split CI with the id alone
        acks = (
            "ack"
            if "acks" in exchanges
            else "delivery_ack"
            if "delivery_acks" in exchanges
            else None
        )
        self.outcome_counts = OutcomeCounter(
            self.series, self.totals, self.raster, self.link_flags, T, N, acks,
            pairs="factors" in exchanges,
        )  # fmt: skip


def expected_links(scenario: Scenario) -> float:
    """Sensing links per step and trial: each robot sees the lattice neighbours inside the
    sensing radius, ``pi R^2 / spacing^2``, at most the rest of its team."""
    team, radius = scenario.world.team, scenario.world.sensing.radius
    return team.robots * min(team.robots - 1, math.pi * radius**2 / team.spacing**2 + 4)


def run_bytes(scenario: Scenario) -> float:
    """Estimated peak memory (bytes) of :func:`run_scenario`: the links and state of one
    estimator's step, and what every estimator keeps: its state, the series ``(steps, T)``,
    the trial-0 track, covariances ``(steps + 1, N, 3, 3)`` (float32) and link outcomes
    (calibrated against measured peaks in ``docs/reliability.md``)."""
    run, n = scenario.run, scenario.world.team.robots
    estimators = len(run.filters) + (1 if run.dead_reckoning else 0)
    robots = run.trials * n
    links = expected_links(scenario)
    step = BYTES_PER_ROBOT_STEP * robots + BYTES_PER_LINK * links * run.trials
    records = (run.steps + 1) * (8.0 * len(SERIES) * run.trials + (24 + 36) * n) + run.steps * (
        n + links
    )
    kept = estimators * (BYTES_PER_ROBOT_KEPT * robots + records)
    # Truth, trial-0 link columns, and the per-step Python objects (small arrays, lists).
    shared = (run.steps + 1) * (24.0 * n + 13.0 * links + STEP_OBJECTS * (1 + estimators))
    return RUN_MARGIN * (step + kept + shared) + RUN_OVERHEAD


def check_run_size(scenario: Scenario) -> None:
    """Refuse (one line, before allocating) a run that needs more memory than this machine
    can give it. Raises :class:`~resloc.errors.ConfigError`."""
    run, team = scenario.run, scenario.world.team
    check_memory(
        run_bytes(scenario),
        f"run.trials x team.robots = {run.trials} x {team.robots} robots over {run.steps} steps",
        "lower team.robots, run.trials or run.steps (or split the trials over several runs)",
    )


def _beyond_paper(params: CLParams, tampered: bool) -> bool:
    """Whether the run's compiled corrections take the link loops' form with the options'
    stages (:func:`resloc.cl.kernels.options_beyond_paper`; ``tampered``: the stealthy
    attacker hands the links its tamper hook), so that the warm-up compiles the form the
    run uses."""
    if tampered:
        return True
    try:
        from resloc.cl.kernels import options_beyond_paper
    except ImportError:  # pragma: no cover - numba is optional
        return True
    return options_beyond_paper(params)


def run_scenario(
    scenario: Scenario,
    filters: list[str] | None = None,
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    metric_stride: int = 1,
    params: CLParams | None = None,
    first_trial: int = 0,
    adversary=None,
    without: dict[str, np.ndarray] | None = None,
) -> RunResult:
    """Simulate ``scenario`` and run its estimators.

    Parameters
    ----------
    scenario : Scenario
    filters : list of str, optional
        Override ``run.filters`` (``ckf``, ``ukf``, ``ekf``).
    seed : int, optional
        Override ``run.seed``.
    progress : callable(k, steps), optional
        Called after every step.
    metric_stride : int
        Compute the O(N^2) MSLE/NEES/RMSE every ``metric_stride`` steps (others ``nan``).
    params : CLParams, optional
        Estimator parameters to use instead of ``scenario.cl_params()`` (e.g. per-robot
        detector thresholds ``(T * N,)`` to sweep a threshold over the trials of one run).
    first_trial : int
        Simulate trials ``first_trial .. first_trial + run.trials - 1`` of the seed (trial
        ``t`` is identical whichever trials are batched with it), so the seeds of one
        scenario can be split across tasks and re-run alone.
    adversary : Attacker, optional
        A strategy of the adversary suite (:mod:`resloc.world.attackers`): it chooses the
        links it falsifies each step and what every estimator receives on them.
    without : dict of str to ndarray, optional
        ``{name: ids}``: every estimator also records the MSLE of the team without robots
        ``ids`` as series ``msle_<name>`` (e.g. the robots an attacker runs left out;
        :class:`~resloc.experiments.metrics.AccuracyRecorder`).

    Returns
    -------
    RunResult
    """
    t_start = time.perf_counter()
    if filters is not None or seed is not None:
        changes = {}
        if filters is not None:
            changes["run.filters"] = list(filters)
        if seed is not None:
            changes["run.seed"] = int(seed)
        scenario = scenario.replace(**changes)
    check_run_size(scenario)
    run = scenario.run
    # With distributed estimates the world still computes the true (component) lambda2,
    # which is only recorded, to measure the estimates' error.
    world = World(
        scenario.world,
        run.trials,
        run.seed,
        scenario.trigger.lambda2.graph_mode,
        first_trial=first_trial,
    )
    params = scenario.cl_params() if params is None else params
    T, N, steps, dt = run.trials, world.n, run.steps, world.dt
    x0, P0 = world.initial_estimates()
    est = scenario.estimator
    fusion = fusion_strategy(params.fusion)
    rounds = est.gauge_rounds if est.gauge_sums is GaugeSums.CONSENSUS else None
    tracks = []
    truth = TruthDistances()  # every estimator's metrics see the same truth
    for name in run.filters:
        filt = make_filter(FilterKind(name), est.ukf_alpha, est.ukf_beta, est.ukf_kappa)
        tracks.append(EstimatorTrack(name, filt, x0, P0, steps, T, N, fusion, truth, without))
        fusion.init(tracks[-1].memory, x0, P0, N, rounds=rounds)
    dr = None
    if run.dead_reckoning:
        dr = EstimatorTrack(
            DEAD_RECKONING, make_filter(FilterKind.EKF), x0, P0, steps, T, N, truth=truth
        )
    estimated = scenario.trigger.risk_source is RiskSource.ESTIMATED
    setup = Estimation(
        params, dt, N, (world.sdz, world.cdz) if estimated else None, adversary=adversary
    )
    source = _WorldSteps(scenario, params, world, first_trial, adversary, metric_stride)
    everyone = [*tracks, *([dr] if dr is not None else [])]
    tick = None if progress is None else (lambda k: progress(k, steps))
    # Load (or compile) the kernels before any estimator's timer starts: otherwise the first
    # estimator's wall time carries the cache load.
    beyond = _beyond_paper(params, source.stealthy)
    either = adversary is not None  # an attacker of the suite may hand the links a hook
    warm_up_kernels(paper=either or not beyond, options=either or beyond)
    run_lockstep(source, everyone, setup, tick)
    for tr in everyone:  # a stopped estimator's buffered steps keep their records
        tr.accuracy.flush()
        tr.outcome_counts.flush()
    for tr in tracks:  # consensus exchanges are counted by the fusion's bookkeeping
        exchanged = int(getattr(tr.memory.joint, "messages", 0) or 0)
        tr.totals["consensus_messages"] += exchanged // T + (np.arange(T) < exchanged % T)
        if params.zone_trust or params.reciprocal:  # estimates carry the sender's readings
            tr.totals["readings"] += tr.totals["triggered"]
        if "delivery_acks" in fusion.node_exchanges:  # split CI: and its independent part
            tr.totals["independent_parts"] += tr.totals["triggered"]
        if "factors" in fusion.node_exchanges:  # factorized: the factor kept for the receiver
            tr.totals["factors"] += tr.totals["triggered"]
        if source.dl2 is not None:  # the distributed lambda2's exchanges, per trial
            tr.totals["connectivity_messages"] += source.dl2.messages_per_team
        if params.witness:  # a note per reading, one frame per observer and step
            tr.totals["witness_notes"] += tr.totals["candidates"]
            tr.totals["witness_frames"] += source.observer_steps
    shared = link_columns(source.trial0_links)
    results = {}
    for tr in everyone:
        log = LinkLog(shared, np.concatenate(tr.link_flags)) if tr.link_flags else None
        records = (tr.series, tr.totals, tr.raster, tr.track, tr.wall, tr.cov)
        results[tr.name] = EstimatorResult(tr.name, *records, log, tr.diverged)
    return RunResult(
        scenario,
        results,
        source.truth,
        dt * np.arange(1, steps + 1),
        time.perf_counter() - t_start,
        {"robots": N, "trials": T, **source.meta()},
    )


class _WorldSteps:
    """The simulated world as a :class:`~resloc.experiments.lockstep.StepSource`: one link
    group per step (every sensed link, neighbours at their predicted estimates), and the
    run's records (truth and links of trial 0, per-step series, per-trial totals).

    Per-run extensions (``docs/beyond.md``): with ``trigger.lambda2 = "distributed"`` every
    robot's own ``lambda2`` from a :class:`~resloc.cl.connectivity.DistributedLambda2` on
    the communication graph (the world's true component value is kept to measure the
    error); with ``attack.kind = "stealthy"`` a ``LinkBatch.tamper`` that injects the
    largest bias the estimator's detector accepts on the links the world marked attacked.
    """

    def __init__(self, scenario, params, world, first_trial, adversary, metric_stride):
        self.world, self.params, self.steps_total = world, params, scenario.run.steps
        self.adversary, self.metric_stride = adversary, metric_stride
        self.attack = scenario.world.attack
        self.stealthy = bool(world.sdz) and self.attack.kind is AttackKind.STEALTHY
        self.comm_radius = scenario.world.sensing.comm_radius
        self.dl2: DistributedLambda2 | None = None
        self.l2_true: list[float] = []
        self.l2_est: list[float] = []
        self.l2_abs_rel: list[float] = []
        self.observer_steps = np.zeros(world.trials, np.int64)  # witness frames, per trial
        self._l2_seen: tuple = (None, 0.0)  # the world's last lambda2 array and its mean
        if scenario.trigger.lambda2 is Lambda2Source.DISTRIBUTED:
            # Initial Fiedler-vector guesses drawn per trial (independent of the batching).
            y0 = np.concatenate(
                [
                    np.random.default_rng([scenario.run.seed, t, 0x1A2]).uniform(-1, 1, world.n)
                    for t in range(first_trial, first_trial + world.trials)
                ]
            )
            self.dl2 = DistributedLambda2(
                world.B, float(world.n), scenario.trigger.lambda2_rounds, y0=y0
            )
        N = world.n
        self.truth = np.zeros((self.steps_total + 1, N, 3))
        self.truth[0] = world.pose[:N]
        self.trial0_links: list[tuple] = []  # the world's links of trial 0, shared

    def steps(self) -> Iterator[Step]:
        world, N, T, dt = self.world, self.world.n, self.world.trials, self.world.dt
        for k in range(self.steps_total):
            ws = world.step()
            attack_step = None
            if self.adversary is not None:
                from resloc.world.attackers import AttackStep  # the suite loads numba

                attack_step = AttackStep(k + 1, dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
                ws.attacked = attack_step.attacked = self.adversary.mark(ws.attacked, attack_step)
            self.truth[k + 1] = ws.pose[:N]
            own = ws.i < N
            i, j = ws.i[own].astype(np.int32), ws.j[own].astype(np.int32)
            self.trial0_links.append((np.full(len(i), k + 1, np.int32), i, j, ws.attacked[own]))
            # Shared by every estimator's record of this step.
            self.ws, self.own_links = ws, len(i)
            self.team_i = world.team[ws.i]
            self.candidates = np.bincount(self.team_i, minlength=T)
            self.observer_steps += np.bincount(world.team[np.unique(ws.i)], minlength=T)
            self.attacked_n = np.bincount(self.team_i, weights=ws.attacked, minlength=T)
            self.record_metrics = (k + 1) % self.metric_stride == 0 or k == self.steps_total - 1
            lambda2 = self.lambda2(ws)
            links = LinkGroup(ws.i, ws.j, ws.z, ws.channel_ok, extras=self.link_extras(ws))
            edges = self.comm_edges(ws)
            yield Step(k, ws.u_meas, [links], ws.risk_s, ws.risk_c, lambda2, edges, attack_step)

    def record(self, tr: EstimatorTrack, step: Step) -> None:
        k = step.k
        if tr.diverged is not None:  # stopped: no estimate, no link outcomes from here on
            tr.track[k + 1], tr.cov[k + 1] = np.nan, np.nan
            tr.outcome_counts.flush()  # the steps before it first, in order
            tr.link_flags.append(np.zeros(self.own_links, np.uint8))
            return
        out = tr.outcomes[0] if tr.outcomes else None
        T, N = self.world.trials, self.world.n
        args = (self.team_i, self.candidates, self.attacked_n, T, N, self.record_metrics)
        record_step(tr, tr.fusion, k, self.ws, out, *args)

    def comm_edges(self, ws) -> tuple[np.ndarray, np.ndarray]:
        """This step's links that can carry a message (in radio range, not jammed)."""
        ok = self.in_comm(ws) & ws.channel_ok
        return ws.i[ok], ws.j[ok]

    def in_comm(self, ws) -> np.ndarray:
        """Which of this step's links are within radio range (the world's own flags)."""
        if ws.in_comm is not None:
            return ws.in_comm
        p = ws.pose[:, :2]
        return np.hypot(*(p[ws.i] - p[ws.j]).T) <= self.comm_radius

    def lambda2(self, ws) -> np.ndarray:
        """The ``lambda2`` each robot's trigger uses this step, shape (B,)."""
        if self.dl2 is None:
            # The world hands the same array until the graph changes: its mean is kept.
            if ws.lambda2 is not self._l2_seen[0]:
                ok = ws.lambda2 > 0
                self._l2_seen = (ws.lambda2, float(ws.lambda2[ok].mean()) if ok.any() else 0.0)
            self.l2_true.append(self._l2_seen[1])
            return ws.lambda2
        ok = ws.lambda2 > 0
        in_comm = self.in_comm(ws)
        est = self.dl2.step(ws.i[in_comm], ws.j[in_comm])
        self.l2_true.append(float(ws.lambda2[ok].mean()) if ok.any() else float("nan"))
        self.l2_est.append(float(est[ok].mean()) if ok.any() else float("nan"))
        rel = np.abs(est[ok] - ws.lambda2[ok]) / ws.lambda2[ok]
        self.l2_abs_rel.append(float(rel.mean()) if ok.any() else float("nan"))
        return est

    def link_extras(self, ws) -> dict:
        """Optional ``LinkBatch`` fields for this step (the same for every estimator)."""
        if not self.stealthy:
            return {}
        from resloc.world.adversary import stealthy_tamper  # loads numba: only when stealthy

        p, a = self.params, self.attack
        tamper = stealthy_tamper(
            ws.z,
            ws.attacked,
            ws.i,
            np.asarray(a.stealth_direction, float),
            a.stealth_margin,
            np.asarray(a.bias, float),
            p.detector,
            p.detector_norm,
            p.rho,
            p.noise_std,
            p.cusum_k if p.cusum else None,
            a.stealth_knowledge,
            p.mean_cusum_k if p.mean_cusum else None,
        )
        return {"tamper": tamper}

    def meta(self) -> dict:
        """Run-level records: ``lambda2`` (true mean over connected robots; with the
        distributed mode also the estimates and their error)."""
        if self.dl2 is None:
            return {"lambda2": {"true_mean": float(np.mean(self.l2_true))}}

        def mean(values: list[float]) -> float:
            return float(np.nanmean(values)) if values else float("nan")

        return {
            "lambda2": {
                "true_mean": mean(self.l2_true),
                "estimate_mean": mean(self.l2_est),
                "abs_rel_error_mean": mean(self.l2_abs_rel),
                "abs_rel_error_series": np.asarray(self.l2_abs_rel),
                "messages": self.dl2.messages,
            }
        }


def record_step(tr, fusion, k, ws, out, team_i, candidates, attacked_n, T, N, record) -> None:
    """Accumulate one step of one estimator (its link outcomes and accuracy are counted in
    bulk: :class:`~resloc.experiments.outcomes.OutcomeCounter`,
    :class:`~resloc.experiments.metrics.AccuracyRecorder`)."""
    tr.outcome_counts.add(k, out, ws.i, team_i, ws.attacked, candidates, attacked_n, ws.j)
    tr.track[k + 1] = tr.x[:N]
    P = tr.P if fusion is None else fusion.reported(tr.memory, tr.x, tr.P)
    tr.cov[k + 1] = P[:N]
    if record:  # computed in bulk (complete once the last step is recorded)
        tr.accuracy.add(k, ws.pose, tr.x, P)
