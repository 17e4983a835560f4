"""The witness stage (cl/detection_witness.py): observers compare notes on each robot."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl.detection import Evidence
from resloc.cl.detection_witness import (
    STATE,
    WitnessCheck,
    WitnessNotes,
    step_notes,
    witness_state,
    witness_statistic,
)
from resloc.cl.detection_witness_frames import (
    deliver_witness,
    delivered_store,
    received_state,
    record_witness,
)
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.errors import ConfigError
from resloc.world.attackers.estimates import shifted_prediction
from resloc.world.attackers.outvoted import shielding_notes
from resloc.world.attackers.witness import lying_notes, within_witness

PARAMS = CLParams(witness=True, witness_liars=2.0, witness_k=4.0, witness_h=20.0)
SUSPECT = 0
OBSERVERS = 9
SD_Q = 0.01  # each note's own noise (m)
SD_P = 0.005  # the suspect's own estimation error, common to every note (m)


def _notes(rng, lie=(0.0, 0.0), accusers=0, accusation=(0.0, 0.0)) -> WitnessNotes:
    """One step's notes of ``OBSERVERS`` observers (1..) on robot 0: the suspect's own
    error (shared), each note's independent noise, a lie in its broadcast seen by every
    observer, and ``accusers`` observers whose notes are moved by ``accusation``."""
    n = OBSERVERS
    shared = rng.normal(0.0, SD_P, 2)
    u = shared + rng.normal(0.0, SD_Q, (n, 2)) + np.asarray(lie)
    u[:accusers] += np.asarray(accusation)
    Q = np.tile(np.eye(2) * SD_Q**2, (n, 1, 1))
    P = np.tile(np.eye(2) * SD_P**2, (n, 1, 1))
    return WitnessNotes(u, Q, P, np.arange(1, n + 1), np.full(n, SUSPECT), np.ones(n, bool))


#: The observers' radio links: each receives every other's frames.
MESH = np.array(
    [(r, o) for r in range(1, OBSERVERS + 1) for o in range(1, OBSERVERS + 1) if r != o]
)
RECEIVER = 1


def _frames(ok=None):
    """The step's links as the notes travel on them (receiver i, sender j)."""
    ok = np.ones(len(MESH), bool) if ok is None else ok
    return SimpleNamespace(i=MESH[:, 0], j=MESH[:, 1], channel_ok=ok)


def _run(steps, make, params=PARAMS, memory=None, ok=None):
    """Receiver 1's statistic on the suspect after each step's notes arrived (with the
    frames of the step after)."""
    memory = LinkMemory(OBSERVERS + 1) if memory is None else memory
    out = []
    for k in range(steps):
        record_witness(make(k), params, memory)
        deliver_witness(params, memory, _frames(ok))
        out.append(float(witness_state(memory, [RECEIVER], [SUSPECT])[0]))
    return np.array(out), memory


def _convicted(memory, params=PARAMS) -> bool:
    ev = Evidence(
        np.zeros((1, 2)), np.eye(2)[None], np.zeros(1), np.array([RECEIVER]),
        np.array([SUSPECT]), np.zeros(1, bool),
    )  # fmt: skip
    return bool(WitnessCheck().discard(ev, params, memory)[0])


def test_honest_notes_raise_no_alarm():
    rng = np.random.default_rng(1)
    S, memory = _run(500, lambda k: _notes(rng))
    assert S.max() < 0.5 * PARAMS.witness_h
    assert not _convicted(memory)


def test_a_coherent_liar_seen_by_every_observer_is_convicted():
    rng = np.random.default_rng(2)
    # 1.5 sd of one note: every per-link test of one observer passes it most of the time
    S, memory = _run(20, lambda k: _notes(rng, lie=(1.5 * SD_Q, 0.0)))
    assert S[-1] > PARAMS.witness_h and _convicted(memory)


