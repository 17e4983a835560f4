"""The adversary suite: the acceptance oracle, the strategies, the study and its command."""

from typing import ClassVar

import numpy as np
import pytest
from typer.testing import CliRunner

import resloc
from resloc.cl.cusum import chi2_gate
from resloc.cl.detector import InnovationNorm
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.experiments.attack import CLEAN, run_attack_study
from resloc.experiments.attack_report import save_attack_study
from resloc.world.attackers import (
    ATTACKERS,
    accepted,
    attacker,
    largest_accepted,
    make_attacker,
    variants,
)
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
    robot = mem.stage_statistic("robot_cusum")
    robot.set(np.array([0]), np.array([0]), np.array([2.0]))
    copy = scratch_memory(mem)
    copy.cusum.values[0] = 5.0
    copy.stage_statistic("robot_cusum").set(np.array([0]), np.array([0]), np.array([7.0]))
    copy.stage_statistic("recovery_runs").set(np.array([1]), np.array([1]), np.array([3.0]))
    assert mem.cusum.values[0] == 1.0
    assert robot.get(np.array([0]), np.array([0]))[0] == 2.0  # the stages' own state too
    assert "recovery_runs" not in mem._stage_statistics
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


def test_study_table_worst_case_search_and_files(tmp_path):
    base = _tiny(20)
    defences = {"paper": {}, "nis": {"detector.norm": "nis", "detector.false_alarm": 0.01}}
    res = run_attack_study(base, defences, ["range_bias", "compromised"], seeds=2)
    assert {r["defence"] for r in res.worst} == set(defences)
    points = 1 + len(variants("range_bias")) + len(variants("compromised"))
    assert len(res.table) == 2 * points
    clean = [r for r in res.table if r["attacker"] == CLEAN]
    assert all(r["msle_ratio"]["mean"] == pytest.approx(1.0) for r in clean)
    for r in res.worst:
        same = [x for x in res.table if x["defence"] == r["defence"] and x["attacker"] != CLEAN]
        assert r["msle_ratio"]["mean"] == max(x["msle_ratio"]["mean"] for x in same)
    # the defence x attacker entry of a strategy is the worst point of its grid search
    assert len(res.searched) == 2 * 2
    for r in res.searched:
        grid = [x for x in res.table if x["defence"] == r["defence"] and x["family"] == r["family"]]
        assert len(grid) == len(variants(r["family"]))
        assert r["msle_ratio"]["mean"] == max(x["msle_ratio"]["mean"] for x in grid)
    files = save_attack_study(res, tmp_path)
    assert [f.name for f in files] == ["attack.md", "attack.csv", "attack.json"]
    text = files[0].read_text()
    assert "Worst case per defence" in text and "Searched:" in text
    assert len(files[1].read_text().strip().splitlines()) == 1 + 2 * points


def test_more_seeds_reuse_the_stored_ones(tmp_path):
    from resloc.experiments.executor import Study
    from resloc.experiments.store import ResultStore

    base = _tiny(12)
    defences = {"nis": {"detector.norm": "nis", "detector.false_alarm": 0.01}}
    store = ResultStore(tmp_path / "store")
    first = Study(jobs=1, store=store)
    two = run_attack_study(base, defences, ["starve"], seeds=2, study=first)
    assert first.stats.computed == 2 * 2 and first.stats.from_store == 0
    again = Study(jobs=1, store=store)
    three = run_attack_study(base, defences, ["starve"], seeds=3, study=again)
    # only the new seed of each cell (clean and starve) is simulated
    assert again.stats.from_store == 2 * 2 and again.stats.computed == 2
    for name in (CLEAN, "starve"):
        np.testing.assert_array_equal(
            three.cells["nis"][name]["msle"][:2], two.cells["nis"][name]["msle"]
        )
    # the seed computed alone equals the same seed computed in a batch of three
    fresh = run_attack_study(base, defences, ["starve"], seeds=3)
    np.testing.assert_allclose(
        three.cells["nis"]["starve"]["msle"], fresh.cells["nis"]["starve"]["msle"]
    )


