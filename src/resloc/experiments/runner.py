"""Run a scenario: one world, every estimator in lockstep on the same data.

All estimators see exactly the same truth, odometry, measurements, attacks and channel
outcomes (common random numbers), so their differences are the filters' own.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from resloc.cl.connectivity import DistributedLambda2
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.gauge import GaugeSums
from resloc.cl.graph import Lambda2Source
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.cl.step import LinkBatch, correct, predict
from resloc.errors import NumericalError
from resloc.experiments.config import RiskSource, Scenario
from resloc.experiments.metrics import (
    NEES_EXCEED_3DOF,
    communication,
    confusion_counts,
    detector_rates,
    msle,
    nees,
    nees_consistency_counts,
    position_rmse,
    rate,
    relative_nees,
)
from resloc.experiments.recording import LinkLog, link_columns, pack_outcomes
from resloc.filters.base import FilterKind, GaussianFilter, make_filter
from resloc.linalg import symmetrize
from resloc.validation import check_memory
from resloc.world.adversary import stealthy_tamper
from resloc.world.attackers import AttackStep
from resloc.world.attacks import AttackKind
from resloc.world.world import World

__all__ = [
    "DEAD_RECKONING",
    "EstimatorResult",
    "RunResult",
    "check_run_size",
    "divergence",
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

#: Name of the odometry-only baseline in results.
DEAD_RECKONING = "dr"

#: Per-step series recorded for every estimator, each of shape (steps, T).
SERIES = (
    "msle",
    "rmse",
    "nees",
    "nees_rel",
    "candidates",
    "triggered",
    "delivered",
    "detected",
    "attacked",
)
#: Per-trial totals, each of shape (T,).
TOTALS = (
    "candidates",
    "triggered",
    "delivered",
    "failed",
    "detected",
    "fused",
    "attacked",
    "tp",
    "fp",
    "fn",
    "tn",
    "attacked_fused",
    "repairs",
    "nees_samples",
    "nees_exceed",
    "nees_rel_exceed",
    "ack_links",
    "ack_frames",
    "consensus_messages",
)


@dataclass
class EstimatorResult:
    """Everything recorded for one estimator over a run.

    Attributes
    ----------
    name : str
        ``ckf``, ``ukf``, ``ekf`` or ``dr``.
    series : dict of str to ndarray, each shape (steps, T)
        Per-step metrics (``msle``, ``rmse``, ``nees``) and link counts.
    totals : dict of str to ndarray, each shape (T,)
        Per-trial counts over the run.
    raster : ndarray of int8, shape (steps, N)
        Transmissions attempted by each robot of trial 0 at each step.
    track : ndarray, shape (steps + 1, N, 3)
        Estimated poses of trial 0.
    wall_time : float
        Seconds spent in this estimator's predict/correct.
    cov : ndarray of float32, shape (steps + 1, N, 3, 3), optional
        Covariances of trial 0 (as reported: with gauge fusion ``D_i + J_i G J_i^T``).
    links : LinkLog, optional
        Every sensed link of trial 0 over the run, each shape (M,): ``step`` (1-based),
        ``i``, ``j``, ``attacked`` (shared by the estimators) and this estimator's
        ``detected``, ``triggered``, ``delivered``, ``fused`` (for exports and figures).
    diverged : dict or None
        If the estimator diverged: ``step`` (1-based), ``time_s``, ``trial``, ``robot`` and
        ``reason`` (see :func:`divergence`). Its series, track and covariances are ``nan``
        from that step on (its link outcomes all false) and its summary's error statistics
        are ``nan``: an average over the steps before the failure would look like a result.
    """

    name: str
    series: dict[str, np.ndarray]
    totals: dict[str, np.ndarray]
    raster: np.ndarray
    track: np.ndarray
    wall_time: float = 0.0
    cov: np.ndarray | None = None
    links: LinkLog | None = None
    diverged: dict | None = None

    def summary(self) -> dict[str, float]:
        """Scalar summary: means over steps and trials, final values, rates, detector scores
        (error statistics ``nan`` and ``diverged_step`` set if the estimator diverged)."""
        with warnings.catch_warnings():  # a diverged estimator has all-NaN final steps
            warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
            warnings.filterwarnings("ignore", "All-NaN slice", RuntimeWarning)
            out = self._summary()
        if self.diverged:
            for key in ("msle_mean", "msle_final", "rmse_mean", "rmse_final"):
                out[key] = float("nan")
            out["nees_mean"] = out["nees_median"] = float("nan")
            out["diverged_step"] = self.diverged["step"]
        return out

    def _summary(self) -> dict[str, float]:
        s, t = self.series, self.totals
        steps = s["msle"].shape[0]
        out = {
            "msle_mean": float(np.nanmean(s["msle"])),
            "msle_final": float(np.nanmean(s["msle"][-1])),
            "rmse_mean": float(np.nanmean(s["rmse"])),
            "rmse_final": float(np.nanmean(s["rmse"][-1])),
            "nees_mean": float(np.nanmean(s["nees"])),
            "nees_median": float(np.nanmedian(s["nees"])),
            "comm_rate": rate(t["triggered"].sum(), t["candidates"].sum()),
            "delivery_rate": rate(t["delivered"].sum(), t["triggered"].sum()),
            "fused_rate": rate(t["fused"].sum(), t["candidates"].sum()),
            "attacked_rate": rate(t["attacked"].sum(), t["candidates"].sum()),
            "attacked_fused": int(t["attacked_fused"].sum()),
            "candidates": int(t["candidates"].sum()),
            "transmissions": int(t["triggered"].sum()),
            "delivered": int(t["delivered"].sum()),
            "failed": int(t["failed"].sum()),
            "discarded": int(t["detected"].sum()),
            "repairs": int(t["repairs"].sum()),
            "wall_time_s": self.wall_time,
            "steps": steps,
        }
        scores = detector_rates(*(int(t[k].sum()) for k in ("tp", "fp", "fn", "tn")))
        out["detector_precision"] = scores["precision"]
        out["detector_recall"] = scores["recall"]
        out["detector_false_alarm"] = scores["false_alarm_rate"]
        out.update(self._honest_summary())
        return out

    def _honest_summary(self) -> dict[str, float]:
        """Relative NEES, the consistency tests on every per-robot, per-step sample, and the
        messages and bytes of every kind (``WIRE_BYTES``)."""
        s, t = self.series, self.totals
        n = int(t["nees_samples"].sum())
        out = {"nees_rel_mean": float(np.nanmean(s["nees_rel"]))}
        for key, series in (("nees", s["nees"]), ("nees_rel", s["nees_rel"])):
            test = nees_consistency_counts(
                float(np.nanmean(series)) * n, n, int(t[f"{key}_exceed"].sum())
            )
            out[f"{key}_band_lo"], out[f"{key}_band_hi"] = test["band_lo"], test["band_hi"]
            out[f"{key}_exceed_share"] = test["exceed_share"]
            out[f"{key}_exceed_pvalue"] = test["exceed_pvalue"]
        for kind, (messages, wire) in communication(t).items():
            out[f"messages_{kind}"] = int(messages.sum())
            out[f"bytes_{kind}"] = int(wire.sum())
        return out

    def bytes_per_trial(self) -> np.ndarray:
        """Robot-to-robot bytes of every kind per trial, shape (T,) (``communication``)."""
        return communication(self.totals)["total"][1]

    def per_trial(self, metric: str) -> np.ndarray:
        """A per-trial scalar, shape (T,): ``msle_mean``, ``msle_final``, ``rmse_mean``,
        ``nees_mean`` or ``comm_rate``."""
        s, t = self.series, self.totals
        if metric == "comm_rate":
            with np.errstate(invalid="ignore", divide="ignore"):
                return t["triggered"] / t["candidates"]
        key, how = metric.rsplit("_", 1)
        return np.nanmean(s[key], axis=0) if how == "mean" else s[key][-1]


@dataclass
class RunResult:
    """A finished run: the resolved scenario, the truth of trial 0, and every estimator."""

    scenario: Scenario
    estimators: dict[str, EstimatorResult]
    truth: np.ndarray  # (steps + 1, N, 3) true poses of trial 0
    time: np.ndarray  # (steps,) seconds
    wall_time: float = 0.0
    meta: dict = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, float]]:
        """``{estimator: summary}``."""
        return {name: est.summary() for name, est in self.estimators.items()}


class EstimatorTrack:
    """Mutable state of one estimator during a run."""

    def __init__(self, name: str, filt: GaussianFilter, x0, P0, steps: int, T: int, N: int):
        self.name = name
        self.filt = filt
        self.x = x0.copy()
        self.P = P0.copy()
        self.memory = LinkMemory(T * N)
        self.series = {k: np.full((steps, T), np.nan) for k in SERIES}
        self.totals = {k: np.zeros(T, dtype=np.int64) for k in TOTALS}
        self.raster = np.zeros((steps, N), dtype=np.int8)
        self.track = np.zeros((steps + 1, N, 3))
        self.track[0] = x0[:N]
        self.cov = np.zeros((steps + 1, N, 3, 3), dtype=np.float32)
        self.cov[0] = P0[:N]
        self.link_flags: list[np.ndarray] = []  # trial 0, packed per step
        self.wall = 0.0
        self.diverged: dict | None = None
        self.out = None
        self.pending_P: np.ndarray | None = None

    def stop(self, k: int, dt: float, N: int, P: np.ndarray, reason: str) -> None:
        """Mark the estimator diverged at step index ``k`` (0-based) and blank its future."""
        self.diverged = divergence(k, dt, N, P, reason)
        self.track[k + 1 :] = np.nan
        self.cov[k + 1 :] = np.nan
        for arr in self.series.values():
            arr[k:] = np.nan


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


def run_scenario(
    scenario: Scenario,
    filters: list[str] | None = None,
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    metric_stride: int = 1,
    params: CLParams | None = None,
    first_trial: int = 0,
    adversary=None,
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
    distributed = scenario.trigger.lambda2 is Lambda2Source.DISTRIBUTED
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
    hooks = _Hooks(scenario, params, world, distributed, first_trial)
    est = scenario.estimator
    tracks = [
        EstimatorTrack(
            name,
            make_filter(FilterKind(name), est.ukf_alpha, est.ukf_beta, est.ukf_kappa),
            x0,
            P0,
            steps,
            T,
            N,
        )
        for name in run.filters
    ]
    fusion = fusion_strategy(params.fusion)
    rounds = est.gauge_rounds if est.gauge_sums is GaugeSums.CONSENSUS else None
    for tr in tracks:
        fusion.init(tr.memory, x0, P0, N, rounds=rounds)
    dr = None
    if run.dead_reckoning:
        dr = EstimatorTrack(DEAD_RECKONING, make_filter(FilterKind.EKF), x0, P0, steps, T, N)
    truth = np.zeros((steps + 1, N, 3))
    truth[0] = world.pose[:N]
    team = world.team
    trial0_links: list[tuple] = []  # the world's links of trial 0, shared by the estimators
    for k in range(steps):
        ws = world.step()
        attack_step = None
        if adversary is not None:
            attack_step = AttackStep(k + 1, dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
            ws.attacked = attack_step.attacked = adversary.mark(ws.attacked, attack_step)
        truth[k + 1] = ws.pose[:N]
        own = ws.i < N
        trial0_links.append(
            (
                np.full(int(own.sum()), k + 1, np.int32),
                ws.i[own].astype(np.int32),
                ws.j[own].astype(np.int32),
                ws.attacked[own],
            )
        )
        team_i = team[ws.i]
        candidates = np.bincount(team_i, minlength=T)
        attacked_n = np.bincount(team_i, weights=ws.attacked, minlength=T)
        record = (k + 1) % metric_stride == 0 or k == steps - 1
        lambda2 = hooks.lambda2(ws)
        comm_edges = hooks.comm_edges(ws)
        step_inputs = _StepInputs(
            params, fusion, hooks, world, scenario, lambda2, comm_edges, dt, adversary, attack_step
        )
        for tr in tracks:
            if tr.diverged is None:
                _isolated_step(tr, k, ws, step_inputs, N)
            if tr.diverged is not None:  # stopped: no link outcomes from here on
                tr.link_flags.append(np.zeros(int(own.sum()), np.uint8))
                continue
            record_step(tr, fusion, k, ws, tr.out, team_i, candidates, attacked_n, T, N, record)
        if dr is not None:
            t0 = time.perf_counter()
            dr.x, dr.P = predict(dr.filt, dr.x, dr.P, ws.u_meas, dt, params)
            dr.wall += time.perf_counter() - t0
            record_step(dr, None, k, ws, None, team_i, candidates, attacked_n, T, N, record)
        if progress is not None:
            progress(k + 1, steps)
    for tr in tracks:  # consensus exchanges are counted by the fusion's bookkeeping
        exchanged = int(getattr(tr.memory.joint, "messages", 0) or 0)
        tr.totals["consensus_messages"] += exchanged // T + (np.arange(T) < exchanged % T)
    shared = link_columns(trial0_links)
    results = {}
    for tr in [*tracks, *([dr] if dr is not None else [])]:
        log = LinkLog(shared, np.concatenate(tr.link_flags)) if tr.link_flags else None
        results[tr.name] = EstimatorResult(
            tr.name,
            tr.series,
            tr.totals,
            tr.raster,
            tr.track,
            tr.wall,
            tr.cov,
            log,
            tr.diverged,
        )
    return RunResult(
        scenario,
        results,
        truth,
        dt * np.arange(1, steps + 1),
        time.perf_counter() - t_start,
        {"robots": N, "trials": T, **hooks.meta()},
    )


@dataclass
class _StepInputs:
    """What every estimator's step shares within one world step."""

    params: CLParams
    fusion: object
    hooks: _Hooks
    world: World
    scenario: Scenario
    lambda2: np.ndarray
    comm_edges: tuple[np.ndarray, np.ndarray]
    dt: float
    adversary: object = None  # a strategy of resloc.world.attackers, with its AttackStep
    attack_step: object = None