def test_a_receiver_judges_only_the_notes_it_received():
    """Receiver 1's frames from every other observer are jammed: it holds its own note on
    the liar only (not judged, f = 2), while receiver 2, which hears everyone, convicts."""
    rng = np.random.default_rng(2)
    ok = MESH[:, 0] != RECEIVER
    S, memory = _run(20, lambda k: _notes(rng, lie=(1.5 * SD_Q, 0.0)), ok=ok)
    assert S.max() == 0.0 and not _convicted(memory)
    assert witness_state(memory, [2], [SUSPECT])[0] > PARAMS.witness_h
    # half of receiver 1's frames get through: it judges on what arrived (5 notes, a
    # larger lie to convict on them)
    rng = np.random.default_rng(2)
    half = ok | (MESH[:, 1] % 2 == 0)
    S, memory = _run(20, lambda k: _notes(rng, lie=(4.0 * SD_Q, 0.0)), ok=half)
    assert S[-1] > PARAMS.witness_h and _convicted(memory)


@pytest.mark.parametrize("size", [0.02, 0.05, 1.0])
def test_lying_notes_of_f_observers_do_not_convict_an_honest_robot(size):
    rng = np.random.default_rng(3)
    f = int(PARAMS.witness_liars)
    S, memory = _run(300, lambda k: _notes(rng, accusers=f, accusation=(size, 0.0)))
    assert S.max() < PARAMS.witness_h and not _convicted(memory)
    # the same accusations convict when the stage drops none of them (the test can fail)
    rng = np.random.default_rng(3)
    naive = CLParams(witness=True, witness_liars=0.0, witness_k=4.0, witness_h=20.0)
    S0, _ = _run(300, lambda k: _notes(rng, accusers=f, accusation=(size, 0.0)), naive)
    assert S0.max() > PARAMS.witness_h


def test_a_robot_that_stops_lying_is_readmitted():
    rng = np.random.default_rng(4)
    lying = 30

    def make(k):
        return _notes(rng, lie=(0.05, 0.0) if k < lying else (0.0, 0.0))

    S, memory = _run(lying + 30, make)
    assert S[lying - 1] == pytest.approx(2 * PARAMS.witness_h)  # the statistic is capped
    back = np.flatnonzero(S[lying:] <= PARAMS.witness_h)
    # from the cap, about h / (k - E T) steps (E T < 1 for honest notes here)
    assert back.size and back[0] <= PARAMS.witness_h / (PARAMS.witness_k - 1.0) + 1
    assert not _convicted(memory)


def test_a_robot_with_at_most_f_notes_is_not_judged():
    rng = np.random.default_rng(5)
    notes = _notes(rng, lie=(1.0, 0.0))
    keep = np.arange(OBSERVERS) < PARAMS.witness_liars
    few = WitnessNotes(notes.u, notes.Q, notes.P_pos, notes.i, notes.j, keep)
    ids, T, judged = witness_statistic(few, PARAMS)
    assert list(ids) == [SUSPECT] and not judged[0] and T[0] == 0.0
    ids, T, judged = witness_statistic(notes, PARAMS)
    assert judged[0] and T[0] > 1e3


def _ring(liars=(0,)):
    """Robot 0 at the origin, observers 1..7 on a unit circle (heading 0), every pair linked
    both ways (sensing and radio); honest readings exact."""
    n = 8
    ang = np.linspace(0.0, 2 * np.pi, n - 1, endpoint=False)
    pos = np.vstack([[0.0, 0.0], np.c_[np.cos(ang), np.sin(ang)]])
    x = np.c_[pos, np.zeros(n)]
    P = np.tile(np.diag([1e-4, 1e-4, 1e-5]), (n, 1, 1))
    i, j = np.array([(a, b) for a in range(n) for b in range(n) if a != b]).T  # every pair
    rel = x[j, :2] - x[i, :2]
    z = np.c_[np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])]
    is_liar = np.isin(np.arange(n), liars)
    return x, P, i, j, z, is_liar


