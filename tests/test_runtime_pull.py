"""Pulled estimates (``estimator.neighbour_estimate = "cached"``): the runtime sends an
estimate only when a trigger fires (REQUEST on the link, REPLY with the estimate), and a
lockstep run equals the in-process simulator's cached semantics to 1e-9. Real processes and
Zenoh sessions on 127.0.0.1, stopped by pid by the supervisor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from resloc.experiments.runner import run_scenario
from resloc.runtime.swarm import run_swarm
from resloc.runtime.transport import free_endpoint
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
