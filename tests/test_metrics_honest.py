"""Relative NEES, the consistency test with power, and the wire sizes of every message kind."""

import numpy as np
import pytest

from resloc.experiments.metrics import (
    align_se2,
    nees,
    nees_consistency,
    relative_nees,
    remove_team_rigid_motion,
)
from resloc.experiments.traffic import WIRE_BYTES, communication


def _team(rng, T=3, N=6):
    x = np.zeros((T, N, 3))
    x[..., :2] = rng.uniform(-2, 2, (T, N, 2))
    x[..., 2] = rng.uniform(-np.pi, np.pi, (T, N))
    return x


def test_align_se2_batched_recovers_each_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(4, 10, 2))
    ang = np.array([0.3, -2.0, np.pi - 1e-3, 0.0])
    t = rng.normal(size=(4, 2))
    c, s = np.cos(ang), np.sin(ang)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    dst = src @ np.swapaxes(R, -1, -2) + t[:, None]
    R_fit, t_fit = align_se2(src, dst)
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, t, atol=1e-12)
    R0, t0 = align_se2(src[1], dst[1])  # unbatched: same answer
    np.testing.assert_allclose(R0, R[1], atol=1e-12)
    np.testing.assert_allclose(t0, t[1], atol=1e-12)


def test_relative_nees_ignores_a_common_rigid_motion_but_not_a_relative_error():
    rng = np.random.default_rng(2)
    truth = _team(rng)
    ang, shift = 0.2, np.array([0.5, -0.3])
    c, s = np.cos(ang), np.sin(ang)
    moved = truth.copy()
    moved[..., :2] = truth[..., :2] @ np.array([[c, -s], [s, c]]).T + shift
    moved[..., 2] += ang
    P = np.broadcast_to(np.eye(3) * 1e-4, (*truth.shape[:2], 3, 3))
    absolute = nees(truth.reshape(-1, 3), moved.reshape(-1, 3), P.reshape(-1, 3, 3))
    assert absolute.min() > 100  # the absolute error is large
    np.testing.assert_allclose(relative_nees(truth, moved, P), 0.0, atol=1e-12)
    np.testing.assert_allclose(remove_team_rigid_motion(truth, moved), truth, atol=1e-12)
    lied = moved.copy()
    lied[:, 0, :2] += 0.1  # one robot displaced relative to the others
    assert relative_nees(truth, lied, P)[:, 0].min() > 10


def test_consistency_test_accepts_chi2_samples_and_rejects_scaled_ones():
    rng = np.random.default_rng(3)
    good = rng.chisquare(3, size=20000)
    ok = nees_consistency(good)
    assert ok["in_band"] == 1.0
    assert ok["exceed_pvalue"] > 0.01
    assert ok["exceed_share"] == pytest.approx(0.05, abs=0.01)
    bad = nees_consistency(1.3 * good)  # 30 % overconfident: seed means would not see it
    assert bad["in_band"] == 0.0
    assert bad["exceed_pvalue"] < 1e-6
    assert nees_consistency(np.array([np.nan]))["samples"] == 0


def test_communication_counts_every_kind_in_bytes():
    totals = {
        "triggered": np.array([10, 0]),
        "ack_frames": np.array([2, 0]),
        "ack_links": np.array([5, 0]),
        "consensus_messages": np.array([7, 1]),
    }
    comm = communication(totals)
    assert comm["estimate"][1][0] == 10 * WIRE_BYTES["estimate"]
    assert comm["ack"][1][0] == 2 * WIRE_BYTES["ack"] + 5 * WIRE_BYTES["ack_per_link"]
    np.testing.assert_array_equal(comm["total"][0], [19, 1])
    np.testing.assert_array_equal(comm["total"][1], [sum(b[0] for b in _parts(comm)), 229])


def _parts(comm):
    return [comm[k][1] for k in ("estimate", "ack", "consensus")]


