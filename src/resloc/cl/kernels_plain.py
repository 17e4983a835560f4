"""The compiled link loops' input structures in the form they are called with.

numba types a NamedTuple argument in Python, a plain tuple by its fast fingerprint
(measured: the link loop's ten structures cost 16.5 us a call as NamedTuples, 7 us as plain
tuples). The structures keep their NamedTuple classes as their documented layout
(:mod:`resloc.cl.kernels_inputs`, the options' modules); the kernels read their fields by
position, and :func:`resloc.cl.kernels.fast_correct` calls them with the plain forms made
here.
"""

from __future__ import annotations

import weakref

import numpy as np

__all__ = ["contiguous", "plain", "plain_with"]


def contiguous(a, dtype=float) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype`` (itself when it is one)."""
    return np.ascontiguousarray(a, dtype=dtype)


#: Per structure type: the positions of its fields that are structures themselves.
_NESTED: dict[type, tuple[int, ...]] = {}


def plain(structure: tuple) -> tuple:
    """A kernel input structure (a NamedTuple, nested ones too) as plain tuples, the form
    the compiled loop is called with."""
    nested = _NESTED.get(type(structure))
    if nested is None:
        nested = _NESTED[type(structure)] = tuple(
            k for k, v in enumerate(structure) if isinstance(v, tuple)
        )
    if not nested:
        return tuple(structure)
    fields = list(structure)
    for k in nested:
        fields[k] = plain(fields[k])
    return tuple(fields)


#: Per structure type: its fields' positions by name.
_FIELDS: dict[type, dict[str, int]] = {}


#: Per memory: the last structure :func:`plain_with` was given for it, its plain form, the
#: changes' names and values and the result (a run's steady state gives the same detection
#: structure every step, kernels_stores.steady_state, and the same pre-passes' arrays,
#: kernels_prepass; weak: a finished run's arrays go with its memory).
_LAST: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_NOTHING_KEPT = (None, None, (), (), None)


def plain_with(structure: tuple, changes: dict, memory=None) -> tuple:
    """``plain(structure._replace(**changes))`` without the NamedTuple built between
    (``_replace`` costs ~0.7 us and a keyword argument ~0.5 more), from the plain form of
    the last ``structure`` given with ``memory`` when it is the same object (immutable: its
    plain form too), the last result when the changes are the same objects too (nothing is
    kept without a ``memory``)."""
    if not changes:
        return plain(structure)
    kept = None if memory is None else _LAST.get(memory)
    last, plain_form, names, values, result = _NOTHING_KEPT if kept is None else kept
    new_names, new_values = tuple(changes), tuple(changes.values())
    if last is structure and names == new_names:  # (the same names: as many values)
        for a, b in zip(values, new_values, strict=True):  # (all() of a generator: 0.3 us)
            if a is not b:
                break
        else:
            return result
    if last is not structure:
        plain_form = plain(structure)
    index = _FIELDS.get(type(structure))
    if index is None:
        index = _FIELDS[type(structure)] = {name: k for k, name in enumerate(structure._fields)}
    fields = list(plain_form)
    for name, value in changes.items():
        fields[index[name]] = plain(value) if isinstance(value, tuple) else value
    result = tuple(fields)
    if memory is not None:
        _LAST[memory] = (structure, plain_form, new_names, new_values, result)
    return result