def _isolated_step(tr: EstimatorTrack, k: int, ws, inputs: _StepInputs, N: int) -> None:
    """:func:`_step_estimator`, timed; a numerical failure or a non-finite estimate stops
    this estimator (``tr.diverged``) instead of the run: the others' results must not be
    lost to one filter's divergence."""
    t0 = time.perf_counter()
    tr.pending_P = None
    try:
        _step_estimator(tr, ws, inputs)
    except (NumericalError, np.linalg.LinAlgError, FloatingPointError) as exc:
        last = tr.pending_P if tr.pending_P is not None else tr.P
        tr.stop(k, inputs.dt, N, last, str(exc))
        return
    finally:
        tr.wall += time.perf_counter() - t0
    if not (np.all(np.isfinite(tr.x)) and np.all(np.isfinite(tr.P))):
        tr.stop(k, inputs.dt, N, tr.P, "the estimate became NaN or infinite")


def _step_estimator(tr: EstimatorTrack, ws, inputs: _StepInputs) -> None:
    """One step (predict, links, correct, exchange) of one estimator; sets ``tr.x``,
    ``tr.P``, ``tr.out`` (and ``tr.pending_P``, the predicted covariance, for divergence
    reports)."""
    params, fusion, world, dt = inputs.params, inputs.fusion, inputs.world, inputs.dt
    xp, Pp = predict(tr.filt, tr.x, tr.P, ws.u_meas, dt, params)
    tr.pending_P = Pp
    Pp = fusion.predict(tr.memory, tr.x, ws.u_meas, dt, params, Pp)
    if inputs.scenario.trigger.risk_source is RiskSource.ESTIMATED:
        risk_s = world.sdz.risk(xp[:, :2]) if world.sdz else ws.risk_s
        risk_c = world.cdz.risk(xp[:, :2]) if world.cdz else ws.risk_c
    else:
        risk_s, risk_c = ws.risk_s, ws.risk_c
    links = LinkBatch.from_predicted(
        ws.i,
        ws.j,
        ws.z,
        xp,
        Pp,
        ws.channel_ok,
        risk_s,
        risk_c,
        inputs.lambda2,
        **fusion.link_fields(tr.memory, ws.j),
        **inputs.hooks.link_extras(ws),
    )
    if inputs.adversary is not None:
        links = inputs.adversary.attack(links, inputs.attack_step, params, tr.memory)
    tr.x, tr.P, tr.out = correct(tr.filt, xp, Pp, links, params, tr.memory)
    fusion.exchange(tr.memory, *inputs.comm_edges)


