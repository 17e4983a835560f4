"""The simulated world: T independent teams of N unicycle robots, advanced in one batch.

Robot ``b`` of the batch is robot ``b % N`` of trial ``b // N``. Each trial draws from its
own random streams (spawned from the seed by trial index), so trial ``t`` of a batched run
is identical to a run of that trial alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.backend import backend
from resloc.cl.graph import Lambda2Memo, component_lambda2
from resloc.models.measurement import range_bearing
from resloc.models.motion import unicycle_step
from resloc.world.attacks import AttackKind, apply_injection, attackable_links, injection
from resloc.world.control import LeaderPath, lattice_offsets, si_to_unicycle
from resloc.world.network import PAIRWISE_MAX, radius_links
from resloc.world.spec import ChannelRule, FormationFrame, WorldSpec, ZoneSpec
from resloc.world.zones import Zone, ZoneField

__all__ = ["World", "WorldStep", "compiled_world", "zone_field"]

_STREAMS = ("init", "odometry", "measurement", "attack", "channel")


def _stacked(draws: list[np.ndarray]) -> np.ndarray:
    """The trials' draws of one stream stacked along the first axis (one trial: its own
    array, no copy)."""
    return draws[0] if len(draws) == 1 else np.concatenate(draws)


def compiled_world(team_size: int):
    """The compiled twin of the world's step (:mod:`resloc.world.kernels`), or None for the
    numpy one: with the CL's compiled backend (:func:`resloc.cl.backend.backend`) and
    teams of at most :data:`~resloc.world.network.PAIRWISE_MAX` robots (every pair of a
    team is tested; larger teams take :func:`~resloc.world.network.radius_links`' cell
    lists or KD-tree). The kernels are loaded (or compiled) here, once per process."""
    if backend() != "numba" or team_size > PAIRWISE_MAX:
        return None
    from resloc.world import kernels  # loads numba: only for a compiled world

    kernels.warm_up()  # before the first step (a world process's first step is timed)
    return kernels


def zone_field(specs: tuple[ZoneSpec, ...]) -> ZoneField:
    """Build a :class:`ZoneField` from zone specs."""
    return ZoneField(
        [Zone(tuple(z.center), z.radius, z.peak, z.profile, z.tau) for z in specs]  # type: ignore[arg-type]
    )


@dataclass
class WorldStep:
    """What the world produced at step ``k`` (after moving from ``k-1`` to ``k``).

    Attributes
    ----------
    k : int
    pose : ndarray, shape (B, 3)
        True poses at step ``k``.
    u_meas : ndarray, shape (B, 2)
        Odometry measured over the move (true command plus noise).
    i, j : ndarray of int, shape (E,)
        Sensed directed links (batch indices), sorted by ``i`` then ``j``.
    z : ndarray, shape (E, 2)
        Range/bearing measurements, falsified where ``attacked``.
    attacked : ndarray of bool, shape (E,)
    channel_ok : ndarray of bool, shape (E,)
        A transmission on the link would get through (in comm range and not jammed).
    risk_s, risk_c : ndarray, shape (B,)
        ``Ds(i)``, ``Dc(i)`` at the true positions.
    lambda2 : ndarray, shape (B,)
        Algebraic connectivity of the communication graph seen by each robot.
    in_comm : ndarray of bool, shape (E,), optional
        The link is within radio range (``channel_ok`` before the CDZ's failures).
    """

    k: int
    pose: np.ndarray
    u_meas: np.ndarray
    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    attacked: np.ndarray
    channel_ok: np.ndarray
    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    in_comm: np.ndarray | None = None


class World:
    """Batched leader-follower world with sensing and communication danger zones.

    Parameters
    ----------
    spec : WorldSpec
    trials : int
        Independent teams simulated together.
    seed : int
    lambda2_mode : {"component", "global"}
        How each robot's ``lambda2`` is taken from the communication graph.
    first_trial : int
        Index of the first trial: trials ``first_trial .. first_trial + trials - 1`` of the
        seed are simulated (so seeds can be split across processes and re-run alone).
    """

    def __init__(
        self,
        spec: WorldSpec,
        trials: int = 1,
        seed: int = 0,
        lambda2_mode: str = "component",
        first_trial: int = 0,
    ) -> None:
        self.spec = spec
        self.trials = int(trials)
        self.seed = int(seed)
        self.lambda2_mode = lambda2_mode
        self.n = spec.team.robots
        self.B = self.trials * self.n
        self.team = np.repeat(np.arange(self.trials), self.n)
        self.rid = np.tile(np.arange(self.n), self.trials)
        self.dt = spec.motion.dt
        self.sdz = zone_field(spec.sdz)
        self.cdz = zone_field(spec.cdz)
        self.path = LeaderPath(spec.motion.waypoints)
        self.offsets = lattice_offsets(self.n - 1, spec.team.spacing, spec.team.leader_gap)
        # Trial t, stream s: SeedSequence(seed).spawn -> child t -> its child s. Deterministic
        # in (seed, t, s) and independent of how many trials are batched.
        trial_seqs = np.random.SeedSequence(self.seed).spawn(first_trial + self.trials)
        children = [c.spawn(len(_STREAMS)) for c in trial_seqs[first_trial:]]
        self._rng = {
            name: [np.random.default_rng(c[k]) for c in children] for k, name in enumerate(_STREAMS)
        }
        self.k = 0
        self.pose = self._initial_poses()
        self._l2_key: tuple | None = None
        self._l2: np.ndarray = np.zeros(self.B)
        self._odometry_std = np.asarray(spec.motion.odometry_std, float)
        self._measurement_std = np.array([spec.sensing.range_std, spec.sensing.bearing_std])
        self._replay = None
        if spec.attack.kind is AttackKind.REPLAY:
            # Imported here: the adversary module loads the compiled kernels (numba).
            from resloc.world.adversary import ReplayBuffer

            self._replay = ReplayBuffer(spec.attack.replay_delay, self.B)
        self._compiled = compiled_world(self.n)
        self._sdz_compiled = self._compiled and self._compiled.zone_arrays(self.sdz)
        self._cdz_compiled = self._compiled and self._compiled.zone_arrays(self.cdz)

    # ------------------------------------------------------------------ set-up
    def _desired(self, t: float) -> tuple[np.ndarray, float]:
        """Desired positions ``(N, 2)`` of one team at time ``t`` and the path heading."""
        p_leader, off, heading = self._leader_and_offsets(t)
        return np.vstack([p_leader[None, :], p_leader + off]), heading

    def _leader_and_offsets(self, t: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The leader's desired position ``(2,)`` at time ``t``, the followers' offsets
        from it ``(N - 1, 2)`` in the world frame, and the path heading."""
        p_leader, heading = self.path.at(self.spec.motion.leader_speed * t)
        off = self.offsets
        if self.spec.motion.formation is FormationFrame.LEADER:
            c, s = np.cos(heading), np.sin(heading)
            off = off @ np.array([[c, s], [-s, c]])
        return p_leader, off, heading

    def _initial_poses(self) -> np.ndarray:
        p, heading = self._desired(0.0)
        pose = np.zeros((self.B, 3))
        pose[:, :2] = np.tile(p, (self.trials, 1))
        pose[:, 2] = heading
        return pose

    def initial_estimates(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial estimates: truth plus seeded Gaussian error, and the matching covariance.

        Returns
        -------
        x0 : ndarray, shape (B, 3)
        P0 : ndarray, shape (B, 3, 3)
        """
        sp_, sh = self.spec.team.init_pos_std, self.spec.team.init_heading_std
        std = np.array([sp_, sp_, sh])
        err = np.vstack([g.normal(size=(self.n, 3)) for g in self._fresh("init")]) * std
        x0 = self.pose.copy() + err
        var = np.maximum(std**2, 1e-8)
        P0 = np.broadcast_to(np.diag(var), (self.B, 3, 3)).copy()
        return x0, P0

    def _fresh(self, stream: str) -> list[np.random.Generator]:
        return self._rng[stream]

    # ------------------------------------------------------------------ stepping
    def commands(self) -> np.ndarray:
        """True unicycle commands ``(B, 2)`` for the move from step ``k`` to ``k + 1``."""
        m = self.spec.motion
        t_next = (self.k + 1) * self.dt
        p_des, _ = self._desired(t_next)
        p_des = np.tile(p_des, (self.trials, 1))
        c, s = np.cos(self.pose[:, 2]), np.sin(self.pose[:, 2])
        ahead = self.pose[:, :2] + m.projection * np.stack([c, s], axis=1)
        v_si = m.gain * (p_des - ahead)
        speed = np.sqrt(np.add.reduce(v_si * v_si, axis=1, keepdims=True))  # = np.linalg.norm
        v_si *= np.minimum(1.0, m.v_max / np.maximum(speed, 1e-12))
        return si_to_unicycle(self.pose, v_si, m.projection, m.v_max, m.omega_max)

    def _move(self) -> np.ndarray:
        """Move every robot from step ``k`` to ``k + 1`` (``self.pose``); returns the true
        commands ``(B, 2)``."""
        if self._compiled is None:
            u = self.commands()
            self.pose = unicycle_step(self.pose, u, self.dt)
            return u
        m = self.spec.motion
        leader, offsets, _ = self._leader_and_offsets((self.k + 1) * self.dt)
        u, pose = np.empty((self.B, 2)), np.empty((self.B, 3))
        self._compiled.move_team(
            self.pose, leader, offsets, m.projection, m.gain, m.v_max, m.omega_max, self.dt, u, pose
        )
        self.pose = pose
        return u

    def _sense(self) -> tuple[np.ndarray, ...]:
        """The sensed links ``i, j`` of the current poses, their measurements ``z: (E, 2)``
        (noise drawn from each trial's stream), links per trial ``(T,)`` and which links
        are within radio range ``(E,)``."""
        sens = self.spec.sensing
        rngs = self._fresh("measurement")
        if self._compiled is None:
            p = self.pose[:, :2]
            i, j = radius_links(p, self.team, sens.radius)
            z = range_bearing(self.pose[i], self.pose[j])
            counts = np.bincount(self.team[i], minlength=self.trials)
            noise = _stacked([g.normal(size=(c, 2)) for g, c in zip(rngs, counts, strict=True)])
            z = z + noise.reshape(-1, 2) * self._measurement_std
            z[:, 0] = np.abs(z[:, 0])
            z[:, 1] = wrap_angle(z[:, 1])
            in_comm = np.hypot(*(p[i] - p[j]).T) <= sens.comm_radius
            return i, j, z, counts, in_comm
        found = self._compiled.team_links(
            self.pose, self.n, float(sens.radius), float(sens.comm_radius)
        )
        i, j, dx, dy, distance, in_comm, counts = found
        noise = _stacked([g.normal(size=(c, 2)) for g, c in zip(rngs, counts, strict=True)])
        angle = np.arctan2(dy, dx)  # numpy's: numba's libm atan2 differs in the last bit
        z = self._compiled.noisy_measurements(
            distance, angle, self.pose, i, noise.reshape(-1, 2), self._measurement_std
        )
        return i, j, z, counts, in_comm

    def _risk(self, field: ZoneField, compiled) -> np.ndarray:
        """``field``'s risk at the robots' true positions, ``(B,)``."""
        if not field:
            return np.zeros(self.B)
        if compiled is not None:
            return compiled.risk(self.pose[:, :2])
        return field.risk(self.pose[:, :2])

    def step(self) -> WorldStep:
        """Move every robot one ``dt``, then sense and draw attacks and channel outcomes."""
        att = self.spec.attack
        u = self._move()
        self.k += 1
        u_meas = u + _stacked([g.normal(size=(self.n, 2)) for g in self._fresh("odometry")]) * (
            self._odometry_std
        )
        i, j, z, counts, in_comm = self._sense()
        risk_s = self._risk(self.sdz, self._sdz_compiled)
        risk_c = self._risk(self.cdz, self._cdz_compiled)

        attacked = np.zeros(len(i), dtype=bool)
        att_rngs = self._fresh("attack")
        if self.sdz:
            u_att = _stacked([g.random(c) for g, c in zip(att_rngs, counts, strict=True)])
            can = attackable_links(
                self.rid[i], self.rid[j], att.links, att.link_fraction, self.seed
            )
            attacked = can & (u_att < risk_s[i])
            if att.kind is AttackKind.REPLAY:
                # The same link's honest measurement from replay_delay steps ago.
                found, z_old = self._replay.replayed(i, j)
                attacked &= found
                honest = z.copy()
                z[attacked] = z_old[attacked]
                self._replay.record(i, j, honest)
            elif att.kind is AttackKind.STEALTHY:
                pass  # injected per victim by the runner's LinkBatch.tamper (adversary.py)
            elif attacked.any():
                per_trial = np.bincount(self.team[i][attacked], minlength=self.trials)
                gamma = np.vstack(
                    [
                        injection(att.kind, np.asarray(att.bias), c, g)
                        for g, c in zip(att_rngs, per_trial, strict=True)
                    ]
                )
                z[attacked] = apply_injection(z[attacked], gamma)

        channel_ok = in_comm.copy()
        if self.cdz:
            u_ch = _stacked(
                [g.random(c) for g, c in zip(self._fresh("channel"), counts, strict=True)]
            )
            if att.channel is ChannelRule.EITHER:
                p_fail = 1.0 - (1.0 - risk_c[i]) * (1.0 - risk_c[j])
            else:
                p_fail = risk_c[i]
            channel_ok &= u_ch >= p_fail

        lambda2 = self._lambda2(i[in_comm], j[in_comm])
        return WorldStep(
            self.k,
            self.pose.copy(),
            u_meas,
            i,
            j,
            z,
            attacked,
            channel_ok,
            risk_s,
            risk_c,
            lambda2,
            in_comm,
        )

    def _lambda2(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Per-robot ``lambda2``, recomputed only when the communication graph changes, and
        then only for the large components that changed (a :class:`Lambda2Memo`)."""
        key = (len(i), hash(i.tobytes()), hash(j.tobytes()))
        if key != self._l2_key:
            memo = self.__dict__.setdefault("_l2_memo", Lambda2Memo())
            self._l2 = component_lambda2(
                i, j, self.B, self.lambda2_mode, group=self.team, memo=memo
            )
            self._l2_key = key
        return self._l2
