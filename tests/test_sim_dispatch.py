"""The run's per-step dispatch, made cheaper without changing a result: the compiled index
check before the CL kernel, the refusal and preparations kept per filter and parameters,
and the outcome counts from the links' bytes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from resloc.cl.backend import HAVE_NUMBA, kernel_refusal, use_backend
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams, UpdateMode
from resloc.experiments.outcomes import (
    _COUNTS_OF_BYTE,
    COUNTED,
    counted_masks,
    per_group_counts,
)
from resloc.experiments.recording import pack_outcomes
from resloc.filters.base import make_filter

needs_numba = pytest.mark.skipif(not HAVE_NUMBA, reason="the compiled path needs numba")


def _batch(rng, B=12):
    x = rng.normal(size=(B, 3))
    P = np.broadcast_to(0.01 * np.eye(3), (B, 3, 3)).copy()
    i = np.repeat(np.arange(B), 2)
    j = (i + np.tile([1, 2], B)) % B
    z = np.abs(rng.normal(size=(len(i), 2)))
    links = LinkBatch.from_predicted(
        i, j, z, x, P, np.ones(len(i), bool), np.zeros(B), np.zeros(B), np.ones(B)
    )
    return x, P, links


def _robot_fields(links):
    return links.risk_s, links.risk_c, links.lambda2


@needs_numba
def test_observer_bound_is_one_past_the_largest_observer_or_minus_one():
    from resloc.cl.kernels_checks import observer_bound

    i = np.array([0, 0, 3, 5, 5], np.int64)
    j = np.array([1, 2, 0, 1, 3], np.int64)
    none = np.zeros(0, np.int64)
    assert observer_bound(i, j, none, 0) == 6
    assert observer_bound(i, j, np.array([0, 1, 2, 3, 4], np.int64), 5) == 6
    assert observer_bound(i[:0], j[:0], none, 0) == 0
    assert observer_bound(np.array([-1, 0], np.int64), j[:2], none, 0) == -1  # negative
    assert observer_bound(np.array([0, 0], np.int64), np.array([1, 1]), none, 0) == -1  # twice
    assert observer_bound(i, j, np.array([0, 1, 2, 3, 5], np.int64), 5) == -1  # row 5 of 5
    assert observer_bound(i, j, np.array([0, 1, -2, 3, 4], np.int64), 5) == -1


@needs_numba
def test_links_the_kernel_must_not_read_go_to_the_reference():
    from resloc.cl import kernels

    rng = np.random.default_rng(0)
    x, P, links = _batch(rng)
    filt, params = make_filter("ckf"), CLParams()
    with use_backend("numba"):
        assert kernels.fast_correct(filt, x, P, links, params) is not None
        beyond = dataclasses.replace(links, i=links.i + 1)  # the last observer has no state
        assert kernels.fast_correct(filt, x, P, beyond, params) is None
        stray = LinkBatch.from_predicted(
            links.i, links.j + 100, links.z, x, P, links.channel_ok, *_robot_fields(links)
        )  # neighbour rows outside the estimates
        assert kernels.fast_correct(filt, x, P, stray, params) is None
        wrong_dtype = LinkBatch.from_predicted(
            links.i, links.j.astype(float), links.z, x, P, links.channel_ok, *_robot_fields(links)
        )
        assert kernels.fast_correct(filt, x, P, wrong_dtype, params) is None


@needs_numba
def test_the_kept_refusal_follows_the_backend_filter_and_params():
    from resloc.cl import kernels, kernels_prepared
    from resloc.cl.kernels_tamper import no_tamper

    rng = np.random.default_rng(1)
    x, P, links = _batch(rng)
    ckf, ekf = make_filter("ckf"), make_filter("ekf")
    params = CLParams()
    with use_backend("numba"):
        for filt in (ckf, ekf, ckf):  # estimators alternate
            assert kernels_prepared.refusal(filt, params, links) is None
        summed = dataclasses.replace(params, update_mode=UpdateMode.SUMMED, fusion="ci")
        assert kernels_prepared.refusal(ckf, summed, links) == kernel_refusal(ckf, summed, links)
        assert kernels_prepared.refusal(ckf, summed, links) is not None

        class PythonHook:  # an adversary's hook without a compiled form
            kernel_form = None

        hooked = dataclasses.replace(links, tamper=PythonHook())
        assert kernels_prepared.refusal(ckf, params, hooked) is not None
        assert kernels_prepared.refusal(ckf, params, links) is None

        class CompiledHook:
            kernel_form = no_tamper()

        compiled_hook = dataclasses.replace(links, tamper=CompiledHook())
        assert kernels_prepared.refusal(ckf, params, compiled_hook) is None
    with use_backend("numpy"):
        assert kernels_prepared.refusal(ckf, params, links) == "the backend is numpy"
        assert kernels.fast_correct(ckf, x, P, links, params) is None


@pytest.mark.parametrize("groups, links", [(5, 400), (3000, 50)])
def test_byte_counts_equal_the_masks_counts(groups, links):
    """Both of its ways (the table of byte values; the masks when the groups outnumber the
    links) count what the 11 masks count."""
    rng = np.random.default_rng(groups)
    flags = rng.random((6, links)) < 0.4
    packed = pack_outcomes(*flags)
    group = np.sort(rng.integers(0, groups, links))
    want = per_group_counts(counted_masks(*flags), group, groups)
    got = _COUNTS_OF_BYTE.count(packed, group, groups)
    assert got.shape == (len(COUNTED), groups)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)
    direct = np.stack(
        [np.bincount(group, weights=m, minlength=groups) for m in counted_masks(*flags)]
    )
    np.testing.assert_array_equal(got, direct.astype(np.int64))


def test_running_counts_accept_bool_and_integer_masks():
    rng = np.random.default_rng(3)
    masks = rng.random((4, 300)) < 0.5
    group = np.sort(rng.integers(0, 7, 300))
    want = np.stack([np.bincount(group, weights=m, minlength=7) for m in masks]).astype(np.int64)
    np.testing.assert_array_equal(per_group_counts(masks, group, 7), want)
    np.testing.assert_array_equal(per_group_counts(masks.astype(np.int64), group, 7), want)
