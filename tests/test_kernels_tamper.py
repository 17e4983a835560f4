"""The stealthy attacker computed inside the compiled CL kernel (its ``kernel_form``,
:mod:`resloc.cl.kernels_tamper`) against the reference path calling its Python hook, over
multi-step runs and every detector it keeps under."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, correct, kernels, predict
from resloc.cl.backend import kernel_refusal
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from resloc.world.adversary import StealthKnowledge, stealthy_tamper
from test_engine import assert_equivalent

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {"ckf": make_filter("ckf"), "ekf": make_filter("ekf")}
CASES = {
    "euclidean-gate": (dict(rho=0.5), StealthKnowledge.FULL, (1.0, 0.0)),
    "scaled-gate": (dict(detector_norm="scaled", rho=3.0), StealthKnowledge.FULL, (1.0, 1.0)),
    "nis-cusums-full": (
        dict(detector_norm="nis", rho=3.03, cusum=True, mean_cusum=True),
        StealthKnowledge.FULL,
        (1.0, 0.0),
    ),
    "nis-cusums-gate-only": (
        dict(detector_norm="nis", rho=3.03, cusum=True, mean_cusum=True),
        StealthKnowledge.GATE,
        (0.6, -0.8),
    ),
    "no-detector": (dict(detector=False), StealthKnowledge.FULL, (1.0, 0.0)),
}


def attacker(ws, params, direction, knowledge, attacked):
    """The runner's stealthy attacker of one step (``_Hooks.link_extras``) on the links
    ``attacked`` (drawn here: the scenario's zone is reached only late)."""
    return stealthy_tamper(
        ws.z, attacked, ws.i, np.asarray(direction), 0.9, np.array([0.3, 0.6]),
        params.detector, params.detector_norm, params.rho, params.noise_std,
        params.cusum_k if params.cusum else None, knowledge,
        params.mean_cusum_k if params.mean_cusum else None,
    )  # fmt: skip


def run_attacked(filt, params, direction, knowledge, steps: int, seed: int) -> int:
    sc = default_scenario().replace(**{"attack.kind": "stealthy", "attack.bias": [0.3, 0.6]})
    world = default_world(1, seed, scenario=sc)
    state = start_states(world, ("numba", "numpy"))
    rng = np.random.default_rng(seed)
    moved = 0
    for _ in range(steps):
        ws = world.step()
        hit = rng.random(len(ws.i)) < 0.4
        res = {}
        for backend, (x, P, memory) in state.items():
            with kernels.use_backend(backend):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s,
                    ws.risk_c, ws.lambda2, tamper=attacker(ws, params, direction, knowledge, hit),
                )  # fmt: skip
                assert (kernel_refusal(filt, params, links, memory) is None) == (backend == "numba")
                res[backend] = correct(filt, xp, Pp, links, params, memory)
            state[backend] = (res[backend][0], res[backend][1], memory)
        assert_equivalent(res["numba"], res["numpy"])
        moved += int((res["numpy"][2].norm[hit] > 0).sum())
    return moved


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("name", list(FILTERS))
def test_compiled_stealthy_attacker_matches_the_hook(name: str, case: str) -> None:
    changes, knowledge, direction = CASES[case]
    params = replace(default_scenario().cl_params(), **changes)
    seed = 3 + list(CASES).index(case)
    assert run_attacked(FILTERS[name], params, direction, knowledge, 30, seed) > 0


def test_the_attacker_changes_what_the_victim_receives() -> None:
    """The compiled attacker injects (the equivalence above is not between two no-ops)."""
    sc = default_scenario().replace(**{"attack.kind": "stealthy", "attack.bias": [0.3, 0.6]})
    world = default_world(1, 5, scenario=sc)
    params = sc.cl_params()
    x, P = world.initial_estimates()
    filt = FILTERS["ckf"]
    changed = 0
    for _ in range(10):
        ws = world.step()
        x, P = predict(filt, x, P, ws.u_meas, world.dt, params)
        base = LinkBatch(
            ws.i, ws.j, ws.z, x[ws.j], P[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
        )
        hit = np.ones(len(ws.i), bool)
        tamper = attacker(ws, params, (1.0, 0.0), StealthKnowledge.FULL, hit)
        with kernels.use_backend("numba"):
            honest = correct(filt, x, P, base, params)
            attacked = correct(filt, x, P, replace(base, tamper=tamper), params)
        assert honest[2].compiled and attacked[2].compiled
        changed += int((np.abs(honest[2].norm - attacked[2].norm) > 1e-9).sum())
        x, P = attacked[:2]
    assert changed > 0


def test_a_hook_without_compiled_form_keeps_the_reference_path() -> None:
    sc = default_scenario()
    world = default_world(1, 1, scenario=sc)
    ws = world.step()
    x, P = world.initial_estimates()
    links = LinkBatch(
        ws.i, ws.j, ws.z, x[ws.j], P[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2,
        tamper=lambda rows, z_hat, S: ws.z[rows],
    )  # fmt: skip
    with kernels.use_backend("numba"):
        assert "kernel_form" in kernel_refusal(FILTERS["ckf"], sc.cl_params(), links)
        assert not correct(FILTERS["ckf"], x, P, links, sc.cl_params())[2].compiled