def divergence(k: int, dt: float, N: int, P: np.ndarray, reason: str) -> dict:
    """Describe a divergence at step index ``k``: when, and which robot.

    The failing computation may be inside a link update, so the robot is the one whose
    covariance among ``P`` (shape ``(T * N, 3, 3)``, the last one computed) is non-finite
    or closest to singular (smallest eigenvalue relative to its trace).

    Returns
    -------
    dict
        ``step`` (1-based), ``time_s``, ``trial``, ``robot``, ``min_eigenvalue``, ``reason``.
    """
    P = np.asarray(P, dtype=float)
    finite = np.all(np.isfinite(P), axis=(-1, -2))
    score = np.full(len(P), -np.inf)
    if finite.any():
        Pf = symmetrize(P[finite])
        eig = np.linalg.eigvalsh(Pf)[:, 0]
        trace = np.maximum(np.trace(Pf, axis1=-2, axis2=-1), 1e-300)
        score[finite] = eig / trace
    b = int(np.argmin(score)) if len(P) else 0
    min_eig = float(np.linalg.eigvalsh(symmetrize(P[b]))[0]) if finite[b] else float("nan")
    return {
        "step": k + 1,
        "time_s": round((k + 1) * dt, 9),
        "trial": b // N,
        "robot": b % N,
        "min_eigenvalue": min_eig,
        "reason": reason.splitlines()[0] if reason else "",
    }


