"""The adversary suite: the acceptance oracle, the strategies, the study and its command."""

import numpy as np
import pytest
from typer.testing import CliRunner

import resloc
from resloc.cl.cusum import chi2_gate
from resloc.cl.detector import InnovationNorm
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.experiments.attack import CLEAN, run_attack_study, save_attack_study
from resloc.world.attackers import ATTACKERS, accepted, attacker, largest_accepted
from resloc.world.attackers.oracle import scratch_memory

NIS = dict(detector_norm=InnovationNorm.NIS, rho=float(np.sqrt(chi2_gate(0.01))))


def _one_link(nu_honest, S=None):
    S = np.diag([0.005**2, 0.05**2])[None] if S is None else S
    z_hat = np.array([[1.0, 0.2]])
    return z_hat + nu_honest, z_hat, S, np.array([0]), np.array([1])


def test_oracle_uses_the_whole_gate_even_when_honest_noise_is_large():
    params = CLParams(**NIS)
    # honest range innovation at 0.95 of the gate: today's stealthy attacker sends nothing
    z, z_hat, S, i, j = _one_link(np.array([[0.95 * params.rho * 0.005, 0.0]]))
    lie = np.array([[-0.1, 0.0]])  # a lie that first crosses the region, then leaves it
    a = largest_accepted(z, lie, z_hat, S, i, j, params, None)
    assert a[0] > 0.0
    sent = z + a[:, None] * lie
    assert accepted(sent, z_hat, S, i, j, params, None)[0]
    beyond = z + (a[:, None] + 2e-3) * lie
    assert not accepted(beyond, z_hat, S, i, j, params, None)[0]
    # the accepted lie reaches the far side of the gate: innovation about -rho sigma
    assert (sent - z_hat)[0, 0] == pytest.approx(-params.rho * 0.005, rel=1e-2)


def test_oracle_reads_the_victims_cusum_state_and_leaves_it_untouched():
    params = CLParams(**NIS, cusum=True, cusum_k=3.0, cusum_h=10.0)
    z, z_hat, S, i, j = _one_link(np.zeros((1, 2)))
    lie = np.array([[0.5, 0.0]])
    fresh = LinkMemory(2)
    a_fresh = largest_accepted(z, lie, z_hat, S, i, j, params, fresh)
    loaded = LinkMemory(2)
    loaded.cusum.set(i, j, np.array([9.9]))  # almost at h: no slack left
    before = loaded.cusum.values.copy()
    a_loaded = largest_accepted(z, lie, z_hat, S, i, j, params, loaded)
    np.testing.assert_array_equal(loaded.cusum.values, before)
    assert 0.0 < a_loaded[0] < a_fresh[0]
    nis = ((a_loaded[0] * 0.5) / 0.005) ** 2
    # the CUSUM accepts up to k + (h - S): the attacker spends the last slack too
    assert nis == pytest.approx(params.cusum_k + 10.0 - 9.9, rel=1e-2)


def test_scratch_memory_copies_statistics():
    mem = LinkMemory(3)
    mem.cusum.set(np.array([0]), np.array([1]), np.array([1.0]))
    copy = scratch_memory(mem)
    copy.cusum.values[0] = 5.0
    assert mem.cusum.values[0] == 1.0
    assert scratch_memory(None) is None


def _tiny(steps=40):
    return resloc.default_scenario().replace(
        **{
            "run.steps": steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "team.robots": 6,
            "sdz": [{"center": [0.0, 0.0], "radius": 5.0}],
        }
    )


def test_every_attacker_runs_and_marks_what_it_falsifies():
    base = _tiny(35).replace(**{"detector.norm": "nis", "detector.false_alarm": 0.01})
    for name, adv in ATTACKERS.items():
        if name in ("displaced", "compromised"):
            continue  # robot 5 exists; run below with the study
        res = resloc.run_scenario(base.replace(**adv.overrides), adversary=adv)
        s = res.summary()["ckf"]
        assert np.isfinite(s["msle_mean"]), name
        assert s["attacked_rate"] > 0, name
    with pytest.raises(KeyError, match="known"):
        attacker("nope")


def test_range_bias_beats_the_reviewer_against_sequence_tests():
    base = _tiny(60).replace(
        **{
            "detector.norm": "nis",
            "detector.false_alarm": 0.01,
            "detector.cusum": True,
            "detector.mean_cusum": True,
        }
    )
    msle = {}
    for name in ("range_bias", "reviewer"):
        adv = ATTACKERS[name]
        msle[name] = resloc.run_scenario(base.replace(**adv.overrides), adversary=adv).summary()[
            "ckf"
        ]
    clean = resloc.run_scenario(base.replace(sdz=[])).summary()["ckf"]["msle_mean"]
    # the full-knowledge attacker hurts, and is never caught by the sequence tests it knows
    assert msle["range_bias"]["msle_mean"] > 3 * clean
    assert msle["range_bias"]["detector_recall"] <= msle["reviewer"]["detector_recall"]


def test_study_table_worst_case_and_files(tmp_path):
    base = _tiny(20)
    defences = {"paper": {}, "nis": {"detector.norm": "nis", "detector.false_alarm": 0.01}}
    res = run_attack_study(base, defences, ["range_bias", "compromised"], seeds=2)
    assert {r["defence"] for r in res.worst} == set(defences)
    assert len(res.table) == 2 * 3
    clean = [r for r in res.table if r["attacker"] == CLEAN]
    assert all(r["msle_ratio"]["mean"] == pytest.approx(1.0) for r in clean)
    for r in res.worst:
        same = [x for x in res.table if x["defence"] == r["defence"] and x["attacker"] != CLEAN]
        assert r["msle_ratio"]["mean"] == max(x["msle_ratio"]["mean"] for x in same)
    files = save_attack_study(res, tmp_path)
    assert [f.name for f in files] == ["attack.md", "attack.csv", "attack.json"]
    assert "Worst case per defence" in files[0].read_text()
    assert len(files[1].read_text().strip().splitlines()) == 1 + 6


def test_cli_bad_defence_and_attacker_are_one_line_errors(tmp_path):
    from resloc.cli.app import app

    runner = CliRunner()
    for args in (["--defence", "nope"], ["--attacker", "nope"], ["--defence", "x:novalue"]):
        res = runner.invoke(app, ["attack", *args, "--out", str(tmp_path / "o")])
        assert res.exit_code == 2, res.output
        assert len(res.output.strip().splitlines()) == 1
        assert not (tmp_path / "o").exists()