@pytest.mark.parametrize("liars", [(0,), (0, 1)])
def test_the_compromised_robots_lie_sits_on_the_witness_threshold(liars):
    params = CLParams(witness=True, witness_liars=1.0, witness_k=4.0, witness_h=20.0)
    x, P, i, j, z, is_liar = _ring(liars)
    rows = np.flatnonzero(j == 0)  # robot 0's broadcast to each observer
    shift = np.array([0.3, 0.0])  # world +x, every observer's heading is 0

    def path(frac):
        lied = shifted_prediction(z[rows], frac[..., None] * shift[None])
        return z[rows][None] - (lied - z[rows][None])

    memory = LinkMemory(len(x))
    receivers = np.arange(1, len(x))
    S0 = np.linspace(12.0, 20.0, len(receivers))  # each receiver's statistic on robot 0
    memory.stage_statistic(STATE).set(receivers, np.zeros(len(receivers), int), S0)
    ok = np.ones(len(i), bool)
    a = within_witness(
        np.ones(len(rows)), path, rows, z, x[i], P[i], x[j], P[j], i, j, ok, is_liar, params,
        memory, budget="common",
    )  # fmt: skip
    assert 0.0 < a.min() and np.ptp(a) == 0.0  # one common factor, a lie is sent
    now = delivered_store(params, memory, i, j, ok, np.array([0]))

    def S_after(frac):
        zz = z.copy()
        zz[rows] = path(frac[None])[0]
        notes = lying_notes(
            step_notes(zz, x[i], P[i], x[j], P[j], i, j, params, ok), is_liar, params
        )
        recv, _, S = received_state(notes, params, now, i, j, ok, np.array([0]))
        return S[~is_liar[recv]].max()  # the honest receivers' largest

    assert S_after(a) == pytest.approx(params.witness_h, rel=0.02)
    assert S_after(1.05 * a) > params.witness_h


def test_lying_notes_exonerate_a_fellow_liar_and_accuse_the_honest():
    params = CLParams(witness=True, witness_liars=1.0)
    x, P, i, j, z, is_liar = _ring((0, 1))
    rows = j == 0
    z = z.copy()  # robot 0 lies: 5 cm along world +x to every observer
    z[rows] -= shifted_prediction(z[rows], np.array([[0.05, 0.0]])) - z[rows]
    notes = step_notes(z, x[i], P[i], x[j], P[j], i, j, params, np.ones(len(i), bool))
    lied = lying_notes(notes, is_liar, params)
    T = witness_statistic(notes, params)[1]
    T_lied = witness_statistic(lied, params)[1]
    assert T[0] > 10.0 and T_lied[0] < 0.9 * T[0]  # robot 1 note lowers robot 0 statistic
    accusing = (i == 0) & (j > 1)  # robot 0's notes on the honest robots
    assert accusing.sum() == 6 and (lied.u[accusing, 0] > notes.u[accusing, 0] + 1e-3).all()
    assert np.array_equal(lied.u[i > 1], notes.u[i > 1])  # honest notes unchanged


@pytest.mark.parametrize("shield", [False, True])
def test_a_liar_sends_its_notes_on_links_jammed_to_it(shield):
    params = CLParams(witness=True, witness_liars=1.0)
    x, P, i, j, z, is_liar = _ring((0, 1))
    received = np.ones(len(i), bool)
    received[(i == 0) & (j == 5)] = False  # robot 5's estimate jammed to the liar 0
    received[(i == 0) & (j == 1)] = False  # and its fellow liar's
    received[(i == 3) & (j == 5)] = False  # and to the honest robot 3
    notes = step_notes(z, x[i], P[i], x[j], P[j], i, j, params, received)
    assert not notes.sent[(i == 0) & (j == 5)].any()  # the defence's rule for the honest
    hook = shielding_notes if shield else lying_notes
    lied = hook(notes, is_liar, params)
    assert lied.sent[i == 0].all()  # the liar is not bound by what reached it
    assert not lied.sent[(i == 3) & (j == 5)].any()  # an honest observer is
    assert np.array_equal(lied.sent[i > 1], notes.sent[i > 1])
    if not shield:  # it accuses there too (a shield's note is the victim's best candidate)
        accusing = (i == 0) & (j == 5)
        assert lied.u[accusing, 0] > notes.u[accusing, 0] + 1e-3