class _Hooks:
    """Per-run extensions of the lockstep loop (issue 6, ``docs/beyond.md``).

    * ``trigger.lambda2 = "distributed"``: every robot's own estimate of ``lambda2`` from a
      :class:`~resloc.cl.connectivity.DistributedLambda2` run on the communication graph
      (the world's true component value is kept to measure the error);
    * ``attack.kind = "stealthy"``: a ``LinkBatch.tamper`` per estimator that injects the
      largest bias that estimator's detector accepts, on the links the world marked attacked.

    The cl layer never imports the world: it only calls the hooks it is given.
    """

    def __init__(
        self,
        scenario: Scenario,
        params: CLParams,
        world: World,
        distributed: bool,
        first_trial: int = 0,
    ):
        self.params = params
        self.world = world
        self.attack = scenario.world.attack
        self.stealthy = bool(world.sdz) and self.attack.kind is AttackKind.STEALTHY
        self.comm_radius = scenario.world.sensing.comm_radius
        self.dl2: DistributedLambda2 | None = None
        self.l2_true: list[float] = []
        self.l2_est: list[float] = []
        self.l2_abs_rel: list[float] = []
        if distributed:
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

    def comm_edges(self, ws) -> tuple[np.ndarray, np.ndarray]:
        """This step's links that can carry a message (in radio range, not jammed)."""
        p = ws.pose[:, :2]
        ok = (np.hypot(*(p[ws.i] - p[ws.j]).T) <= self.comm_radius) & ws.channel_ok
        return ws.i[ok], ws.j[ok]

    def lambda2(self, ws) -> np.ndarray:
        """The ``lambda2`` each robot's trigger uses this step, shape (B,)."""
        if self.dl2 is None:
            ok = ws.lambda2 > 0
            self.l2_true.append(float(ws.lambda2[ok].mean()) if ok.any() else 0.0)
            return ws.lambda2
        p = ws.pose[:, :2]
        in_comm = np.hypot(*(p[ws.i] - p[ws.j]).T) <= self.comm_radius
        est = self.dl2.step(ws.i[in_comm], ws.j[in_comm])
        ok = ws.lambda2 > 0
        self.l2_true.append(float(ws.lambda2[ok].mean()) if ok.any() else float("nan"))
        self.l2_est.append(float(est[ok].mean()) if ok.any() else float("nan"))
        rel = np.abs(est[ok] - ws.lambda2[ok]) / ws.lambda2[ok]
        self.l2_abs_rel.append(float(rel.mean()) if ok.any() else float("nan"))
        return est

    def link_extras(self, ws) -> dict:
        """Optional ``LinkBatch`` fields for this step and estimator."""
        extra: dict = {}
        if self.stealthy:
            p, a = self.params, self.attack
            extra["tamper"] = stealthy_tamper(
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
        return extra

    def meta(self) -> dict:
        """Run-level records: ``lambda2`` (true mean over connected robots; with the
        distributed mode also the estimates and their error)."""
        if self.dl2 is None:
            return {"lambda2": {"true_mean": float(np.mean(self.l2_true))}}
        return {
            "lambda2": {
                "true_mean": float(np.nanmean(self.l2_true)) if self.l2_true else float("nan"),
                "estimate_mean": float(np.nanmean(self.l2_est)) if self.l2_est else float("nan"),
                "abs_rel_error_mean": float(np.nanmean(self.l2_abs_rel))
                if self.l2_abs_rel
                else float("nan"),
                "abs_rel_error_series": np.asarray(self.l2_abs_rel),
                "messages": self.dl2.messages,
            }
        }


def record_step(tr, fusion, k, ws, out, team_i, candidates, attacked_n, T, N, record) -> None:
    """Accumulate one step of one estimator."""
    s, tot = tr.series, tr.totals
    s["candidates"][k] = candidates
    s["attacked"][k] = attacked_n
    tot["candidates"] += candidates
    tot["attacked"] += attacked_n.astype(np.int64)
    if out is not None:
        att = ws.attacked

        def count(mask):
            return np.bincount(team_i, weights=mask, minlength=T).astype(np.int64)

        trig = count(out.triggered)
        s["triggered"][k] = trig
        s["delivered"][k] = count(out.delivered)
        s["detected"][k] = count(out.detected)
        tot["triggered"] += trig
        tot["delivered"] += count(out.delivered)
        tot["failed"] += count(out.triggered & ~out.delivered)
        tot["detected"] += count(out.detected)
        tot["fused"] += count(out.fused)
        tot["attacked_fused"] += count(out.fused & att)
        for key, per_trial in confusion_counts(out.detected, att, team_i, T).items():
            tot[key] += per_trial
        tot["repairs"] += count(out.repaired)
        if fusion is not None and "acks" in fusion.node_exchanges:  # gauge acknowledges fusions
            tot["ack_links"] += count(out.fused)
            senders = np.unique(ws.i[out.fused])
            tot["ack_frames"] += np.bincount(senders // N, minlength=T)
        own = ws.i < N
        tr.raster[k] = np.bincount(ws.i[own], weights=out.triggered[own], minlength=N)
        flags = (out.detected, out.triggered, out.delivered, out.fused)  # LINK_FLAGS order
        tr.link_flags.append(pack_outcomes(*(f[own] for f in flags)))
    tr.track[k + 1] = tr.x[:N]
    P = tr.P if fusion is None else fusion.reported(tr.memory, tr.x, tr.P)
    tr.cov[k + 1] = P[:N]
    if record:
        pos_t = ws.pose[:, :2].reshape(T, N, 2)
        pos_e = tr.x[:, :2].reshape(T, N, 2)
        s["msle"][k] = msle(pos_t, pos_e)
        s["rmse"][k] = position_rmse(pos_t, pos_e)
        per_robot = nees(ws.pose, tr.x, P).reshape(T, N)
        rel = relative_nees(ws.pose.reshape(T, N, 3), tr.x.reshape(T, N, 3), P.reshape(T, N, 3, 3))
        s["nees"][k] = per_robot.mean(axis=1)
        s["nees_rel"][k] = rel.mean(axis=1)
        tot["nees_samples"] += N
        tot["nees_exceed"] += (per_robot > NEES_EXCEED_3DOF).sum(axis=1)
        tot["nees_rel_exceed"] += (rel > NEES_EXCEED_3DOF).sum(axis=1)
