"""``evaluate_claims`` on synthetic results: every verdict (holds, does not hold, not
reproduced, inconclusive), the unit check, and notes that appear only when their test passes.
No simulation runs here: the results are built from known per-seed numbers."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.experiments.reproduce import claims as claims_module
from resloc.experiments.reproduce.claims import evaluate_claims
from resloc.experiments.reproduce.evidence import (
    EQUIVALENCE_MARGIN,
    PaperValue,
    Samples,
    UnitMismatchError,
    compare_with_paper,
    directional,
)
from resloc.experiments.stats import Verdict

SEEDS = 10
RADII = (0.2, 0.3, 0.4, 0.5)
RHOS = (0.2, 0.3, 0.5, 0.75, 1.0, 1.5)
ALPHAS = (0.0, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0)
TEAMS = (5, 9, 12, 17, 25, 33, 40)
FILTERS = ("ckf", "ukf", "ekf")


@dataclass
class FakeEstimator:
    metrics: dict[str, np.ndarray]
    scores: dict[str, float] = field(default_factory=dict)

    def per_trial(self, metric: str) -> np.ndarray:
        return self.metrics[metric]

    def summary(self) -> dict[str, float]:
        return self.scores


@dataclass
class FakeRun:
    estimators: dict[str, FakeEstimator]


@dataclass
class FakeSweep:
    values: tuple
    runs: list[FakeRun]

    @property
    def spec(self):
        return SimpleNamespace(values=self.values)

    def per_trial(self, name: str, metric: str) -> np.ndarray:
        return np.stack([r.estimators[name].per_trial(metric) for r in self.runs])


@dataclass
class FakeReproduction:
    results: dict
    quick: bool = False
    seeds: int = SEEDS
    steps: int = 1000

    def run(self, key: str) -> FakeRun:
        return self.results[key]

    def sweep(self, key: str) -> FakeSweep:
        return self.results[key]


def _seed_effect(rng, spread: float = 0.05) -> np.ndarray:
    """The seed-to-seed variation all filters share (common random numbers)."""
    return 1.0 + spread * rng.standard_normal(SEEDS)


def _noisy(rng, values: np.ndarray, rel: float = 0.002) -> np.ndarray:
    return values * (1.0 + rel * rng.standard_normal(values.shape))


def _filters(rng, base: np.ndarray, factors: dict[str, float], rel: float = 0.002) -> FakeRun:
    return FakeRun(
        {f: FakeEstimator({"msle_mean": _noisy(rng, base * factors[f], rel)}) for f in factors}
    )


def paper_world(seed: int = 0, **change) -> FakeReproduction:
    """Synthetic results in which every claim of the paper holds; ``change`` replaces one
    part (a function of the generator returning that experiment's result)."""
    rng = np.random.default_rng(seed)
    shared = _seed_effect(rng)
    better = {"ckf": 0.9, "ukf": 1.0, "ekf": 1.0}
    res = {
        "fig4a": _filters(rng, 2e-5 * shared, better),
        "fig4b": _filters(rng, 2e-4 * shared, better),
        "fig4c": _filters(rng, 4e-4 * shared, better),
    }
    rate_rise = np.array([0.3, 0.5, 0.7, 0.9])
    ablation_rise = np.array([0.3, 0.35, 0.4, 0.45])
    res["fig5a"] = FakeSweep(
        RADII,
        [
            FakeRun(
                {
                    "ckf": FakeEstimator(
                        {
                            "msle_mean": _noisy(rng, 1e-4 * (1 + 5 * r) * shared),
                            "comm_rate": _noisy(rng, np.full(SEEDS, q)),
                        }
                    )
                }
            )
            for r, q in zip(RADII, rate_rise, strict=True)
        ],
    )
    res["fig5a_zeta0"] = FakeSweep(
        RADII,
        [
            FakeRun({"ckf": FakeEstimator({"comm_rate": _noisy(rng, np.full(SEEDS, q))})})
            for q in ablation_rise
        ],
    )
    res["fig5b"] = FakeSweep(
        RHOS,
        [
            FakeRun(
                {
                    "ckf": FakeEstimator(
                        {"msle_mean": _noisy(rng, 1e-4 * (1 + rho) * shared)},
                        {"detector_false_alarm": 0.0, "detector_recall": 1.0 / (1 + rho)},
                    )
                }
            )
            for rho in RHOS
        ],
    )
    rates = [1.0 - 0.8 * a for a in ALPHAS]
    res["fig5c"] = FakeSweep(
        ALPHAS,
        [
            FakeRun(
                {
                    "ckf": FakeEstimator(
                        {
                            # The paper: MSLE improves slightly as the rate falls.
                            "msle_mean": _noisy(rng, 1e-4 * (1 + 0.1 * q) * shared),
                            "comm_rate": _noisy(rng, np.full(SEEDS, q)),
                        }
                    )
                }
            )
            for q in rates
        ],
    )
    res["fig5d"] = FakeSweep(TEAMS, [_filters(rng, 0.05 * 12 / n * shared, better) for n in TEAMS])
    for key, make in change.items():
        res[key] = make(rng, shared)
    return FakeReproduction(res)


def by_short(claims) -> dict[str, claims_module.Claim]:
    return {c.short: c for c in claims}


def test_every_claim_holds_where_the_data_say_so():
    claims = evaluate_claims(paper_world())
    assert len(claims) == 13
    assert {c.verdict for c in claims} == {Verdict.HOLDS}, [
        (c.short, c.verdict.value) for c in claims if c.verdict is not Verdict.HOLDS
    ]
    # Every measured number carries an interval; MSLE numbers carry their unit.
    assert all("±" in c.measured for c in claims)
    assert "m^2" in by_short(claims)["CKF lowest MSLE, no adversary"].measured


def _fig4a(factors: dict[str, float], rel: float = 0.002):
    return {"fig4a": lambda rng, shared: _filters(rng, 2e-5 * shared, factors, rel)}


def test_equal_filters_are_not_reproduced_not_inconclusive():
    # The review's case: CKF = UKF = EKF to 0.07%, tight intervals.
    rep = paper_world(**_fig4a({"ckf": 1.0007, "ukf": 1.0, "ekf": 0.9997}, rel=0.0005))
    claim = by_short(evaluate_claims(rep))["CKF lowest MSLE, no adversary"]
    assert claim.verdict is Verdict.NOT_REPRODUCED
    assert "equivalent within" in claim.note and "absent" in claim.note
    margin = claim.data["ckf_minus_ukf"]["equivalence"]["smallest_symmetric_margin"]
    assert margin < 0.01 * claim.data["ckf_minus_ukf"]["reference"]


def test_filter_verdicts_follow_the_data():
    cases = {
        Verdict.DOES_NOT_HOLD: ({"ckf": 1.1, "ukf": 1.0, "ekf": 1.0}, 0.002),
        # Seed-to-seed noise of 30% per filter: a 10% advantage cannot be decided.
        Verdict.INCONCLUSIVE: ({"ckf": 0.95, "ukf": 1.0, "ekf": 1.0}, 0.3),
        # Better than one filter, equal to the other: the claimed "lowest" is absent.
        Verdict.NOT_REPRODUCED: ({"ckf": 0.9, "ukf": 1.0, "ekf": 0.9}, 0.002),
    }
    for expected, (factors, rel) in cases.items():
        claim = by_short(evaluate_claims(paper_world(**_fig4a(factors, rel))))
        assert claim["CKF lowest MSLE, no adversary"].verdict is expected, expected
        assert "equivalent within ±" not in claim["CKF lowest MSLE, no adversary"].note or (
            expected is Verdict.NOT_REPRODUCED
        )


def test_n25_bound_is_compared_in_metres():
    def team(msle_at_25: float):
        def make(rng, shared):
            return FakeSweep(
                TEAMS,
                [
                    _filters(rng, msle_at_25 * 25 / n * shared, {"ckf": 0.9, "ukf": 1, "ekf": 1})
                    for n in TEAMS
                ],
            )

        return {"fig5d": make}

    def verdict(msle_at_25):
        return by_short(evaluate_claims(paper_world(**team(msle_at_25))))[
            "CKF MSLE < 0.25 at N = 25"
        ]

    # 0.04 m^2 -> root 0.18 m: below 0.25 m in both readings.
    assert verdict(0.04 / 0.9).verdict is Verdict.HOLDS
    # 0.16 m^2 -> root 0.4 m: above 0.25 m, below 0.25 "m^2": the readings disagree.
    c = verdict(0.16 / 0.9)
    assert c.verdict is Verdict.INCONCLUSIVE and c.data["verdict_m"] == "does not hold"
    assert c.data["verdict_m2"] == "holds" and "disagree" in c.note
    assert verdict(0.36 / 0.9).verdict is Verdict.DOES_NOT_HOLD


def test_a_unit_mismatch_is_an_error(monkeypatch):
    with pytest.raises(UnitMismatchError, match="m\\^2 compared with one in m"):
        compare_with_paper(Samples(np.full(5, 0.01), "m^2"), PaperValue(0.25, "m", "x"), "below")
    assert (
        compare_with_paper(
            Samples(np.full(5, 0.01), "m^2").sqrt(), PaperValue(0.25, "m", "x"), "below"
        )
        is Verdict.HOLDS
    )
    with pytest.raises(UnitMismatchError):
        Samples(np.ones(3), "m").sqrt()
    # A paper value declared in the wrong unit stops the evaluation.
    wrong = {r: PaperValue(v.value, "m", v.source) for r, v in claims_module.PAPER_RATES.items()}
    monkeypatch.setattr(claims_module, "PAPER_RATES", wrong)
    with pytest.raises(UnitMismatchError):
        evaluate_claims(paper_world())


def _ablation(rise):
    def make(rng, shared):
        return FakeSweep(
            RADII,
            [
                FakeRun({"ckf": FakeEstimator({"comm_rate": _noisy(rng, np.full(SEEDS, q))})})
                for q in rise
            ],
        )

    return {"fig5a_zeta0": make}


def test_zeta0_ablation_decides_the_mechanism():
    mech = "rate rise is the risk term's doing"
    # Without the risk term the rate rises by 0.15 of the 0.6: the mechanism adds 75%.
    c = by_short(evaluate_claims(paper_world()))[mech]
    assert c.verdict is Verdict.HOLDS
    assert c.data["share"]["mean"] == pytest.approx(0.75, abs=0.02)
    assert "most of the rise comes from the paper's mechanism" in c.note
    # Half of the rise remains: the mechanism contributes, but not most of it (the review).
    c = by_short(evaluate_claims(paper_world(**_ablation([0.3, 0.4, 0.5, 0.6]))))[mech]
    assert c.verdict is Verdict.HOLDS and c.data["share"]["mean"] == pytest.approx(0.5, abs=0.02)
    assert "most of" not in c.note
    # The whole rise remains: not the paper's mechanism.
    rep = paper_world(**_ablation([0.3, 0.5, 0.7, 0.9]))
    c = by_short(evaluate_claims(rep))[mech]
    assert c.verdict is Verdict.NOT_REPRODUCED and "not the paper's mechanism" in c.note
    rise = by_short(evaluate_claims(rep))["comm rate rises with zone radius"]
    assert rise.verdict is Verdict.HOLDS and "100%" in rise.note


def _alpha_sweep(cost_at_rate):
    def make(rng, shared):
        return FakeSweep(
            ALPHAS,
            [
                FakeRun(
                    {
                        "ckf": FakeEstimator(
                            {
                                "msle_mean": _noisy(rng, 1e-4 * cost_at_rate(q) * shared),
                                "comm_rate": _noisy(rng, np.full(SEEDS, q)),
                            }
                        )
                    }
                )
                for q in (1.0 - 0.8 * a for a in ALPHAS)
            ],
        )

    return {"fig5c": make}


def test_costs_little_uses_the_margin_and_reports_every_alpha():
    little = "lower comm rate costs little MSLE"
    improves = "MSLE improves as comm rate falls"
    # Saving messages costs 60% more MSLE at the lowest rate: rises at every step.
    rep = paper_world(**_alpha_sweep(lambda q: 1.0 + 0.6 * (1.0 - q)))
    claims = by_short(evaluate_claims(rep))
    c = claims[little]
    assert c.verdict is Verdict.DOES_NOT_HOLD
    sweep = c.data["alpha_sweep"]
    assert [r["alpha"] for r in sweep] == list(ALPHAS[1:])
    # Costs grow with alpha: the small alphas hold, the default (0.6: +29%) does not.
    assert sweep[0]["verdict"] == "holds" and sweep[-1]["verdict"] == "does not hold"
    assert c.data["ratio"]["mean"] == pytest.approx(1 + 0.6 * 0.48, abs=0.01)
    assert "It holds at alpha = 0.1" in c.note
    assert claims[improves].verdict is Verdict.DOES_NOT_HOLD
    assert "rises at every step" not in claims[improves].note  # MSLE falls with the rate
    assert "falls at every step" in claims[improves].note
    # No cost, no gain: "costs little" holds and "improves" is not reproduced.
    claims = by_short(evaluate_claims(paper_world(**_alpha_sweep(lambda q: 1.0))))
    assert claims[little].verdict is Verdict.HOLDS
    assert claims[improves].verdict is Verdict.NOT_REPRODUCED
    assert "Not monotone" in claims[improves].note
    # A cost lost in 40% noise per seed: neither side.
    noisy = {
        "fig5c": lambda rng, shared: FakeSweep(
            ALPHAS,
            [
                FakeRun(
                    {
                        "ckf": FakeEstimator(
                            {
                                "msle_mean": 1e-4 * (1 + 0.4 * np.abs(rng.standard_normal(SEEDS))),
                                "comm_rate": np.full(SEEDS, 1.0 - 0.8 * a),
                            }
                        )
                    }
                )
                for a in ALPHAS
            ],
        )
    }
    assert by_short(evaluate_claims(paper_world(**noisy)))[little].verdict is (Verdict.INCONCLUSIVE)


def _rho_sweep(shape, scores=lambda rho: {}):
    def make(rng, shared):
        return FakeSweep(
            RHOS,
            [
                FakeRun(
                    {
                        "ckf": FakeEstimator(
                            {"msle_mean": _noisy(rng, 1e-4 * shape(rho) * shared)}, scores(rho)
                        )
                    }
                )
                for rho in RHOS
            ],
        )

    return {"fig5b": make}


def test_rho_notes_only_when_their_tests_pass():
    claim = "MSLE grows with rho"
    # Monotone rise: the note says so, no interior minimum, no plateau.
    c = by_short(evaluate_claims(paper_world()))[claim]
    assert "rises at every step of the rho grid" in c.note
    assert "interior rho" not in c.note and "equivalent (TOST" not in c.note
    # A clear interior minimum at rho = 0.5, then a plateau from 1.0.
    shape = {0.2: 3.0, 0.3: 2.0, 0.5: 1.0, 0.75: 1.5, 1.0: 2.5, 1.5: 2.5}
    c = by_short(evaluate_claims(paper_world(**_rho_sweep(shape.get))))[claim]
    assert "lowest at an interior rho = 0.5" in c.note and c.data["interior_minimum"]
    assert "From rho = 1 on, MSLE is equivalent" in c.note
    assert "Not monotone" in c.note and c.verdict is Verdict.HOLDS
    # A flat curve: the trend is not reproduced, and no minimum is claimed.
    c = by_short(evaluate_claims(paper_world(**_rho_sweep(lambda rho: 1.0))))[claim]
    assert c.verdict is Verdict.NOT_REPRODUCED
    assert "interior minimum is not shown" in c.note


def test_quick_runs_are_flagged():
    rep = paper_world()
    rep.quick = True
    assert all("Quick run" in c.note for c in evaluate_claims(rep))


def test_directional_margin_is_relative_to_the_reference():
    effect = np.full(SEEDS, -0.02) + 1e-4 * np.arange(SEEDS)
    assert directional(effect, 1.0, "below").verdict is Verdict.NOT_REPRODUCED
    assert directional(effect, 0.1, "below").verdict is Verdict.HOLDS
    assert directional(-effect, 0.1, "below").verdict is Verdict.DOES_NOT_HOLD
    assert EQUIVALENCE_MARGIN == 0.05
