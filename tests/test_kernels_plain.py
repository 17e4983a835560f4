"""The link loops' arguments as plain tuples (:mod:`resloc.cl.kernels_plain`).

* :func:`~resloc.cl.kernels_plain.plain_with` is ``plain(structure._replace(**changes))``,
  field for field the same objects;
* its last result is kept per memory: estimators that alternate each get their own back
  (the same tuple) while their structure and changes are the same objects, and a finished
  memory is not kept."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest

from resloc.cl import LinkMemory, kernels
from resloc.cl.kernels_plain import plain, plain_with
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

if kernels.HAVE_NUMBA:
    from resloc.cl.kernels_detection import detector_state


def _detection(memory: LinkMemory):
    """The kernel's detection structure of the zone, CUSUM and redundancy chain on
    ``memory`` (a structure with nested structures)."""
    sc = default_scenario().replace(**DEFENCES["zone+full+redundancy+sequence"])
    rows = np.arange(4, dtype=np.int64)
    return detector_state(sc.cl_params(), memory, rows, (rows + 1) % 4).kernel


def _same_objects(got: tuple, want: tuple) -> bool:
    return len(got) == len(want) and all(
        a is b or (type(a) is tuple and _same_objects(a, b)) for a, b in zip(got, want, strict=True)
    )


def test_plain_with_is_the_plain_replaced_structure() -> None:
    memory = LinkMemory(4)
    detect = _detection(memory)
    zone = detect.zone._replace(on=True)
    fixes, other = np.ones(4, bool), np.zeros(4, bool)
    for changes in ({}, {"fixes": fixes, "zone": zone}, {"fixes": fixes, "zone": zone},
                    {"fixes": other, "zone": zone}, {"fixes": other}):  # fmt: skip
        for kept in (memory, None):
            got = plain_with(detect, changes, kept)
            assert type(got) is tuple
            assert _same_objects(got, plain(detect._replace(**changes)))


def test_the_last_result_is_kept_per_memory() -> None:
    first, second = LinkMemory(4), LinkMemory(4)
    detect = {m: _detection(m) for m in (first, second)}
    changes = {m: {"fixes": np.ones(4, bool)} for m in (first, second)}
    results = {m: plain_with(detect[m], changes[m], m) for m in (first, second)}
    for _ in range(2):  # the estimators alternate: each gets its own result back
        for m in (first, second):
            assert plain_with(detect[m], dict(changes[m]), m) is results[m]
    other = {"fixes": np.ones(4, bool)}  # equal values, another object: a new result
    fresh = plain_with(detect[first], other, first)
    assert fresh is not results[first]
    assert fresh[detect[first]._fields.index("fixes")] is other["fixes"]
    assert plain_with(detect[first], changes[first], None) is not results[first]


def test_a_finished_memory_is_not_kept() -> None:
    memory = LinkMemory(4)
    plain_with(_detection(memory), {"fixes": np.ones(4, bool)}, memory)
    gone = weakref.ref(memory)
    del memory
    gc.collect()
    assert gone() is None
