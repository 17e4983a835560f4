"""What a fusion method with a compiled twin records beside the link loop's update: its
working arrays, the commit of its records after the loop and their undo when it fails, by
the name its strategy declares (:attr:`FusionStrategy.kernel_bookkeeping
<resloc.cl.fusion_methods.FusionStrategy.kernel_bookkeeping>`), for
:func:`resloc.cl.kernels.fast_correct`."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from resloc.cl.kernels_gauge import gauge_commit, gauge_state, gauge_undo, no_gauge

__all__ = ["COMPILED_BOOKKEEPING", "CompiledBookkeeping"]


class CompiledBookkeeping(NamedTuple):
    """What a fusion method with a compiled twin records beside the kernel's update.

    Attributes
    ----------
    state : callable ``(memory, E) -> KernelGauge or None``
        (:class:`~resloc.cl.kernels_gauge.KernelGauge`)
        The kernel's working arrays for ``E`` links (None: the kernel cannot run it).
    commit : callable ``(memory, state, i, j, fused) -> None``
        Hands the kernel's records to the method's state in ``memory``.
    undo : callable ``(memory, state) -> None``
        The kernel failed: puts back what it changed in place in ``memory``.
    """

    state: Callable
    commit: Callable
    undo: Callable


def _nothing_to_commit(memory, state, i, j, fused) -> None:
    del memory, state, i, j, fused


def _nothing_to_undo(memory, state) -> None:
    del memory, state


def _gauge_commit(memory, state, i, j, fused) -> None:
    gauge_commit(memory.joint, state, i, j, fused)


def _gauge_undo(memory, state) -> None:
    gauge_undo(memory.joint, state)


#: The per-link bookkeeping of a fusion method in the compiled path, by the name its strategy
#: declares (:attr:`FusionStrategy.kernel_bookkeeping
#: <resloc.cl.fusion_methods.FusionStrategy.kernel_bookkeeping>`).
COMPILED_BOOKKEEPING: dict[str, CompiledBookkeeping] = {
    "none": CompiledBookkeeping(
        lambda memory, E: no_gauge(E), _nothing_to_commit, _nothing_to_undo
    ),
    "gauge": CompiledBookkeeping(
        lambda memory, E: None if memory is None else gauge_state(memory.joint, E),
        _gauge_commit,
        _gauge_undo,
    ),
}