def test_cli_bad_defence_and_attacker_are_one_line_errors(tmp_path):
    from resloc.cli.app import app

    runner = CliRunner()
    for args in (["--defence", "nope"], ["--attacker", "nope"], ["--defence", "x:novalue"]):
        res = runner.invoke(app, ["attack", *args, "--out", str(tmp_path / "o")])
        assert res.exit_code == 2, res.output
        assert len(res.output.strip().splitlines()) == 1
        assert not (tmp_path / "o").exists()


def test_oracle_judges_a_per_robot_test_as_one_round_without_holding_back():
    # the per-robot CUSUM adds up a round's rows: 33 stacked copies of one candidate would
    # alarm it and the attacker would hold back; judged as one round it does not
    params = CLParams(**NIS, robot_cusum=True, robot_cusum_k=3.0, robot_cusum_h=30.0)
    z, z_hat, S, i, j = _one_link(np.zeros((1, 2)))
    lie = np.array([[0.5, 0.0]])
    gate_only = largest_accepted(z, lie, z_hat, S, i, j, CLParams(**NIS), None)
    a = largest_accepted(z, lie, z_hat, S, i, j, params, LinkMemory(2))
    assert a[0] == pytest.approx(gate_only[0], rel=1e-3)
    # near its threshold the per-robot test leaves g + NIS - k <= h: the last slack, spent
    loaded = LinkMemory(2)
    loaded.stage_statistic("robot_cusum").set(i, i, np.array([29.0]))
    a = largest_accepted(z, lie, z_hat, S, i, j, params, loaded)
    assert loaded.stage_statistic("robot_cusum").get(i, i)[0] == 29.0  # left untouched
    nis = ((a[0] * 0.5) / 0.005) ** 2
    assert nis == pytest.approx(3.0 + 1.0, rel=0.05)
    assert accepted(z + a[:, None] * lie, z_hat, S, i, j, params, loaded)[0]


class _FixedRampCompromised:
    """The suite's former compromised robot (a fixed sideways ramp, 0.05 m/s to 0.5 m, not
    consulting the victims' detector): the baseline the strengthened one must beat."""

    name = "fixed_ramp"
    overrides: ClassVar[dict] = {"attack.kind": "stealthy"}

    def mark(self, sdz_attacked, step):
        return step.j % step.robots == 5

    def attack(self, links, step, params, memory):
        import dataclasses

        rows = np.flatnonzero(links.j % step.robots == 5)
        offset = min(0.5, 0.05 * step.k * step.dt)
        x_nb = links.x_nb.copy()
        x_nb[rows, 0] -= offset * np.sin(x_nb[rows, 2])
        x_nb[rows, 1] += offset * np.cos(x_nb[rows, 2])
        return dataclasses.replace(links, x_nb=x_nb, tamper=None)


