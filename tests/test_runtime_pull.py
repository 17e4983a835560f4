"""Pulled estimates (``estimator.neighbour_estimate = "cached"``): the runtime sends an
estimate only when a trigger fires (REQUEST on the link, REPLY with the estimate), and a
lockstep run equals the in-process simulator's cached semantics to 1e-9. Real processes and
Zenoh sessions on 127.0.0.1, stopped by pid by the supervisor."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.experiments.runner import run_scenario
from resloc.runtime.messages import FLAG_DELIVERED, FLAG_FUSED, FLAG_HEARD, FLAG_TRIGGERED, Kind
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.robot import RobotAgent
from resloc.runtime.swarm import run_swarm
from resloc.runtime.team import team_setup
from resloc.runtime.transport import free_endpoint
from test_runtime_robot import KEY, RecordingBus, msg, sensors
from test_runtime_swarm import TOL, hot_scenario, load_outputs, swarm_options

STEPS = 30


def cached_scenario(filt: str, **changes):
    return hot_scenario(
        STEPS, **{"run.filters": [filt], "estimator.neighbour_estimate": "cached", **changes}
    )


@pytest.mark.parametrize(
    ("filt", "per_process", "changes"),
    [
        ("ckf", 1, {}),
        ("ukf", 5, {"estimator.update_without_transmission": True}),
        ("ekf", 2, {"estimator.fusion": "ci"}),
        ("ckf", 5, {"estimator.update_mode": "summed"}),
        ("ekf", 5, {"trigger.risk_source": "estimated"}),
    ],
)
def test_lockstep_pull_equals_the_simulator(tmp_path, filt, per_process, changes) -> None:
    sc = cached_scenario(filt, **changes)
    opts = swarm_options(tmp_path, sc, filt)
    result = run_swarm(opts, [free_endpoint()], per_process, log_dir=tmp_path / "logs")
    assert result.end == "complete"
    runtime, summary, est = load_outputs(Path(opts.out))
    sim = run_scenario(sc)
    dx = np.abs(est["x"] - sim.estimators[filt].track)
    dx[..., 2] = np.abs((dx[..., 2] + np.pi) % (2 * np.pi) - np.pi)
    assert dx.max() <= TOL, f"estimates differ by {dx.max():.2e}"
    mine, theirs = summary["estimators"][filt], sim.summary()[filt]
    np.testing.assert_allclose(mine["msle_mean"], theirs["msle_mean"], rtol=TOL)
    assert mine["delivered"] == theirs["delivered"] > 0
    wire = runtime["wire_by_kind"]
    assert runtime["estimates"] == "pulled on trigger"
    assert wire["estimate"]["messages"] == 0  # nothing is broadcast
    # Every delivered transmission is one reply copy; a reply is sent only on request.
    # A delivered transmission is one reply copy; the others answered links never heard from
    # before, which the detector then discarded.
    counters = runtime["robot_counters"]
    assert wire["reply"]["copies_delivered"] == mine["delivered"] + counters["replies_unused"]
    assert 0 < wire["reply"]["messages"] <= wire["request"]["messages"] < 5 * STEPS * 4
    assert wire["request"]["copies_lost"] > 0  # the CDZ jammed some exchanges
    assert runtime["robot_counters"]["unheard"] == wire["request"]["copies_lost"]
    # One request copy per requested link: each triggered link, plus the links never heard
    # from before (asked unconditionally; discarded or unanswered ones are not triggered).
    sent = counters["requests_sent"]
    assert wire["request"]["copies_delivered"] + wire["request"]["copies_lost"] == sent
    assert (
        mine["transmissions"]
        <= sent
        <= (mine["transmissions"] + counters["replies_unused"] + counters["unheard"])
    )
    assert mine["transmissions"] <= theirs["transmissions"]
    assert all(code == 0 for code in result.exit_codes.values()), result.exit_codes


# ---------------------------------------------------------------- one robot, no network
def pulling_agent(tmp_path, mode: Mode, trigger: bool = True) -> RobotAgent:
    sc = default_scenario().replace(
        **{
            "team.robots": 4,
            "estimator.neighbour_estimate": "cached",
            "trigger.enabled": trigger,
        }
    )
    path = tmp_path / "sc.toml"
    path.write_text(dump_scenario(sc))
    opts = SwarmOptions(scenario=str(path), filter="ekf", mode=mode)
    agent = RobotAgent(0, team_setup(opts), opts, RecordingBus(), KEY)
    start = {"robot": 0, "x": np.zeros(3), "P": np.eye(3) * 0.01, "rejoin": False}
    agent.on_start(msg(Kind.START, 0, start | {"rt": mode is Mode.REALTIME}))
    return agent


def reply(sender: int, step: int, rnd: int, to: list[int], x0: float | None = None):
    x = np.array([1.0 * sender if x0 is None else x0, 0.5, 0.0])
    body = {"round": rnd, "to": np.asarray(to, np.int64), "x": x, "P": np.eye(3) * 0.01}
    return msg(Kind.REPLY, step, body, sender=sender)


def sent(agent: RobotAgent, kind: Kind) -> list:
    return [s for s in agent.bus.sent if s[1] is kind]


def test_realtime_unanswered_request_is_counted_and_its_link_skipped(tmp_path) -> None:
    """A request unanswered within ``reply_window * dt`` is counted and its link skipped;
    a reply arriving after the round closed is counted and never reaches the filter."""
    agent = pulling_agent(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(1, [1, 2]))
    (req,) = sent(agent, Kind.REQUEST)
    np.testing.assert_array_equal(req[3]["to"], [1, 2])  # never heard from: asked at once
    assert agent.phase == (Kind.REPLY, 0)
    expected = agent.deadline - agent.options.reply_window * agent.team.dt
    assert abs(expected - time.monotonic()) < 1.0
    agent.take(reply(1, 1, 0, [0]))
    agent.tick(agent.deadline + 1e-3)  # robot 2 never answers
    report = sent(agent, Kind.REPORT)[-1][3]
    flags = report["flags"]
    assert flags[0] & FLAG_HEARD and flags[0] & FLAG_DELIVERED and flags[0] & FLAG_FUSED
    assert flags[1] == 0  # skipped: nothing to evaluate it with
    assert report["cnt"]["requests_unanswered"] == 1
    x = agent.node.x.copy()
    agent.take(reply(2, 1, 0, [0], x0=50.0))  # too late
    assert agent.counts["replies_late"] == 1
    np.testing.assert_array_equal(agent.node.x, x)


def test_realtime_triggered_cached_link_without_reply_is_triggered_not_delivered(
    tmp_path,
) -> None:
    agent = pulling_agent(tmp_path, Mode.REALTIME, trigger=False)  # every link fires
    agent.on_sensors(sensors(1, [1]))
    agent.take(reply(1, 1, 0, [0]))
    assert agent.phase is None or agent.phase == (Kind.REPLY, 0)
    if agent.phase is not None:
        agent.tick(agent.deadline + 1e-3)
    assert sent(agent, Kind.REPORT)[-1][3]["flags"][0] & FLAG_DELIVERED
    agent.on_sensors(sensors(2, [1]))  # cached now: decided locally, then requested
    (_, req) = sent(agent, Kind.REQUEST)
    np.testing.assert_array_equal(req[3]["to"], [1])
    predicted = agent.node.x.copy()
    agent.tick(agent.deadline + 1e-3)
    report = sent(agent, Kind.REPORT)[-1][3]
    assert report["flags"][0] == FLAG_HEARD | FLAG_TRIGGERED  # attempted, lost, not fused
    assert report["cnt"]["requests_unanswered"] == 1
    np.testing.assert_array_equal(agent.node.x, predicted)  # rolled back, nothing fused


def test_requests_are_answered_with_the_predicted_estimate_of_their_step(tmp_path) -> None:
    agent = pulling_agent(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(3, []))  # no links: nothing to request, reports at once
    assert not sent(agent, Kind.REQUEST) and sent(agent, Kind.REPORT)
    x3, P3 = agent.node.x[0].copy(), agent.node.P[0].copy()
    request = {"round": 0, "to": np.array([0], np.int64)}
    agent.answer([msg(Kind.REQUEST, 3, request, sender=2), msg(Kind.REQUEST, 3, request, 1)])
    agent.answer([msg(Kind.REQUEST, 4, request, sender=1)])  # a step ahead: waits
    (r3,) = sent(agent, Kind.REPLY)
    assert r3[2] == 3
    np.testing.assert_array_equal(r3[3]["to"], [1, 2])  # one frame for both requesters
    np.testing.assert_array_equal(r3[3]["x"], x3)
    np.testing.assert_array_equal(r3[3]["P"], P3)
    agent.on_sensors(sensors(4, []))
    r4 = sent(agent, Kind.REPLY)[-1]
    assert r4[2] == 4 and list(r4[3]["to"]) == [1]
    np.testing.assert_array_equal(r4[3]["x"], agent.snapshots[4][0])
    agent.answer([msg(Kind.REQUEST, 0, request, sender=1)])  # no longer kept
    assert agent.counts["requests_too_old"] == 1


@pytest.mark.parametrize("mode", [Mode.LOCKSTEP, Mode.REALTIME])
def test_one_request_round_per_triggered_link_in_lockstep_one_per_step_in_realtime(
    tmp_path, mode
) -> None:
    """Lockstep is the simulator's sequential correction: a link's trigger is decided after
    the fusions before it, so each triggered link costs a round trip. Realtime asks once per
    step, deciding every link on the predicted estimate."""
    agent = pulling_agent(tmp_path, mode, trigger=False)  # every accepted link fires
    agent.on_sensors(sensors(1, [1, 2]))
    agent.take(reply(1, 1, 0, [0]))
    agent.take(reply(2, 1, 0, [0]))
    if agent.phase is not None:
        agent.advance()
    assert sent(agent, Kind.REPORT)[-1][3]["flags"][1] & FLAG_DELIVERED
    before = len(sent(agent, Kind.REQUEST))
    agent.on_sensors(sensors(2, [1, 2]))  # both cached now
    asked = [list(r[3]["to"]) for r in sent(agent, Kind.REQUEST)[before:]]
    assert asked == ([[1]] if mode is Mode.LOCKSTEP else [[1, 2]])
    agent.take(reply(1, 2, 0, [0]))
    agent.take(reply(2, 2, 0, [0]))  # lockstep: not asked yet in round 0, so not taken
    agent.advance()
    if mode is Mode.LOCKSTEP:
        assert list(sent(agent, Kind.REQUEST)[-1][3]["to"]) == [2]  # round 1
        agent.take(reply(2, 2, 1, [0]))
        agent.advance()
        assert list(sent(agent, Kind.REQUEST)[-1][3]["to"]) == []  # done: the barrier
    flags = sent(agent, Kind.REPORT)[-1][3]["flags"]
    assert all(f & FLAG_DELIVERED and f & FLAG_FUSED for f in flags)


def test_a_late_reply_from_a_never_heard_neighbour_is_cached_never_fused(tmp_path) -> None:
    """The late reply is the last estimate of j that i received: the next step decides that
    link locally instead of asking again; the closed step is not changed by it."""
    agent = pulling_agent(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(1, [1]))
    agent.tick(agent.deadline + 1e-3)  # unanswered
    x = agent.node.x.copy()
    agent.take(reply(1, 1, 0, [0]))
    np.testing.assert_array_equal(agent.node.x, x)
    assert agent.counts["replies_late"] == 1 and agent.counts["late_replies_cached"] == 1
    agent.take(reply(1, 1, 0, [0], x0=50.0))  # a known link's cache is never replaced
    assert agent.counts["late_replies_cached"] == 1
    np.testing.assert_array_equal(agent.node.memory.x[0], [1.0, 0.5, 0.0])
    before = len(sent(agent, Kind.REQUEST))
    agent.on_sensors(sensors(2, [1]))
    flags = sent(agent, Kind.REPORT)[-1][3]["flags"]
    if len(sent(agent, Kind.REQUEST)) == before:  # decided locally: did not fire
        assert flags[0] == FLAG_HEARD
    else:  # fired on the cached estimate: asked as a triggered link
        assert list(sent(agent, Kind.REQUEST)[-1][3]["to"]) == [1]


def test_realtime_overrun_closes_the_pulled_step_without_its_replies(tmp_path) -> None:
    agent = pulling_agent(tmp_path, Mode.REALTIME)
    agent.on_sensors(sensors(1, [1, 2]))
    agent.on_sensors(sensors(2, [1, 2]))  # step 1 still waiting for its replies
    reports = sent(agent, Kind.REPORT)
    assert [r[2] for r in reports] == [1]
    assert reports[0][3]["cnt"]["overrun"] == 1
    assert reports[0][3]["cnt"]["requests_unanswered"] == 2
    assert list(reports[0][3]["flags"]) == [0, 0]
    assert agent.phase == (Kind.REPLY, 0) and sent(agent, Kind.REQUEST)[-1][2] == 2
