"""A dataset cut into replay steps: odometry per step, ground truth at the step times,
every sighting assigned to a step, and the attack layer's draws (seeded, drawn once so every
estimator sees the same ones)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from resloc.angles import wrap_angle
from resloc.datasets.mrclam import MRCLAMDataset
from resloc.errors import ConfigError
from resloc.experiments.mrclam.config import MAX_REPLAY_STEPS, MRCLAMConfig
from resloc.validation import check_memory
from resloc.world.attacks import apply_injection, attackable_links, injection
from resloc.world.zones import Zone, ZoneField

__all__ = [
    "Replay",
    "check_replay_size",
    "default_zones",
    "ground_truth_at",
    "prepare_replay",
    "replay_bytes",
    "step_commands",
]


def ground_truth_at(gt: np.ndarray, t: np.ndarray, max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses interpolated at times ``t`` (heading unwrapped, then wrapped).

    Parameters
    ----------
    gt : ndarray, shape (G, 4)
        ``time, x, y, theta`` rows sorted by time.
    t : ndarray, shape (T,)
    max_gap : float
        A time is valid only inside the ground-truth span and between samples closer than
        this (s).

    Returns
    -------
    pose : ndarray, shape (T, 3)
        Clamped to the first/last sample outside the span.
    valid : ndarray of bool, shape (T,)
    """
    tg = gt[:, 0]
    pose = np.empty((len(t), 3))
    pose[:, 0] = np.interp(t, tg, gt[:, 1])
    pose[:, 1] = np.interp(t, tg, gt[:, 2])
    pose[:, 2] = wrap_angle(np.interp(t, tg, np.unwrap(gt[:, 3])))
    if len(tg) < 2:
        return pose, np.isclose(t, tg[0])
    k = np.clip(np.searchsorted(tg, t), 1, len(tg) - 1)
    valid = (t >= tg[0]) & (t <= tg[-1]) & (tg[k] - tg[k - 1] <= max_gap)
    return pose, valid


