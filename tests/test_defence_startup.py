"""The start-up stage: no robot's covariance shrinks below a floor in its first corrections."""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl.detection_startup import StartupFloor, applied_startup_factors, startup_floor
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.errors import ConfigError

PARAMS = CLParams(startup_steps=5, startup_floor_std=0.01)
N = 4


def _links():
    """Robots 0-2 observe (receivers); robot 3 only sends."""
    return SimpleNamespace(i=np.array([0, 0, 1, 2]), j=np.array([1, 2, 0, 3]))


def _P():
    """Robot 0 at 2 mm, robot 1 at 5 mm (x) and 1 mm (y), robot 2 at 30 mm, robot 3 at 1 mm."""
    P = np.tile(np.eye(3) * 1e-4, (N, 1, 1))
    P[0, :2, :2] = np.eye(2) * 0.002**2
    P[1, :2, :2] = np.diag([0.005**2, 0.001**2])
    P[2, :2, :2] = np.eye(2) * 0.03**2
    P[3, :2, :2] = np.eye(2) * 0.001**2
    return P


def test_a_young_robot_is_raised_to_the_floor_then_left_alone():
    memory = LinkMemory(N)
    factors = []
    for _ in range(8):
        P = _P()
        used = startup_floor(PARAMS, memory, _links(), P)
        factors.append(used[:, 0, 0] / P[:, 0, 0])
        if used is not P:
            # the whole 3 x 3 block by one factor (heading too), the larger diagonal at the floor
            assert np.allclose(used[0], P[0] * used[0, 0, 0] / P[0, 0, 0])
            assert max(used[0, 0, 0], used[0, 1, 1]) == pytest.approx(0.01**2)
            assert max(used[1, 0, 0], used[1, 1, 1]) == pytest.approx(0.01**2)
    factors = np.array(factors)
    assert factors[:5, 0] == pytest.approx(25.0)  # (10 mm / 2 mm)^2 for five corrections
    assert factors[:5, 1] == pytest.approx(4.0)  # its larger diagonal: 5 mm
    assert (factors[5:] == 1.0).all()  # the start is over
    assert (factors[:, 2] == 1.0).all()  # wider than the floor: untouched
    assert (factors[:, 3] == 1.0).all()  # not an observer: no correction, untouched


def test_a_decaying_floor_has_no_cliff():
    """With ``startup_decay`` the floor is not dropped after the start but halved (here) at
    each further correction: robot 0 (2 mm) is raised to 10 mm five times, then 5 mm,
    2.5 mm, then the floor (1.25 mm) is below it; the schedule ends below 0.1 mm."""
    from resloc.cl.detection_startup import startup_floor_schedule

    params = replace(PARAMS, startup_decay=0.5)
    memory = LinkMemory(N)
    factors = []
    for _ in range(10):
        P = _P()
        factors.append(startup_floor(params, memory, _links(), P)[0, 0, 0] / P[0, 0, 0])
    assert factors == pytest.approx([25.0] * 5 + [6.25, 1.5625] + [1.0] * 3)
    floors = startup_floor_schedule(params, np.arange(30))
    assert floors[:5] == pytest.approx(0.01) and floors[5:11] == pytest.approx(
        0.01 * 0.5 ** np.arange(1, 7)
    )
    assert (floors[11:] == 0.0).all()  # 0.01 / 2^7 < 0.1 mm: over
    # never shrinks by more than the decay in one correction
    assert (floors[1:11] / floors[:10] >= 0.5 - 1e-12).all()
    # 0: the old cliff
    assert (startup_floor_schedule(PARAMS, np.arange(30))[5:] == 0.0).all()


def test_off_by_default_and_without_memory():
    P = _P()
    assert startup_floor(CLParams(), LinkMemory(N), _links(), P) is P
    assert startup_floor(PARAMS, None, _links(), P) is P
    assert not StartupFloor().active(CLParams()) and StartupFloor().active(PARAMS)


def test_the_attacker_sees_the_raised_covariances():
    from resloc.world.attackers.outvoted import widened

    for params in (PARAMS, replace(PARAMS, witness=True, outvoted=True)):
        memory = LinkMemory(N)
        for k in range(7):
            P = _P()
            used = startup_floor(params, memory, _links(), P)
            assert np.allclose(widened(P, memory, params), used)
            assert (applied_startup_factors(memory, N) > 1.0).any() == (k < 5)
    # the decaying floor too: raised after the five corrections, and the attacker sees it
    params = replace(PARAMS, startup_decay=0.5, witness=True, outvoted=True)
    memory = LinkMemory(N)
    for k in range(8):
        P = _P()
        used = startup_floor(params, memory, _links(), P)
        assert np.allclose(widened(P, memory, params), used)
        assert (applied_startup_factors(memory, N) > 1.0).any() == (k < 7)


def test_the_compiled_path_takes_the_stage():
    from resloc.cl.backend import _params_refusal

    assert StartupFloor.compiled
    assert _params_refusal(PARAMS) is None


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("detector.startup_steps", -1),
        ("detector.startup_floor_std", 0.0),
        ("detector.startup_decay", -0.1),
        ("detector.startup_decay", 1.5),
    ],
)
def test_bad_options_are_one_line_errors(field, value):
    from resloc.experiments.config import default_scenario

    with pytest.raises(ConfigError) as err:
        default_scenario().replace(**{field: value})
    assert field in str(err.value) and "\n" not in str(err.value)
    sc = default_scenario().replace(**{"detector.startup_steps": 20})
    assert sc.detector.startup_steps == 20 and sc.cl_params().startup_steps == 20
    sc = default_scenario().replace(**{"detector.startup_decay": 0.9})
    assert sc.cl_params().startup_decay == 0.9


