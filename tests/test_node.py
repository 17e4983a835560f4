"""Robot-by-robot equivalence (issue 4): a team of :class:`RobotNode` objects, each running
``predict``/``correct`` with batch size 1 on its own links, gives the batched engine's
estimates and decisions (to 1e-9) on a seeded scenario, for the CKF, the UKF and the EKF,
with the compiled kernels and with the numpy reference path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world
from resloc.cl import LinkBatch, LinkMemory, ThresholdInnovation, correct, kernels, predict
from resloc.cl.fusion import FusionMethod
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.node import RobotNode
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.filters.base import make_filter
from resloc.world.world import World

TOL = 1e-9
FLAGS = ("detected", "triggered", "delivered", "fused")
BACKENDS = [
    pytest.param(
        "numba",
        marks=pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed"),
    ),
    "numpy",
]


def hot_scenario(steps: int):
    """The default scenario with its sensing and communication danger zones moved onto the
    team's start, so attacks, detections, triggers and channel failures all occur from the
    first steps."""
    sc = default_scenario()
    start = World(sc.world).pose[:, :2].mean(axis=0)
    cx, cy = (float(v) for v in start)
    return sc.replace(
        **{
            "run.steps": steps,
            "sdz": [{"center": [cx - 0.3, cy], "radius": 0.6}],
            "cdz": [{"center": [cx + 0.3, cy], "radius": 0.6}],
        }
    )


def simulate(scenario, trials: int, seed: int):
    world = default_world(trials, seed, scenario=scenario)
    x0, P0 = world.initial_estimates()
    return world, x0, P0, [world.step() for _ in range(scenario.run.steps)]


def run_batched(filt, params, world, x0, P0, steps):
    """The engine, as the runner drives it: every robot of every trial in one batch."""
    x, P = x0.copy(), P0.copy()
    memory = LinkMemory(world.B)
    history = []
    for ws in steps:
        xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
        links = LinkBatch(
            ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
        )
        x, P, out = correct(filt, xp, Pp, links, params, memory)
        history.append((x.copy(), P.copy(), out))
    return history


def correct_nodes(nodes, ws):
    """Every node corrects from its own links and its neighbours' predicted estimates (and
    their independent parts, with split covariance intersection)."""
    sent = [node.estimate for node in nodes]
    independent = [node.independent for node in nodes]
    factorized = nodes[0].params.fusion is FusionMethod.FACTORIZED
    outs = []
    for b, node in enumerate(nodes):
        rows = np.flatnonzero(ws.i == b)
        nb = ws.j[rows]
        outs.append(
            node.correct(
                nb,
                ws.z[rows],
                np.array([sent[j][0] for j in nb]).reshape(-1, 3),
                np.array([sent[j][1] for j in nb]).reshape(-1, 3, 3),
                ws.channel_ok[rows],
                ws.risk_s[b],
                ws.risk_c[b],
                ws.lambda2[b],
                P_nb_ind=None
                if independent[0] is None
                else np.array([independent[j] for j in nb]).reshape(-1, 3, 3),
                factor_nb=np.array([nodes[j].factor_for(b) for j in nb]) if factorized else None,
            )
        )
    return outs


def run_nodes(filt, params, world, x0, P0, steps):
    """One RobotNode per robot; each gets only its own links and its neighbours' predicted
    estimates (what their transmissions carry)."""
    nodes = [RobotNode(b, filt, params, x0[b], P0[b], n_ids=world.B) for b in range(world.B)]
    history = []
    for ws in steps:
        for node, u in zip(nodes, ws.u_meas, strict=True):
            node.predict(u, world.dt)
        outs = correct_nodes(nodes, ws)
        x = np.concatenate([node.x for node in nodes])
        P = np.concatenate([node.P for node in nodes])
        history.append((x, P, outs))
    return history


def assert_same(batched, by_robot, ws_list, compiled: bool) -> int:
    """Compare step by step; returns the number of fused links (to check coverage).
    ``compiled``: which path must have computed every non-empty correction."""
    fused = 0
    for k, ((xb, Pb, ob), (xn, Pn, outs), ws) in enumerate(
        zip(batched, by_robot, ws_list, strict=True)
    ):
        dx = np.abs(xb - xn)
        dx[:, 2] = np.abs((dx[:, 2] + np.pi) % (2 * np.pi) - np.pi)
        assert dx.max() <= TOL, f"estimates differ by {dx.max():.3e} at step {k}"
        assert np.abs(Pb - Pn).max() <= TOL, f"covariances differ at step {k}"
        for b, out in enumerate(outs):
            rows = np.flatnonzero(ws.i == b)
            for name in FLAGS:
                np.testing.assert_array_equal(getattr(out, name), getattr(ob, name)[rows])
            np.testing.assert_allclose(out.norm, ob.norm[rows], rtol=0, atol=TOL)
        assert sum(o.repairs for o in outs) == ob.repairs
        assert all(o.compiled is compiled for o in (ob, *outs) if len(o.norm)), k
        fused += int(ob.fused.sum())
    return fused


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["ckf", "ukf", "ekf"])
def test_robot_nodes_reproduce_the_batched_engine(kind: str, backend: str) -> None:
    steps = 40 if backend == "numba" else 12
    scenario = hot_scenario(steps)
    params = scenario.cl_params()
    world, x0, P0, ws_list = simulate(scenario, trials=2, seed=3)
    filt = make_filter(kind)
    with kernels.use_backend(backend):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
    fused = assert_same(batched, by_robot, ws_list, compiled=backend == "numba")
    # The scenario exercises every branch: attacks detected, triggers, channel failures.
    outs = [h[2] for h in batched]
    assert sum(int(o.detected.sum()) for o in outs) > 0
    assert sum(int((o.triggered & ~o.delivered).sum()) for o in outs) > 0
    assert 0 < fused < sum(len(o.norm) for o in outs)


@pytest.mark.parametrize("backend", BACKENDS)
def test_robot_nodes_with_last_sent_threshold_and_nis_norm(backend: str) -> None:
    """Per-link memory (``last_sent``) lives in each node and gives the same decisions."""
    scenario = hot_scenario(12)
    params = replace(
        scenario.cl_params(),
        threshold_innovation=ThresholdInnovation.LAST_SENT,
        trigger_norm="nis",
        rho=8.0,
        detector_norm="nis",
        alpha=2.0,
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=5)
    filt = make_filter("ckf")
    with kernels.use_backend(backend):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
    assert assert_same(batched, by_robot, ws_list, compiled=backend == "numba") > 0


def test_node_sorts_its_links_and_returns_outcomes_in_given_order() -> None:
    filt = make_filter("ekf")
    params = replace(default_scenario().cl_params(), trigger=False)
    x0 = np.array([0.0, 0.0, 0.2])
    P0 = np.diag([0.01, 0.01, 0.005])
    nb = np.array([[1.0, 0.2, 0.0], [0.1, 1.2, 1.0], [-0.8, 0.3, 2.0]])
    Pn = np.broadcast_to(np.diag([0.02, 0.02, 0.01]), (3, 3, 3)).copy()
    z = np.array([[1.02, 0.0], [1.2, 1.3], [0.85, 2.6]])
    ids = np.array([7, 2, 5])
    a = RobotNode(0, filt, params, x0, P0)
    out_a = a.correct(ids, z, nb, Pn, np.ones(3, bool), 0.0, 0.0, 1.0)
    order = np.argsort(ids)
    b = RobotNode(0, filt, params, x0, P0)
    out_b = b.correct(ids[order], z[order], nb[order], Pn[order], np.ones(3, bool), 0.0, 0.0, 1.0)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    np.testing.assert_array_equal(out_a.norm[order], out_b.norm)
    np.testing.assert_array_equal(out_a.fused[order], out_b.fused)
    x, P = a.estimate
    assert x.shape == (3,) and P.shape == (3, 3)


def _comm_edges(scenario, ws):
    p = ws.pose[:, :2]
    ok = (np.hypot(*(p[ws.i] - p[ws.j]).T) <= scenario.world.sensing.comm_radius) & ws.channel_ok
    return ws.i[ok], ws.j[ok]


def test_robot_nodes_run_gauge_fusion_with_acks_and_consensus() -> None:
    """Gauge fusion robot by robot: each node sends its acknowledgements and runs the
    consensus rounds itself; estimates, covariances and every robot's own G equal the
    batched bookkeeping with the same exchanges (to 1e-9)."""
    from resloc.cl.gauge import GaugeCovariance
    from resloc.models.motion import process_noise

    rounds = 2
    scenario = hot_scenario(15).replace(**{"estimator.fusion": "gauge"})
    params = scenario.cl_params()
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=5)
    filt = make_filter("ekf")
    N = world.n
    # batched
    x, P = x0.copy(), P0.copy()
    memory = LinkMemory(world.B)
    memory.joint = GaugeCovariance(x0, P0, N, rounds=rounds)
    hist_b = []
    for ws in ws_list:
        xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
        Q = process_noise(
            x, world.dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std)
        )
        Pp = memory.joint.predict(x, ws.u_meas, world.dt, Q, Pp)
        links = LinkBatch(
            ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
        )
        x, P, _ = correct(filt, xp, Pp, links, params, memory)
        memory.joint.exchange(*_comm_edges(scenario, ws))
        hist_b.append((x.copy(), memory.joint.reported(x, P)))
    # robot by robot
    nodes = [
        RobotNode(b, filt, params, x0[b], P0[b], n_ids=world.B, team_size=N) for b in range(world.B)
    ]
    with pytest.raises(ValueError, match="team_size"):
        RobotNode(0, filt, params, x0[0], P0[0])
    for k, ws in enumerate(ws_list):
        for node, u in zip(nodes, ws.u_meas, strict=True):
            node.predict(u, world.dt)
        correct_nodes(nodes, ws)
        inbox: list[list[np.ndarray]] = [[] for _ in nodes]
        for node in nodes:
            for j, ack in node.gauge_acks():
                inbox[j].append(ack)
        for node, acks in zip(nodes, inbox, strict=True):
            node.gauge_close(acks)
        ei, ej = _comm_edges(scenario, ws)
        nbrs = [set() for _ in nodes]
        for a, c in zip(ei, ej, strict=True):
            if a != c:
                nbrs[a].add(int(c))
                nbrs[c].add(int(a))
        for _ in range(rounds):
            msgs = [node.gauge_message() for node in nodes]
            for b, node in enumerate(nodes):
                nb = sorted(nbrs[b])
                node.gauge_mix([msgs[j] for j in nb], [len(nbrs[j]) for j in nb])
        xb, Pb = hist_b[k]
        xn = np.concatenate([node.x for node in nodes])
        Pn = np.stack([node.covariance for node in nodes])
        assert np.abs(xb - xn).max() <= TOL, k
        assert np.abs(Pb - Pn).max() <= TOL, k
    assert sum(len(node.gauge_acks()) for node in nodes) > 0


def test_robot_nodes_run_split_ci_with_delivery_acknowledgements() -> None:
    """Split CI robot by robot: transmissions carry the independent parts, and a robot whose
    estimate was fused learns it from an acknowledgement; equal to the batched engine."""
    scenario = hot_scenario(12).replace(**{"estimator.fusion": "split_ci"})
    params = scenario.cl_params()
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=6)
    filt = make_filter("ukf")
    fusion = fusion_strategy("split_ci")
    x, P = x0.copy(), P0.copy()
    memory = LinkMemory(world.B)
    fusion.init(memory, x0, P0, world.n)
    nodes = [RobotNode(b, filt, params, x0[b], P0[b], n_ids=world.B) for b in range(world.B)]
    acks = 0
    for k, ws in enumerate(ws_list):
        xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
        Pp = fusion.predict(memory, x, ws.u_meas, world.dt, params, Pp)
        links = LinkBatch(
            ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c,
            ws.lambda2, **fusion.link_fields(memory, ws.j),
        )  # fmt: skip
        x, P, _ = correct(filt, xp, Pp, links, params, memory)
        for node, u in zip(nodes, ws.u_meas, strict=True):
            node.predict(u, world.dt)
        correct_nodes(nodes, ws)
        received = np.zeros(len(nodes), dtype=int)
        for node in nodes:
            for j in node.delivery_acks():
                received[j] += 1
        for node, n in zip(nodes, received, strict=True):
            node.delivery_close(int(n))
        acks += int(received.sum())
        assert np.abs(x - np.concatenate([n.x for n in nodes])).max() <= TOL, k
        assert np.abs(P - np.concatenate([n.P for n in nodes])).max() <= TOL, k
        assert np.abs(memory.independent - np.stack([n.independent for n in nodes])).max() <= TOL
    assert acks > 0


def test_robot_nodes_run_factorized_fusion_with_pair_exchanges() -> None:
    """Luft et al.'s factors robot by robot: transmissions carry the factor kept for the
    receiver, and every pair that fused exchanges one message at the end of the step; the
    estimates, covariances and every robot's factors equal the batched bookkeeping."""
    scenario = hot_scenario(12).replace(**{"estimator.fusion": "factorized"})
    params = scenario.cl_params()
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=7)
    filt = make_filter("ckf")
    fusion = fusion_strategy("factorized")
    x, P = x0.copy(), P0.copy()
    memory = LinkMemory(world.B)
    fusion.init(memory, x0, P0, world.n)
    nodes = [
        RobotNode(b, filt, params, x0[b], P0[b], n_ids=world.B, team_size=world.n)
        for b in range(world.B)
    ]
    exchanged = 0
    for k, ws in enumerate(ws_list):
        xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
        Pp = fusion.predict(memory, x, ws.u_meas, world.dt, params, Pp)
        links = LinkBatch(
            ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
        )
        x, P, _ = correct(filt, xp, Pp, links, params, memory)
        for node, u in zip(nodes, ws.u_meas, strict=True):
            node.predict(u, world.dt)
        correct_nodes(nodes, ws)
        partners = [set(node.delivery_acks()) for node in nodes]
        for node in nodes:
            for j in node.delivery_acks():
                partners[j].add(node.robot_id)
        inbox = [{p: nodes[p].factor_message(b) for p in partners[b]} for b in range(len(nodes))]
        for node, messages in zip(nodes, inbox, strict=True):
            node.factor_close(messages)
        exchanged += sum(len(p) for p in partners)
        assert np.abs(x - np.concatenate([n.x for n in nodes])).max() <= TOL, k
        assert np.abs(P - np.concatenate([n.P for n in nodes])).max() <= TOL, k
        factors = np.concatenate([n.memory.joint.sig for n in nodes])
        assert np.abs(memory.joint.sig - factors).max() <= TOL, k
    assert exchanged > 0


