"""The compromised robots' own estimates (``own``): they are the attacker's.

With ``own = "dead_reckoning"`` the compromised robots fuse none of their own readings (their
estimates drift with their odometry), the honest robots' links are untouched; the default
(``"localized"``) fuses them as before. Why the option exists: the paper's MSLE counts the
compromised robots' own estimates, which no defence can protect
(``docs/attack/own_estimates.md``).
"""

from __future__ import annotations

import numpy as np
import pytest

from resloc.experiments.config import default_scenario
from resloc.experiments.runner import run_scenario
from resloc.world.attackers import make_attacker
from resloc.world.attackers.estimates import OWN_ESTIMATES


def _fused_by_observer(own: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    sc = default_scenario().replace(
        **{"run.trials": 1, "run.steps": 30, "run.filters": ["ckf"], "run.dead_reckoning": False}
    )
    adv = make_attacker("compromised", robots=3, own=own)
    res = run_scenario(sc.replace(**adv.overrides), adversary=adv)
    log = res.estimators["ckf"].links
    liars = adv.targets(sc.world.team.robots)
    return log["i"], log["fused"], liars


def test_dead_reckoning_liars_fuse_nothing_and_the_honest_robots_fuse_as_before():
    i, fused, liars = _fused_by_observer("dead_reckoning")
    by_liar = np.isin(i, liars)
    assert by_liar.any() and not fused[by_liar].any()
    assert fused[~by_liar].sum() > 100
    i0, fused0, _ = _fused_by_observer("localized")
    assert fused0[np.isin(i0, liars)].sum() > 20  # the default: the liars keep localizing


def test_own_names_its_choices():
    assert make_attacker("compromised").own == "localized" == OWN_ESTIMATES[0]
    with pytest.raises(ValueError, match="parameter own: 'lost' is not one of localized"):
        make_attacker("compromised", own="lost")


def test_the_msle_without_robots_is_the_msle_of_the_others():
    from resloc.experiments.metrics import AccuracyRecorder, msle_of_distances, pair_distances

    rng = np.random.default_rng(3)
    T, N, steps = 2, 5, 4
    series = {k: np.full((steps, T), np.nan) for k in ("msle", "rmse", "nees", "nees_rel")}
    totals = {k: np.zeros(T, np.int64) for k in ("nees_samples", "nees_exceed", "nees_rel_exceed")}
    rec = AccuracyRecorder(series, totals, T, N, without={"h": np.array([1, 3])})
    poses, xs = rng.normal(size=(steps, T * N, 3)), rng.normal(size=(steps, T * N, 3))
    for k in range(steps):
        rec.add(k, poses[k], xs[k], np.tile(np.eye(3), (T * N, 1, 1)))
    keep = [0, 2, 4]
    for k in range(steps):
        pose, x = poses[k].reshape(T, N, 3)[:, keep], xs[k].reshape(T, N, 3)[:, keep]
        expected = msle_of_distances(pair_distances(pose[..., :2]), pair_distances(x[..., :2]))
        np.testing.assert_allclose(series["msle_h"][k], expected, rtol=1e-12)
        assert not np.allclose(series["msle_h"][k], series["msle"][k])


def _six(steps):
    return default_scenario().replace(
        **{
            "run.steps": steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "team.robots": 6,
            "sdz": [{"center": [0.0, 0.0], "radius": 5.0}],
        }
    )


def test_the_study_pairs_the_honest_robots_msle_with_the_clean_runs_over_them():
    from resloc.experiments.attack import CLEAN, HONEST, run_attack_study
    from resloc.experiments.attack_report import markdown

    base = _six(20)
    res = run_attack_study(
        base, {"paper": {}}, [("compromised", {"robots": 1}), ("range_bias", {})], seeds=2
    )
    cells = res.cells["paper"]
    clean_honest = cells[CLEAN][f"{HONEST} 5"]  # robot 5 is the first compromised
    alone = run_scenario(base.replace(sdz=[], **{"run.trials": 2}), without={"x": np.array([5])})
    np.testing.assert_allclose(clean_honest, alone.estimators["ckf"].per_trial("msle_x_mean"))
    assert not np.allclose(clean_honest, cells[CLEAN]["msle"])
    row = next(r for r in res.table if r["family"] == "compromised")
    liar = cells[row["attacker"]]
    expected = np.mean(np.divide(liar[HONEST], clean_honest))
    assert row["honest_ratio"]["mean"] == pytest.approx(expected, rel=1e-12)
    assert row["honest_ratio_max"] == pytest.approx(max(np.divide(liar[HONEST], clean_honest)))
    biased = next(r for r in res.table if r["family"] == "range_bias")
    assert biased["honest_ratio"] is None and HONEST not in cells[biased["attacker"]]
    # the protected worst case reads the honest ratio where the attacker runs robots
    (protected,) = res.protected
    by = {r["family"]: r for r in res.table if r["attacker"] != CLEAN}
    readings = {"compromised": row["honest_ratio"]["mean"], "range_bias": None}
    readings["range_bias"] = by["range_bias"]["msle_ratio"]["mean"]
    assert protected["family"] == max(readings, key=readings.get)
    assert "over the robots the attacker does not run" in markdown(res)