@dataclass
class _Links:
    j: np.ndarray
    tamper: object = "honest"


def test_the_quiet_attacker_sends_nothing_false_during_its_quiet_steps():
    from resloc.world.attackers import make_attacker

    adv = make_attacker("compromised", robots=3, quiet=10)
    links = _Links(j=np.array([5, 10, 1]))
    step = SimpleNamespace(k=3, robots=17)
    assert adv.attack(links, step, PARAMS, None).tamper is None
    with pytest.raises(AttributeError):  # past its quiet steps it goes on to lie
        adv.attack(links, SimpleNamespace(k=10, robots=17), PARAMS, None)
    assert make_attacker("compromised").quiet == 0


def test_the_correction_uses_the_floor_on_both_paths():
    """Robot 0 (1 mm) fuses five neighbours: with the stage its prior is raised to 10 mm
    before the correction, on the compiled path as on the reference (to 1e-9)."""
    import dataclasses

    import resloc.cl.step
    from resloc.cl import kernels
    from resloc.filters.base import make_filter
    from test_defence_redundancy import POSE, _compromised_scene

    base = CLParams(trigger=False, detector=False)
    links, *_ = _compromised_scene(base)
    links = dataclasses.replace(links, neighbours=None)
    P = np.tile(np.diag([1e-6, 1e-6, 1e-4]), (6, 1, 1))
    filt = make_filter("ckf")
    on = replace(base, startup_steps=3, startup_floor_std=0.01)
    runs = {}
    backends = ("numpy", "numba") if kernels.HAVE_NUMBA else ("numpy",)
    for backend in backends:
        for name, params in (("off", base), ("on", on)):
            with kernels.use_backend(backend):
                runs[backend, name] = resloc.cl.step.correct(
                    filt, POSE.copy(), P, links, params, LinkMemory(6)
                )
    # the floored prior: the posterior of robot 0 is wider than without the stage
    assert runs["numpy", "on"][1][0, 0, 0] > 5.0 * runs["numpy", "off"][1][0, 0, 0]
    if kernels.HAVE_NUMBA:
        assert runs["numba", "on"][2].compiled
        for k in (0, 1):
            np.testing.assert_allclose(
                runs["numba", "on"][k], runs["numpy", "on"][k], rtol=0, atol=1e-9
            )


def test_the_claims_an_observer_fuses_are_floored_during_its_start():
    """``startup_claims``: each link's claim is raised to its observer's floor of the step
    (robot 0: 10 mm for five corrections, then 5 mm, 2.5 mm with decay 0.5); robot 1's
    claims are raised by its own floor; once the floor is over the claims go as sent."""
    from resloc.cl.detection_startup import claims_floored, floored_claims

    params = replace(PARAMS, startup_decay=0.5, startup_claims=True)
    links = _links()
    claims = np.tile(np.diag([1e-6, 4e-6, 1e-4]), (len(links.i), 1, 1))  # 2 mm (y)
    memory = LinkMemory(N)
    factors = []
    for _ in range(20):
        startup_floor(params, memory, links, _P())
        used = floored_claims(params, memory, links.i, claims)
        factors.append(used[:, 1, 1] / claims[:, 1, 1])
        if used is not claims:
            np.testing.assert_allclose(used[0], claims[0] * factors[-1][0])
    factors = np.array(factors)
    assert factors[:5, 0] == pytest.approx(25.0)  # (10 mm / 2 mm)^2
    assert factors[5:7, 0] == pytest.approx([6.25, 1.5625])
    assert (factors[7:] == 1.0).all()
    np.testing.assert_array_equal(factors[:, 0], factors[:, 2])  # per observer (robot 1)
    assert not claims_floored(replace(params, startup_claims=False), memory)
    assert floored_claims(replace(params, startup_claims=False), memory, links.i, claims) is claims


def test_floored_claims_on_both_paths():
    """Robot 0 (1 mm) fuses five neighbours claiming 1 mm: with ``startup_claims`` their
    claims are raised to its 10 mm floor too; compiled equals reference (1e-9)."""
    import dataclasses

    import resloc.cl.step
    from resloc.cl import kernels
    from resloc.filters.base import make_filter
    from test_defence_redundancy import POSE, _compromised_scene

    base = CLParams(trigger=False, detector=False)
    links, *_ = _compromised_scene(base)
    claims = np.tile(np.diag([1e-6, 1e-6, 1e-4]), (5, 1, 1))
    links = dataclasses.replace(links, P_nb=claims, neighbours=None)
    P = np.tile(np.diag([1e-6, 1e-6, 1e-4]), (6, 1, 1))
    filt = make_filter("ckf")
    floor = replace(base, startup_steps=3, startup_floor_std=0.01)
    runs = {}
    backends = ("numpy", "numba") if kernels.HAVE_NUMBA else ("numpy",)
    for backend in backends:
        for name, params in (("floor", floor), ("claims", replace(floor, startup_claims=True))):
            with kernels.use_backend(backend):
                runs[backend, name] = resloc.cl.step.correct(
                    filt, POSE.copy(), P, links, params, LinkMemory(6)
                )
    # the neighbours' 1 mm claims raised to 10 mm: the posterior is wider
    assert runs["numpy", "claims"][1][0, 0, 0] > 1.5 * runs["numpy", "floor"][1][0, 0, 0]
    if kernels.HAVE_NUMBA:
        assert runs["numba", "claims"][2].compiled
        for k in (0, 1):
            np.testing.assert_allclose(
                runs["numba", "claims"][k], runs["numpy", "claims"][k], rtol=0, atol=1e-9
            )