def test_bytes_of_the_notes_are_counted():
    import msgpack

    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario
    from resloc.experiments.traffic import WIRE_BYTES, communication
    from resloc.runtime.messages import HEADER, TAG_SIZE

    for n in (1, 3, 4, 15, 31, 32, 40, 818):  # the runtime's note: id i8 and 10 f8
        body = {"wj": np.arange(n).tobytes(), "wn": np.zeros((n, 10)).tobytes()}
        frame = HEADER.size + len(msgpack.packb(body, use_bin_type=True)) + TAG_SIZE
        over = WIRE_BYTES["witness_frame"] + n * WIRE_BYTES["witness_note"] - frame
        assert over == (0 if n >= 32 else 1 if n >= 4 else 2)
    # and the notes' share of the runtime's estimate frame is at most what is counted
    from resloc.runtime.messages import Codec
    from resloc.runtime.schema import Kind

    codec = Codec(b"k" * 32, 3)
    estimate = {"x": np.zeros(3), "P": np.eye(3)}
    plain = len(codec.encode(Kind.ESTIMATE, 1, estimate, "resloc/radio"))
    for n in (1, 16, 40):
        notes = {"wj": np.arange(n), "wn": np.zeros((n, 10))}
        carried = len(codec.encode(Kind.ESTIMATE, 1, estimate | notes, "resloc/radio"))
        assert (
            n * WIRE_BYTES["witness_note"]
            < carried - plain
            < WIRE_BYTES["witness_frame"] + n * WIRE_BYTES["witness_note"]
        )
    sc = default_scenario().replace(
        **{"team.robots": 6, "run.steps": 15, "run.filters": ["ekf"],
           "run.dead_reckoning": False, "detector.witness": True}
    )  # fmt: skip
    est = run_scenario(sc).estimators["ekf"]
    t, log = est.totals, est.links
    frames = sum(len(np.unique(log["i"][log["step"] == k])) for k in np.unique(log["step"]))
    assert int(t["witness_notes"][0]) == len(log["i"]) == int(t["candidates"][0]) > 0
    assert int(t["witness_frames"][0]) == frames > 0
    comm = communication(t)
    w = WIRE_BYTES
    assert comm["witness"][1][0] == frames * w["witness_frame"] + len(log["i"]) * w["witness_note"]
    plain = run_scenario(sc.replace(**{"detector.witness": False})).estimators["ekf"].totals
    assert plain["witness_frames"].sum() == plain["witness_notes"].sum() == 0


@pytest.mark.parametrize(
    ("key", "value"),
    [("witness_k", 0), ("witness_h", -1.0), ("witness_liars", -1), ("witness_false_alarm", 0.9)],
)
def test_bad_witness_values_are_one_line_errors(key, value):
    from resloc.experiments.config import default_scenario

    with pytest.raises(ConfigError) as err:
        default_scenario().replace(**{f"detector.{key}": value})
    assert f"detector.{key}" in str(err.value) and "\n" not in str(err.value)


def test_the_runtime_refuses_the_witness_only_with_pulled_estimates_in_one_line():
    """The notes ride on broadcast estimates (tests/test_runtime_witness.py): pulled ones
    (``cached``) carry none."""
    from resloc.experiments.config import default_scenario
    from resloc.runtime.team import check_supported

    sc = default_scenario().replace(**{"run.trials": 1, "detector.witness": True})
    check_supported(sc)
    with pytest.raises(ConfigError, match=r"detector\.witness") as err:
        check_supported(sc.replace(**{"estimator.neighbour_estimate": "cached"}))
    assert "\n" not in str(err.value)


