"""The on-disk cache of every compiled kernel goes stale when a module of its callees
changes (numba stamps a cached kernel with its own source file only)."""

from __future__ import annotations

import hashlib
import importlib
import pkgutil
from pathlib import Path

import pytest

numba = pytest.importorskip("numba")

import resloc.cl  # noqa: E402
from resloc.cl.kernels_math import _is_dispatcher, callee_modules  # noqa: E402

KERNEL_MODULES = [
    *sorted(m.name for m in pkgutil.iter_modules(resloc.cl.__path__, "resloc.cl.")),
    "resloc.world.kernels",
]


def _kernels():
    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for attr, value in sorted(vars(module).items()):
            if "kernels" in name and _is_dispatcher(value) and value.py_func.__module__ == name:
                yield name, attr, value


def test_every_cached_kernel_is_stamped_with_its_callees_sources() -> None:
    checked = 0
    for name, attr, kernel in _kernels():
        stamp = kernel._cache._cache_file._source_stamp
        callees = set(callee_modules(kernel)) - {importlib.import_module(name)}
        if not callees and not isinstance(stamp, tuple):
            continue  # a kernel of its own module only (numba's own stamp covers it)
        assert isinstance(stamp, tuple) and len(stamp) == 2, (name, attr)
        missing = {m.__name__ for m in callees} - kernel._resloc_pieces
        assert not missing, f"{name}.{attr}: its cache stamp misses {sorted(missing)}"
        digest = hashlib.sha256()
        stamped = [importlib.import_module(m) for m in kernel._resloc_pieces]
        for path in sorted(str(m.__file__) for m in stamped):
            digest.update(Path(path).read_bytes())
        assert stamp[1] == digest.hexdigest(), (name, attr)
        checked += 1
    assert checked > 50  # every kernel module was found


def test_split_ci_update_goes_stale_with_the_ci_pieces_it_inlines() -> None:
    from resloc.cl.kernels_split import split_ci_update

    split_ci_update._cache._cache_file._source_stamp  # noqa: B018 - computes the stamp
    pieces = {"resloc.cl.kernels_ci_weight", "resloc.cl.kernels_ci_update"}
    assert pieces | {"resloc.cl.kernels_joint_links"} <= split_ci_update._resloc_pieces


def test_a_callee_reached_through_its_module_is_found() -> None:
    from resloc.cl import kernels_rounds

    names = {m.__name__ for m in callee_modules(kernels_rounds.correct_rounds)}
    # _rounds reads the stages as module attributes and by name; both are followed
    assert {"resloc.cl.kernels_round_stages", "resloc.cl.kernels_split"} <= names
    assert "resloc.cl.kernels_ci_weight" in names  # through kernels_split (transitively)


def test_the_redundancy_and_witness_kernels_go_stale_with_the_modules_they_were_split_into():
    """The callers of the redundancy stage's fixes and verdicts and of the witness
    statistic and notes (split out of kernels_redundancy and kernels_witness) are stamped
    with the modules those now live in, through every caller that inlines or calls them."""
    from resloc.cl.kernels_claims import claimed_rows
    from resloc.cl.kernels_prepass import prepass_rows
    from resloc.cl.kernels_redundancy_verdicts import fix_verdicts, scaled_fix_verdicts
    from resloc.cl.kernels_witness_frames import delivered_pass
    from resloc.cl.kernels_witness_step import witness_pass

    fixes, verdicts = "resloc.cl.kernels_redundancy_fixes", "resloc.cl.kernels_redundancy_verdicts"
    statistic = "resloc.cl.kernels_witness_statistic"
    expected = {
        fix_verdicts: {fixes},
        scaled_fix_verdicts: {fixes},
        prepass_rows: {fixes, verdicts},
        claimed_rows: {fixes},
        delivered_pass: {statistic},
        witness_pass: {statistic},
    }
    for kernel, modules in expected.items():
        kernel._cache._cache_file._source_stamp  # noqa: B018 - computes the stamp
        assert modules <= kernel._resloc_pieces, kernel.py_func.__name__


def test_the_callers_go_stale_with_the_ci_zone_and_pending_modules_split_out():
    """The callers of covariance intersection's weight and update (split out of
    kernels_fusion), of zone trust's in-loop verdicts (out of kernels_zone) and of the
    pending store's row copy (out of kernels_witness_frames) are stamped with the modules
    those now live in."""
    from resloc.cl.kernels_ci_lanes import ci_lanes
    from resloc.cl.kernels_links import correct_links
    from resloc.cl.kernels_outvoted import outvoted_pass
    from resloc.cl.kernels_rounds import correct_rounds
    from resloc.cl.kernels_summed import correct_summed

    ci = {"resloc.cl.kernels_ci_weight", "resloc.cl.kernels_ci_update"}
    zone = {"resloc.cl.kernels_zone_verdicts"}
    expected = {
        correct_links: ci | zone,
        correct_rounds: ci | zone,
        correct_summed: zone,
        ci_lanes: ci,
        outvoted_pass: {"resloc.cl.kernels_witness_pending"},
    }
    for kernel, modules in expected.items():
        kernel._cache._cache_file._source_stamp  # noqa: B018 - computes the stamp
        assert modules <= kernel._resloc_pieces, kernel.py_func.__name__