def test_robot_nodes_run_ci_fusion_like_the_batched_engine() -> None:
    scenario = hot_scenario(12).replace(**{"estimator.fusion": "ci"})
    params = scenario.cl_params()
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=4)
    filt = make_filter("ckf")
    batched = run_batched(filt, params, world, x0, P0, ws_list)
    by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
    # CI runs in the compiled kernel (kernels_fusion) wherever numba is installed.
    assert assert_same(batched, by_robot, ws_list, compiled=kernels.backend() == "numba") > 0


@pytest.mark.parametrize("method", list(FusionMethod))
def test_robot_node_runs_every_decentralizable_method_and_says_why_not(method) -> None:
    """The node's verdict is the strategy's: it runs a method or refuses it with the
    strategy's reason, one line."""
    params = replace(default_scenario().cl_params(), fusion=method)
    refusal = fusion_strategy(method).node_refusal
    make = lambda: RobotNode(0, make_filter("ekf"), params, np.zeros(3), np.eye(3), team_size=3)  # noqa: E731
    if refusal is None:
        node = make()
        node.predict(np.array([0.1, 0.0]), 0.1)
        assert node.covariance.shape == (3, 3)
        return
    with pytest.raises(ConfigError) as info:
        make()
    assert refusal in str(info.value) and method.value in str(info.value)
    assert "\n" not in str(info.value)


def test_every_method_but_the_centralized_tracked_runs_in_a_node() -> None:
    refused = {m for m in FusionMethod if fusion_strategy(m).node_refusal is not None}
    assert refused == {FusionMethod.TRACKED}


def test_split_ci_node_without_transmitted_independent_parts_says_what_is_missing() -> None:
    params = replace(default_scenario().cl_params(), fusion="split_ci", trigger=False)
    node = RobotNode(0, make_filter("ekf"), params, np.zeros(3), 0.01 * np.eye(3))
    assert node.independent.shape == (3, 3)
    with pytest.raises(ValueError, match="P_nb_ind"):
        node.correct(
            [1], [[1.0, 0.0]], [[1.0, 0.0, 0.0]], [0.01 * np.eye(3)], [True], 0.0, 0.0, 1.0
        )