def test_the_compiled_path_takes_the_stage():
    from resloc.cl.backend import _params_refusal

    assert WitnessCheck.compiled and _params_refusal(CLParams(witness=True)) is None


def test_the_compromised_robot_in_a_run_keeps_under_the_witness_test(monkeypatch):
    """The simulator's attacker (the per-victim oracle, then the witness budget): the
    liar's statistic after every step is at most h, and the budget is used (it reaches h)."""
    import resloc.cl.step as step_module
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import defence_overrides
    from resloc.experiments.runner import run_scenario
    from resloc.world.attackers import make_attacker

    seen = []

    def record(notes, params, memory):
        record_witness(notes, params, memory)
        stat = memory.stage_statistic(STATE)
        r, j = stat.keys // stat.n_nodes, stat.keys % stat.n_nodes
        seen.append(float(stat.values[(j == 5) & (r != 5)].max(initial=0.0)))

    monkeypatch.setattr(step_module, "record_witness", record)  # (either path)
    monkeypatch.setattr("resloc.cl.kernels_witness.record_witness", record)
    adv = make_attacker("compromised", robots=1, claimed_cov=0.01)
    sc = default_scenario().replace(
        **defence_overrides("zone+full+redundancy+sequence+cap+landmarks+witness"),
        **{"run.steps": 12, "run.filters": ["ckf"], "run.dead_reckoning": False},
    )
    run_scenario(sc.replace(**adv.overrides), adversary=adv)
    h = sc.cl_params().witness_h
    assert len(seen) == 12 and max(seen) <= h * (1 + 1e-9)
    assert max(seen) >= 0.98 * h


def test_the_liar_receives_its_victims_honest_readings_of_it(monkeypatch):
    """The lie travels in the liar's broadcast; each victim's reading of the liar, which the
    liar receives (zone trust fuses it inside the map), stays physical, range and bearing."""
    import resloc.cl.step as step_module
    from resloc.cl.backend import use_backend
    from resloc.cl.detection_zone import reciprocal_rows
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import defence_overrides
    from resloc.experiments.runner import run_scenario
    from resloc.world.attackers import make_attacker

    original = step_module.materialize_with_reciprocal
    checked = []

    def materialize(links, z_hat, S):
        honest = np.array(links.z, float)
        reported = links.tamper.reported
        out = original(links, z_hat, S)
        received = reported(out.z_reciprocal)
        reverse = reciprocal_rows(links.i, links.j)
        from_liar = (links.j % 17 == 5) & (reverse >= 0)
        lied = np.abs(out.z[from_liar] - honest[from_liar]).max()
        assert np.array_equal(received[reverse[from_liar]], honest[from_liar])
        checked.append(lied)
        return out

    monkeypatch.setattr(step_module, "materialize_with_reciprocal", materialize)
    adv = make_attacker("compromised", robots=1)
    sc = default_scenario().replace(
        **defence_overrides("zone+full+redundancy+sequence+cap+landmarks"),
        **{"run.steps": 5, "run.filters": ["ckf"], "run.dead_reckoning": False},
    )
    with use_backend("numpy"):  # (the compiled path applies the same hook in its kernels)
        run_scenario(sc.replace(**adv.overrides), adversary=adv)
    assert len(checked) == 5 and max(checked) > 1e-3  # the victims' rows did carry lies