def step_commands(odo: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Time average of a zero-order-held command over each step.

    Parameters
    ----------
    odo : ndarray, shape (M, 3)
        ``time, v, omega`` sorted by time; the command is 0 before the first row.
    times : ndarray, shape (K + 1,)
        Step boundaries.

    Returns
    -------
    ndarray, shape (K, 2)
    """
    if len(odo) == 0:
        return np.zeros((len(times) - 1, 2))
    to = odo[:, 0]
    cum = np.zeros((len(odo), 2))
    cum[1:] = np.cumsum(odo[:-1, 1:] * np.diff(to)[:, None], axis=0)

    def integral(t: np.ndarray) -> np.ndarray:
        k = np.searchsorted(to, t, side="right") - 1
        before = k < 0
        kc = np.maximum(k, 0)
        out = cum[kc] + odo[kc, 1:] * (t - to[kc])[:, None]
        out[before] = 0.0
        return out

    return np.diff(integral(times), axis=0) / np.diff(times)[:, None]


# ---------------------------------------------------------------------------- zones
def default_zones(truth: np.ndarray, valid: np.ndarray) -> tuple[Zone, Zone]:
    """SDZ and CDZ placed where the robots go.

    Along the axis on which the robots' true positions spread most, the SDZ is centred at
    the 30 % quantile and the CDZ at the 70 % quantile (the other coordinate at the median);
    both radii are 15 % of the 5-95 % spread along that axis. Linear risk profile, peak 1.

    Parameters
    ----------
    truth : ndarray, shape (K, N, 3)
    valid : ndarray of bool, shape (K, N)

    Returns
    -------
    sdz, cdz : Zone
    """
    p = truth[..., :2][valid]
    if len(p) == 0:
        raise ConfigError("cannot place danger zones: no valid ground truth in the replay")
    q05, q30, q50, q70, q95 = np.quantile(p, [0.05, 0.3, 0.5, 0.7, 0.95], axis=0)
    axis = int(np.argmax(q95 - q05))
    radius = max(0.15 * float(q95[axis] - q05[axis]), 0.1)
    centres = []
    for q in (q30, q70):
        c = q50.copy()
        c[axis] = q[axis]
        centres.append((float(c[0]), float(c[1])))
    return Zone(centres[0], radius), Zone(centres[1], radius)


# ---------------------------------------------------------------------------- replay data
@dataclass
class Replay:
    """A dataset cut into steps, with every measurement assigned to a step.

    Attributes
    ----------
    dataset : MRCLAMDataset
    time : ndarray, shape (K + 1,)
        Step times ``k dt`` (s, relative to the dataset start).
    u : ndarray, shape (K, N, 2)
        Odometry input of each step.
    truth : ndarray, shape (K + 1, N, 3)
        Ground truth interpolated at the step times.
    valid : ndarray of bool, shape (K + 1, N)
    x0 : ndarray, shape (N, 3)
        Initial poses (ground truth at ``t = 0``).
    step : ndarray of int, shape (M,)
        Step of each measurement (fused after the prediction to ``time[step]``); rows are
        sorted by step, then landmark-before-robot, then observer, then time.
    obs : ndarray of int, shape (M,)
        Observer robot index.
    target : ndarray of int, shape (M,)
        Robot index ``[0, N)`` or ``N + landmark index``.
    is_robot : ndarray of bool, shape (M,)
    z : ndarray, shape (M, 2)
        Range/bearing, falsified where ``attacked``.
    z_clean : ndarray, shape (M, 2)
    attacked : ndarray of bool, shape (M,)
    channel_ok : ndarray of bool, shape (M,)
    risk_s, risk_c : ndarray, shape (K + 1, N)
        ``Ds(i)``, ``Dc(i)`` at the true positions (zeros without zones).
    sdz, cdz : ZoneField
    bounds : ndarray of int, shape (K + 2,)
        Measurement rows of step ``k`` are ``bounds[k]:bounds[k + 1]``.
    """

    dataset: MRCLAMDataset
    time: np.ndarray
    u: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    x0: np.ndarray
    step: np.ndarray
    obs: np.ndarray
    target: np.ndarray
    is_robot: np.ndarray
    z: np.ndarray
    z_clean: np.ndarray
    attacked: np.ndarray
    channel_ok: np.ndarray
    risk_s: np.ndarray
    risk_c: np.ndarray
    sdz: ZoneField
    cdz: ZoneField
    bounds: np.ndarray

    @property
    def steps(self) -> int:
        return len(self.time) - 1

    def initial_estimates(self, init_std: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """``x0: (N, 3)`` (ground truth at ``t = 0``) and ``P0: (N, 3, 3)`` from the
        position and heading standard deviations ``init_std``."""
        p_std, h_std = init_std
        var = np.maximum([p_std**2, p_std**2, h_std**2], 1e-10)
        return self.x0.copy(), np.broadcast_to(np.diag(var), (len(self.x0), 3, 3)).copy()

    def head(self, steps: int) -> Replay:
        """The first ``steps`` steps of this replay (and the sightings fused in them)."""
        cut = self.bounds[steps + 1]
        rows = ("step", "obs", "target", "is_robot", "z", "z_clean", "attacked", "channel_ok")
        return dataclasses.replace(
            self,
            time=self.time[: steps + 1],
            u=self.u[:steps],
            truth=self.truth[: steps + 1],
            valid=self.valid[: steps + 1],
            **{name: getattr(self, name)[:cut] for name in rows},
        )


def replay_bytes(steps: int, robots: int, estimators: int) -> float:
    """Estimated peak memory (bytes) of a replay: per step and robot, the truth, validity,
    commands and risks (8 floats), each estimator's track and covariances (12 floats: the
    estimators run in lockstep), its scored errors and float32 covariances (8 floats), and
    the scoring temporaries of the one being scored (24 floats)."""
    return 8.0 * (steps + 1) * robots * (8 + 20 * estimators + 24)


def check_replay_size(data: MRCLAMDataset, config: MRCLAMConfig, steps: int) -> None:
    """Refuse (one line) a replay too long or too large for this machine, before allocating.

    The message names the row that sets the data's end: one absurd timestamp is the usual
    cause of a replay of years.
    """
    where = f" (the data end at {data.end_row})" if data.end_row else ""
    what = f"replay of {steps * config.dt:.6g} s at dt {config.dt} s = {steps} steps{where}"
    fix = "pass a shorter --duration or a larger --dt, or fix the row named here"
    if steps > MAX_REPLAY_STEPS:
        raise ConfigError(f"{what}: more than {MAX_REPLAY_STEPS} steps; {fix}")
    check_memory(replay_bytes(steps, data.n_robots, 1 + len(config.filters)), what, fix)


def prepare_replay(data: MRCLAMDataset, config: MRCLAMConfig) -> Replay:
    """Cut ``data`` into steps, assign measurements, and draw the attacks (seeded).

    Parameters
    ----------
    data : MRCLAMDataset
    config : MRCLAMConfig

    Returns
    -------
    Replay
    """
    dt = config.dt
    end = data.end
    if config.duration is not None:
        # A cut dataset ends at its last row <= duration: replay the full duration unless
        # the data really stop earlier (more than a second before it).
        end = config.duration if data.end > config.duration - 1.0 else data.end
    K = int(np.ceil(end / dt - 1e-9))  # the last (partial) step holds the last rows
    if K < 1:
        raise ConfigError(
            f"the replay is shorter than one step: {end:.3f} s of data with dt = {dt} s"
        )
    check_replay_size(data, config, K)
    times = dt * np.arange(K + 1)
    N = data.n_robots
    u = np.stack([step_commands(r.odometry, times) for r in data.robots], axis=1)
    truth = np.empty((K + 1, N, 3))
    valid = np.empty((K + 1, N), dtype=bool)
    for r, log in enumerate(data.robots):
        truth[:, r], valid[:, r] = ground_truth_at(log.groundtruth, times, config.gt_max_gap)
    x0 = truth[0].copy()

    subj_to_robot = {s: r for r, s in enumerate(data.robot_subjects.tolist())}
    subj_to_target = subj_to_robot | {
        int(s): N + k for k, s in enumerate(data.landmark_subjects.tolist())
    }
    columns = []
    for r, log in enumerate(data.robots):
        m = log.measurements
        target = np.array([subj_to_target[int(s)] for s in m[:, 1]], dtype=np.int64)
        columns.append((m[:, 0], np.full(len(m), r, np.int64), target, m[:, 2:4].reshape(-1, 2)))
    t_m, obs, target, z = (np.concatenate(c) for c in zip(*columns, strict=True))
    is_robot = target < N
    keep = (t_m > 0.0) & (t_m <= times[-1])
    if not config.landmarks:
        keep &= is_robot
    t_m, obs, target, z, is_robot = t_m[keep], obs[keep], target[keep], z[keep], is_robot[keep]
    step = np.maximum(np.searchsorted(times, t_m - 1e-9 * dt, side="left"), 1)
    order = np.lexsort((t_m, obs, is_robot, step))
    t_m, obs, target, z, is_robot, step = (a[order] for a in (t_m, obs, target, z, is_robot, step))

    z_clean = z.copy()
    attacked = np.zeros(len(z), dtype=bool)
    channel_ok = np.ones(len(z), dtype=bool)
    risk_s = np.zeros((K + 1, N))
    risk_c = np.zeros((K + 1, N))
    sdz = cdz = ZoneField([])
    if config.zones:
        auto_s, auto_c = default_zones(truth, valid)
        sdz = ZoneField([Zone(tuple(config.sdz[:2]), config.sdz[2]) if config.sdz else auto_s])
        cdz = ZoneField([Zone(tuple(config.cdz[:2]), config.cdz[2]) if config.cdz else auto_c])
        flat = truth[..., :2].reshape(-1, 2)
        risk_s = sdz.risk(flat).reshape(K + 1, N)
        risk_c = cdz.risk(flat).reshape(K + 1, N)
        # Risk of each measurement at the observer's true position at measurement time.
        p_obs = np.empty((len(z), 2))
        for r, log in enumerate(data.robots):
            sel = obs == r
            p_obs[sel] = ground_truth_at(log.groundtruth, t_m[sel], np.inf)[0][:, :2]
        ds, dc = sdz.risk(p_obs), cdz.risk(p_obs)
        attack_rng, channel_rng = (
            np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(2)
        )
        robot_rows = np.flatnonzero(is_robot)
        subj = data.robot_subjects
        can = attackable_links(
            subj[obs[robot_rows]],
            subj[target[robot_rows]],
            config.attack_links,
            config.link_fraction,
            config.seed,
        )
        draw = attack_rng.random(len(robot_rows))
        hit = robot_rows[can & (draw < ds[robot_rows])]
        gamma = injection(config.attack_kind, np.asarray(config.attack_bias), len(hit), attack_rng)
        attacked[hit] = True
        z[hit] = apply_injection(z[hit], gamma)
        draw_c = channel_rng.random(len(robot_rows))
        channel_ok[robot_rows] = draw_c >= dc[robot_rows]
    bounds = np.searchsorted(step, np.arange(K + 2), side="left")
    rows = (step, obs, target, is_robot, z, z_clean, attacked, channel_ok)
    return Replay(data, times, u, truth, valid, x0, *rows, risk_s, risk_c, sdz, cdz, bounds)
