"""One robot's protocol state machine (``RobotAgent``) without a network: realtime age rules
for late and stale neighbour estimates, lost and late gauge acknowledgements, and that
nothing a robot did not verify reaches its filter."""

from __future__ import annotations

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.runtime.messages import FLAG_FUSED, FLAG_HEARD, Codec, Kind, Message
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.robot import RobotAgent
from resloc.runtime.team import team_setup

KEY = bytes(range(32))


class RecordingBus:
    """Stands in for the Zenoh bus: keeps what the agent publishes."""

    root = "resloc/team"

    def __init__(self) -> None:
        self.sent: list[tuple[str, Kind, int, dict]] = []

    def key(self, *parts) -> str:
        return "/".join([self.root, *(str(p) for p in parts)])

    def declare(self, key) -> None:
        pass

    def send(self, key, kind, step, body, sender=None) -> bytes:
        self.sent.append((key, kind, step, body))
        return b""


def agent_for(tmp_path, mode: Mode, fusion: str = "naive", max_age: int = 2) -> RobotAgent:
    sc = default_scenario().replace(
        **{"team.robots": 4, "estimator.fusion": fusion, "estimator.gauge_sums": "consensus"}
    )
    path = tmp_path / "sc.toml"
    path.write_text(dump_scenario(sc))
    opts = SwarmOptions(scenario=str(path), filter="ekf", mode=mode, max_age_steps=max_age)
    agent = RobotAgent(0, team_setup(opts), opts, RecordingBus(), KEY)
    agent.on_start(
        msg(
            Kind.START,
            0,
            {
                "robot": 0,
                "x": np.zeros(3),
                "P": np.eye(3) * 0.01,
                "rejoin": False,
                "rt": mode is Mode.REALTIME,
            },
        )
    )
    return agent


def msg(kind: Kind, step: int, body: dict, sender: int = 0xFFF0) -> Message:
    return Message(kind, sender, 1, step, 0.0, step, body, b"")


def sensors(step: int, neighbours: list[int]) -> Message:
    z = np.array([[np.hypot(1.0 * j, 0.5), np.arctan2(0.5, 1.0 * j)] for j in neighbours])
    return msg(
        Kind.SENSORS,
        step,
        {
            "u": np.array([0.1, 0.0]),
            "l2": 1.0,
            "rs": 0.0,
            "rc": 0.0,
            "j": np.asarray(neighbours, np.int64),
            "z": z.reshape(-1, 2),
        },
    )


def estimate(sender: int, step: int) -> Message:
    return msg(
        Kind.ESTIMATE,
        step,
        {"x": np.array([1.0 * sender, 0.5, 0.0]), "P": np.eye(3) * 0.01},
        sender=sender,
    )


def test_realtime_uses_late_estimates_while_fresh_and_drops_stale_ones(tmp_path) -> None:
    agent = agent_for(tmp_path, Mode.REALTIME, max_age=2)
    agent.take(estimate(1, 1))  # will be 4 steps old: stale
    agent.take(estimate(2, 3))  # 2 steps old: late but fresh enough
    agent.on_sensors(sensors(5, [1, 2, 3]))
    agent.take(estimate(3, 5))  # current
    assert agent.phase == (Kind.ESTIMATE, 0)
    agent.tick(agent.deadline + 1.0)  # the window closes
    assert agent.phase is None
    report = agent.bus.sent[-1]
    assert report[1] is Kind.REPORT and report[2] == 5
    flags = report[3]["flags"]
    heard = (flags & FLAG_HEARD) > 0
    np.testing.assert_array_equal(heard, [False, True, True])
    assert not (flags[0] & FLAG_FUSED)  # a stale estimate never reaches the filter
    c = report[3]["cnt"]
    assert c["estimates_stale_dropped"] == 1 and c["estimates_late_used"] == 1
    assert c["unheard"] == 1


def test_realtime_goes_on_early_when_every_current_estimate_arrived(tmp_path) -> None:
    agent = agent_for(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(1, [1, 2]))
    codec = Codec(KEY, 1)
    frames = [
        codec.encode(
            Kind.ESTIMATE,
            1,
            {"x": np.array([1.0, 0.5, 0.0]), "P": np.eye(3) * 0.01},
            "resloc/team/radio/in",
            sender=s,
        )
        for s in (1, 2)
    ]
    delivery = msg(
        Kind.DELIVERY,
        1,
        {"to": 0, "phase": int(Kind.ESTIMATE), "round": 0, "nb": np.array([1, 2]), "msgs": frames},
        sender=0xFFF1,
    )
    agent.on_delivery(delivery)
    assert agent.phase is None and agent.bus.sent[-1][1] is Kind.REPORT
    # the same frames again (a replay through the radio) are rejected by the robot itself
    agent.on_sensors(sensors(2, [1, 2]))
    agent.on_delivery(delivery)
    assert agent.counts["rejected_inner"] == 2
    assert agent.inner.counts()["replayed"] == 2


def test_lockstep_uses_this_steps_estimates_only(tmp_path) -> None:
    agent = agent_for(tmp_path, Mode.LOCKSTEP)
    agent.take(estimate(1, 1))
    agent.on_sensors(sensors(2, [1]))
    agent.advance()  # the radio's delivery of the phase (empty for robot 0)
    flags = agent.bus.sent[-1][3]["flags"]
    assert flags[0] == 0  # the simulator would not use last step's estimate either


def test_lost_acknowledgement_closes_the_step_without_it_and_late_ones_are_counted(
    tmp_path,
) -> None:
    """Gauge fusion: acknowledgements that do not arrive before the step closes are simply
    missing from the receiver's leak (docs/runtime.md); one arriving afterwards is counted
    and dropped; the estimate is the same either way."""
    estimates = []
    for lost in (False, True):
        agent = agent_for(tmp_path, Mode.REALTIME, fusion="gauge")
        agent.on_sensors(sensors(1, [1]))
        agent.take(estimate(1, 1))
        agent.tick(agent.deadline + 1.0)  # correct, send the step's ACK
        assert agent.phase == (Kind.ACK, 0)
        ack = msg(Kind.ACK, 1, {"to": np.array([0]), "ack": np.eye(3)[None] * 0.1}, sender=1)
        if not lost:
            agent.take(ack)
        agent.tick(agent.deadline + 1.0)  # close with what arrived
        assert agent.counts["acks_received"] == (0 if lost else 1)
        if lost:
            agent.take(ack)  # too late: the step is closed
            assert agent.counts["acks_late"] == 1
        estimates.append((agent.node.x.copy(), agent.node.gauge.C_hat.copy()))
    np.testing.assert_array_equal(estimates[0][0], estimates[1][0])
    assert not np.allclose(estimates[0][1], estimates[1][1])  # G misses the lost share


def test_a_lagging_robot_uses_the_estimate_of_its_own_step(tmp_path) -> None:
    """A neighbour that is a step ahead must not push out the estimate of the step this
    robot is closing (nor count as stale)."""
    agent = agent_for(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(5, [1]))
    agent.take(estimate(1, 5))
    ahead = estimate(1, 6)
    ahead.body["x"] = np.array([50.0, 0.5, 0.0])  # would wreck the update if used
    agent.take(ahead)
    agent.tick(agent.deadline + 1.0)
    report = agent.bus.sent[-1][3]
    assert report["flags"][0] & FLAG_HEARD
    assert report["cnt"].get("estimates_stale_dropped", 0) == 0
    assert report["cnt"].get("estimates_late_used", 0) == 0
    assert abs(report["x"][0]) < 5.0