def _compromised_links(params):
    from resloc.models.measurement import range_bearing
    from resloc.world.attackers import AttackStep

    pose = np.array(
        [
            [0.0, 0.0, 0.3],
            [1.0, 0.2, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            [2.0, 0.0, 0],
            [0.8, 0.9, 1.0],
        ]
    )
    i, j = np.array([0, 0, 1]), np.array([1, 5, 5])
    z_hat = range_bearing(pose[i], pose[j])
    z = z_hat + np.array([[0.002, 0.01], [0.003, -0.02], [-0.004, 0.03]])
    links = resloc.LinkBatch(
        i=i,
        j=j,
        z=z,
        x_nb=pose[j],
        P_nb=np.tile(np.diag([1e-4, 1e-4, 1e-4]), (3, 1, 1)),
        channel_ok=np.ones(3, bool),
        risk_s=np.zeros(6),
        risk_c=np.zeros(6),
        lambda2=np.ones(6),
    )
    step = AttackStep(1, 0.033, pose, i, j, z, np.zeros(3, bool), 6)
    S = np.tile(np.diag([0.005**2 + 2e-4, 0.05**2 + 2e-4]), (3, 1, 1))
    return links, step, z_hat, S


def test_compromised_lie_sits_on_the_victims_gate_along_the_gauge_direction():
    from resloc.filters.update import innovation

    params = CLParams(**NIS)
    links, step, z_hat, S = _compromised_links(params)
    adv = make_attacker("compromised", robots=1)
    assert list(adv.mark(None, step)) == [False, True, True]
    tampered = adv.attack(links, step, params, None)
    sent = tampered.tamper(np.arange(3), z_hat, S)
    np.testing.assert_array_equal(sent[0], links.z[0])  # robot 1 is honest
    nu = innovation(sent, z_hat)
    nis = np.einsum("ei,eij,ej->e", nu, np.linalg.inv(S), nu)
    # the largest shift the gate accepts: the innovation is on the gate's edge
    np.testing.assert_allclose(nis[1:], params.rho**2, rtol=2e-3)
    assert accepted(sent, z_hat, S, links.i, links.j, params, None).all()
    # and it is the innovation of robot 5 broadcast further along world +x: the prediction
    # it implies, back in the world frame, is robot 5 moved along +x only
    implied = z_hat + (links.z - sent)  # h(x_i, x_5 + shift)
    for row in (1, 2):
        heading = step.pose[links.i[row], 2]
        rel = [implied[row, 0] * np.cos(implied[row, 1]), implied[row, 0] * np.sin(implied[row, 1])]
        true = [z_hat[row, 0] * np.cos(z_hat[row, 1]), z_hat[row, 0] * np.sin(z_hat[row, 1])]
        c, s_ = np.cos(heading), np.sin(heading)
        d = np.subtract(rel, true)
        world = np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]])
        assert world[0] > 0.005 and abs(world[1]) < 1e-9
    # a smaller claimed covariance is what the victims receive
    small = make_attacker("compromised", claimed_cov=0.01).attack(links, step, params, None)
    np.testing.assert_allclose(small.P_nb[1:], links.P_nb[1:] * 0.01)
    np.testing.assert_array_equal(small.P_nb[0], links.P_nb[0])


def test_compromised_robot_hurts_more_than_the_fixed_ramp_and_stays_under_the_gate():
    base = _tiny(90).replace(**{"detector.norm": "nis", "detector.false_alarm": 0.01, "sdz": []})
    runs = {}
    for name, adv in (
        ("fixed", _FixedRampCompromised()),
        ("oracle", make_attacker("compromised", robots=1)),
    ):
        runs[name] = resloc.run_scenario(base.replace(**adv.overrides), adversary=adv)
    clean = resloc.run_scenario(base).summary()["ckf"]["msle_mean"]
    fixed, strong = (runs[n].summary()["ckf"] for n in ("fixed", "oracle"))
    assert strong["msle_mean"] > 1.5 * fixed["msle_mean"]
    assert strong["msle_mean"] > 1.5 * clean
    # its lies pass the victims' gate: detections on its links at the false-alarm level
    assert strong["detector_recall"] <= 0.05
    assert fixed["detector_recall"] > 0.5  # the fixed ramp is caught


def test_attacker_parameters_are_checked():
    with pytest.raises(ValueError, match="unknown parameter"):
        make_attacker("on_off", nope=1)
    assert make_attacker("on_off", period=10).label == "on_off[period=10]"
    # 2 and 2.0 are one attacker: one label, one stored cell
    assert make_attacker("range_bias", size=2).params == make_attacker("range_bias").params
    with pytest.raises(ValueError, match="period: expected an integer"):
        make_attacker("on_off", period=2.5)
    for name in ATTACKERS:
        labels = [v.label for v in variants(name)]
        assert len(set(labels)) == len(labels), name


def test_cli_pins_an_attackers_parameters():
    from resloc.cli.attack import parse_attacker

    assert parse_attacker("on_off") == "on_off"
    assert parse_attacker("on_off:period=10") == ("on_off", {"period": 10})
    for bad in ("nope", "on_off:nope=1", "on_off:period", "on_off:period=x"):
        with pytest.raises(ValueError, match="--attacker"):
            parse_attacker(bad)
    base = _tiny(10)
    res = run_attack_study(base, {"paper": {}}, [("on_off", {"period": 3})], seeds=2)
    assert [r["attacker"] for r in res.table] == [CLEAN, "on_off[period=3]"]
    assert res.config["grids"] == {"on_off": ["on_off[period=3]"]}