def test_wire_bytes_match_the_runtime_encoder():
    from resloc.runtime.messages import Codec  # msgpack: installed by make test (extra swarm)
    from resloc.runtime.schema import Kind

    codec = Codec(b"k" * 32, 3)
    est = codec.encode(Kind.ESTIMATE, 1, {"x": np.zeros(3), "P": np.eye(3)}, "resloc/radio")
    assert len(est) == WIRE_BYTES["estimate"]
    for n in (1, 2, 3, 4, 8):
        ack = codec.encode(
            Kind.ACK, 1, {"to": np.arange(n), "ack": np.zeros((n, 3, 3))}, "resloc/radio"
        )
        # exact up to 3 links; beyond, msgpack's longer length prefix adds 1 byte
        assert 0 <= len(ack) - (WIRE_BYTES["ack"] + n * WIRE_BYTES["ack_per_link"]) <= int(n > 3)
    cons = codec.encode(
        Kind.CONSENSUS, 1, {"round": 2, "m": np.zeros((2, 3, 3)), "deg": 4}, "resloc/radio"
    )
    assert len(cons) == WIRE_BYTES["consensus"]
    # zone trust: the sender's readings ride on its estimate frame (one reading, exactly)
    body = {"x": np.zeros(3), "P": np.eye(3), "rj": np.arange(1), "rz": np.ones((1, 2))}
    with_reading = codec.encode(Kind.ESTIMATE, 2, body, "resloc/radio")
    assert len(with_reading) - len(est) == WIRE_BYTES["reading"]
    # split CI: the independent part on the estimate, and acknowledgements of ids only
    body = {"x": np.zeros(3), "P": np.eye(3), "Pi": np.eye(3)}
    with_part = codec.encode(Kind.ESTIMATE, 3, body, "resloc/radio")
    assert len(with_part) - len(est) == WIRE_BYTES["independent_part"]
    for n in (0, 1, 5, 31):
        ack = codec.encode(Kind.ACK, 10 + n, {"to": np.arange(n)}, "resloc/radio")
        assert len(ack) == WIRE_BYTES["delivery_ack"] + n * WIRE_BYTES["delivery_ack_per_link"]


def test_wire_bytes_of_factorized_frames_match_the_runtime_encoder():
    from resloc.runtime.messages import Codec
    from resloc.runtime.schema import Kind

    codec = Codec(b"k" * 32, 3)
    estimate = {"x": np.zeros(3), "P": np.eye(3)}
    plain = codec.encode(Kind.ESTIMATE, 1, estimate, "resloc/radio")
    factor = {"fj": np.arange(1), "fs": np.eye(3)[None]}
    carried = codec.encode(Kind.ESTIMATE, 1, estimate | factor, "resloc/radio")
    assert len(carried) - len(plain) == WIRE_BYTES["factor"]
    for n in (1, 2, 16, 31):
        body = {"to": np.arange(n), "round": 1, "pair": np.zeros((n, 4, 3, 3))}
        pairs = codec.encode(Kind.ACK, 1, body, "resloc/radio")
        assert len(pairs) == WIRE_BYTES["pair_frame"] + n * WIRE_BYTES["pair_per_link"]


def test_factorized_counts_its_factors_and_pair_exchange():
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario

    sc = default_scenario().replace(
        **{"team.robots": 6, "run.steps": 30, "run.filters": ["ekf"], "run.dead_reckoning": False,
           "estimator.fusion": "factorized"}
    )  # fmt: skip
    est = run_scenario(sc).estimators["ekf"]
    t, log = est.totals, est.links
    assert np.array_equal(t["factors"], t["triggered"]) and t["triggered"].sum() > 0
    # the same counts from the link log, one step at a time
    fused = log["fused"]
    acks, ack_frames, pairs, pair_frames = 0, 0, 0, 0
    for k in np.unique(log["step"][fused]):
        on = fused & (log["step"] == k)
        links = list(zip(log["i"][on].tolist(), log["j"][on].tolist(), strict=True))
        told = [(i, j) for i, j in links if i < j]
        acks += len(told)
        ack_frames += len({i for i, _ in told})
        closed = {(min(i, j), max(i, j)) for i, j in links}
        pairs += len(closed)
        pair_frames += len({high for _, high in closed})
    assert pairs > 0 and 0 < acks < fused.sum()
    got = [int(t[key][0]) for key in ("pair_ack_links", "pair_ack_frames")]
    assert got == [acks, ack_frames]
    assert [int(t["pair_messages"][0]), int(t["pair_frames"][0])] == [pairs, pair_frames]
    comm = communication(t)
    w = WIRE_BYTES
    assert comm["pair"][1][0] == pair_frames * w["pair_frame"] + pairs * w["pair_per_link"]
    assert comm["estimate"][1][0] == t["triggered"][0] * (w["estimate"] + w["factor"])
    assert np.isfinite(est.bytes_per_step(sc.estimator.fusion)).all()