def _ring_budget(budget, liars=(0,), f=1.0, give_up=0, inside=None, convicting=0):
    """Robot 0's lies to its observers on the ring, scaled by ``budget``; also the honest
    receivers' statistics on it after those lies (a function of the fractions sent)."""
    params = CLParams(witness=True, witness_liars=f, witness_k=4.0, witness_h=20.0)
    if inside is not None:  # a zone-trust map around the observers ``inside``
        x0, *_ = _ring(liars)
        params = dataclasses.replace(
            params, zone_trust=True, zone_trust_map=tuple((*x0[o, :2], 0.2) for o in inside)
        )
    x, P, i, j, z, is_liar = _ring(liars)
    rows = np.flatnonzero(j == 0)
    shift = np.array([0.3, 0.0])

    def path(frac):
        lied = shifted_prediction(z[rows], frac[..., None] * shift[None])
        return z[rows][None] - (lied - z[rows][None])

    memory = LinkMemory(len(x))
    receivers = np.arange(1, len(x))
    S0 = np.linspace(12.0, 20.0, len(receivers))
    S0[:convicting] = 40.0  # receivers that convict the liar whatever it sends
    memory.stage_statistic(STATE).set(receivers, np.zeros(len(receivers), int), S0)
    ok = np.ones(len(i), bool)
    a = within_witness(
        np.ones(len(rows)), path, rows, z, x[i], P[i], x[j], P[j], i, j, ok, is_liar, params,
        memory, budget=budget, give_up=give_up,
    )  # fmt: skip
    now = delivered_store(params, memory, i, j, ok, np.array([0]))

    def S_after(frac):
        zz = z.copy()
        zz[rows] = path(frac[None])[0]
        notes = lying_notes(
            step_notes(zz, x[i], P[i], x[j], P[j], i, j, params, ok), is_liar, params
        )
        recv, _, S = received_state(notes, params, now, i, j, ok, np.array([0]))
        return np.sort(S[~is_liar[recv]])[::-1]  # the honest receivers', largest first

    return a, S_after, params, i[rows]


@pytest.mark.parametrize("liars", [(0,), (0, 1)])
def test_the_spared_budget_lies_more_than_one_common_factor(liars):
    """The default budget fills the links the drop-any-f rule can discard (the f victims
    whose notes weigh most, a fellow liar's links) and still keeps every honest receiver
    under h: more lie in total than one common factor, the f victims at their whole lie."""
    a, S_after, params, observer = _ring_budget("spared", liars, f=2.0)
    common, *_ = _ring_budget("common", liars, f=2.0)
    assert S_after(a)[0] <= params.witness_h * (1 + 1e-9)
    assert a.sum() > 1.5 * common.sum()
    honest = ~np.isin(observer, liars)
    assert (a[honest] == 1.0).sum() >= 2  # f honest victims lied to in full
    assert (a[~honest] == 1.0).all()  # the fellow's lie costs nothing: its note exonerates


def test_a_victim_inside_the_map_keeps_its_whole_lie():
    """Nobody reads the notes of an observer inside the zone-trust map: the lie to it is
    not scaled (the common factor scales it with the others)."""
    a, S_after, params, observer = _ring_budget("spared", f=1.0, inside=(3, 5))
    common, *_ = _ring_budget("common", f=1.0, inside=(3, 5))
    inside = np.isin(observer, (3, 5))
    assert (a[inside] == 1.0).all() and (common[inside] < 1.0).all()
    assert S_after(a)[0] <= params.witness_h * (1 + 1e-9)


def test_giving_up_a_receiver_buys_a_larger_lie():
    """With ``give_up = 1`` one honest receiver (the one starting highest) may exceed h: the
    next one sits at h, and the lie is larger than when every receiver is kept."""
    kept, _, params, _ = _ring_budget("common", f=1.0)
    a, S_after, _, _ = _ring_budget("common", f=1.0, give_up=1)
    assert a.sum() > kept.sum()
    S = S_after(a)
    assert S[0] > params.witness_h and S[1] == pytest.approx(params.witness_h, rel=0.02)
    # A receiver that already convicts it counts: no second one is given up.
    again, S_again, *_ = _ring_budget("common", f=1.0, give_up=1, convicting=1)
    S = S_again(again)
    assert S[0] > params.witness_h and S[1] <= params.witness_h * (1 + 1e-9)
    assert S[1] == pytest.approx(params.witness_h, rel=0.02)


def test_an_unknown_witness_budget_is_a_one_line_error():
    from resloc.world.attackers import make_attacker

    with pytest.raises(ValueError, match="budget") as err:
        make_attacker("compromised", budget="lavish")
    assert "\n" not in str(err.value)