def test_distributed_lambda2_counts_its_exchanges_per_trial_in_bytes():
    import msgpack

    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario
    from resloc.runtime.messages import HEADER, TAG_SIZE

    body = {"round": 2, "y": np.zeros(4).tobytes(), "deg": 4}  # a CONSENSUS-like frame
    frame = HEADER.size + len(msgpack.packb(body, use_bin_type=True)) + TAG_SIZE
    assert frame == WIRE_BYTES["connectivity"]
    sc = default_scenario().replace(
        **{"team.robots": 6, "run.steps": 20, "run.trials": 2, "run.filters": ["ekf"],
           "run.dead_reckoning": False, "trigger.lambda2": "distributed"}
    )  # fmt: skip
    run = run_scenario(sc)
    t = run.estimators["ekf"].totals
    messages = run.meta["lambda2"]["messages"]
    assert messages > 0 and t["connectivity_messages"].sum() == messages
    assert (t["connectivity_messages"] > 0).all()  # both trials, each its own
    comm = communication(t)
    np.testing.assert_array_equal(
        comm["connectivity"][1], t["connectivity_messages"] * WIRE_BYTES["connectivity"]
    )
    plain = run_scenario(sc.replace(**{"trigger.lambda2": "component"})).estimators["ekf"]
    assert plain.totals["connectivity_messages"].sum() == 0


def test_split_ci_counts_its_independent_parts_and_delivery_acknowledgements():
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario

    sc = default_scenario().replace(
        **{"team.robots": 6, "run.steps": 20, "run.filters": ["ekf"], "run.dead_reckoning": False}
    )
    naive = run_scenario(sc).estimators["ekf"].totals
    split = run_scenario(sc.replace(**{"estimator.fusion": "split_ci"})).estimators["ekf"]
    t = split.totals
    assert naive["delivery_ack_links"].sum() == naive["independent_parts"].sum() == 0
    assert np.array_equal(t["independent_parts"], t["triggered"])
    assert np.array_equal(t["delivery_ack_links"], t["fused"]) and t["fused"].sum() > 0
    assert 0 < t["delivery_ack_frames"].sum() <= t["fused"].sum()
    assert t["ack_frames"].sum() == 0  # not gauge's blocks
    comm = communication(t)
    assert np.array_equal(comm["ack"][0], t["delivery_ack_frames"])
    assert np.array_equal(
        comm["ack"][1],
        t["delivery_ack_frames"] * WIRE_BYTES["delivery_ack"]
        + t["fused"] * WIRE_BYTES["delivery_ack_per_link"],
    )


def test_zone_trust_counts_the_readings_on_the_estimates():
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario

    sc = default_scenario().replace(
        **{"team.robots": 6, "run.steps": 20, "run.filters": ["ekf"], "run.dead_reckoning": False}
    )
    plain = run_scenario(sc).estimators["ekf"]
    zone = run_scenario(sc.replace(**{"detector.zone_trust": True})).estimators["ekf"]
    assert plain.totals["readings"].sum() == 0
    sent = zone.totals["triggered"]
    assert sent.sum() > 0 and np.array_equal(zone.totals["readings"], sent)
    extra = zone.bytes_per_trial() - sent * WIRE_BYTES["estimate"]
    assert np.array_equal(extra, sent * WIRE_BYTES["reading"])


def test_run_summary_reports_relative_nees_and_bytes():
    import resloc

    sc = resloc.default_scenario().replace(
        **{
            "run.steps": 30,
            "run.filters": ["ckf"],
            "estimator.fusion": "gauge",
            "estimator.gauge_sums": "consensus",
        }
    )
    s = resloc.run_scenario(sc).summary()["ckf"]
    assert np.isfinite(s["nees_rel_mean"]) and s["nees_rel_mean"] >= 0
    assert s["messages_consensus"] > 0 and s["messages_ack"] > 0
    kinds = ("estimate", "ack", "consensus", "pair", "connectivity")
    assert s["bytes_total"] == sum(s[f"bytes_{k}"] for k in kinds)
    assert s["messages_estimate"] == s["transmissions"]
    assert 0.0 <= s["nees_exceed_share"] <= 1.0


def test_methods_whose_traffic_is_not_counted_report_no_bytes():
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario
    from resloc.experiments.traffic import uncounted_traffic

    assert uncounted_traffic("naive") is None and uncounted_traffic("gauge") is None
    assert uncounted_traffic("split_ci") is None and uncounted_traffic("factorized") is None
    assert "centralized" in uncounted_traffic("tracked")
    sc = default_scenario().replace(
        **{"team.robots": 5, "run.steps": 10, "run.filters": ["ekf"], "run.dead_reckoning": False}
    )
    for fusion, counted in (("naive", True), ("tracked", False), ("factorized", True)):
        est = run_scenario(sc.replace(**{"estimator.fusion": fusion})).estimators["ekf"]
        assert np.isfinite(est.bytes_per_step(fusion)).all() == counted, fusion
