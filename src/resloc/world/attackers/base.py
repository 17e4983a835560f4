"""What an attacker of the suite is: a declared protocol and the sensing-lie template."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.world.attackers.oracle import fix_context, largest_accepted

__all__ = ["AttackStep", "Attacker", "SensingLie", "Strategy"]


@dataclass
class AttackStep:
    """What the attacker sees of one step of the world (it knows everything).

    Attributes
    ----------
    k : int
        Step (1-based).
    dt : float
    pose : ndarray, shape (B, 3)
        True poses.
    i, j : ndarray of int, shape (E,)
        This step's sensed links (batch indices).
    z : ndarray, shape (E, 2)
        Their honest measurements.
    attacked : ndarray of bool, shape (E,)
        The links the attacker controls this step (:meth:`Attacker.mark`).
    robots : int
        Team size N (robot ``b`` of the batch is robot ``b % N`` of its team).
    """

    k: int
    dt: float
    pose: np.ndarray
    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    attacked: np.ndarray
    robots: int


class Attacker(Protocol):
    """One strategy of the adversary suite, with its parameters set.

    Attributes
    ----------
    name : str
        The strategy (family) name.
    summary : str
        One line: what it does and what it knows, with these parameters.
    params : dict of str to float
        Its parameters (the values of one point of :attr:`grid`).
    grid : tuple of dict
        The parameter values the study searches per defence (the worst is reported).
    overrides : dict of str to object
        Dotted scenario overrides the strategy needs (e.g. ``attack.kind``).
    """

    name: str
    summary: str
    params: dict
    grid: tuple
    overrides: dict

    def mark(self, sdz_attacked: np.ndarray, step: AttackStep) -> np.ndarray:
        """The links it falsifies this step, shape (E,) (ground truth of the detector
        scores); ``sdz_attacked``: the links the world's sensing danger zones expose."""

    def attack(
        self, links: LinkBatch, step: AttackStep, params: CLParams, memory: LinkMemory | None
    ) -> LinkBatch:
        """The link batch the victim estimator (``params``, ``memory``) receives."""


class Strategy:
    """Parameters of a strategy: defaults, the searched grid, a label.

    A subclass declares ``defaults`` (every parameter and its default value) and ``grid``
    (the parameter points the study tries against every defence; each point overrides
    some defaults). ``template`` (the one-line summary) may name parameters as ``{name}``.
    """

    name: ClassVar[str] = ""
    template: ClassVar[str] = ""
    overrides: ClassVar[dict] = {"attack.kind": "stealthy"}
    defaults: ClassVar[dict] = {}
    grid: ClassVar[tuple] = ({},)

    def __init__(self, **params) -> None:
        unknown = set(params) - set(self.defaults)
        if unknown:
            raise ValueError(
                f"attacker {self.name!r}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                f"known: {', '.join(self.defaults) or 'none'}"
            )
        # One spelling per value (2 and 2.0 are the same bias, hence the same stored cell).
        self.params = {}
        for key, value in {**self.defaults, **params}.items():
            try:
                self.params[key] = _like(self.defaults[key], value)
            except ValueError as exc:
                raise ValueError(f"attacker {self.name!r}, parameter {key}: {exc}") from None
        for key, value in self.params.items():
            setattr(self, key, value)

    @property
    def summary(self) -> str:
        return self.template.format(**self.params)

    @property
    def label(self) -> str:
        """``name`` and the parameters its grid searches or that differ from the defaults:
        ``on_off[period=10]``."""
        searched = [
            k
            for k in self.params
            if len({str(p.get(k)) for p in self.grid}) > 1 or self.params[k] != self.defaults[k]
        ]
        inner = ",".join(f"{k}={_spelled(self.params[k])}" for k in searched)
        return f"{self.name}[{inner}]" if inner else self.name

    def owned(self, robots: int) -> np.ndarray:
        """The ids (``0 .. robots - 1``) of the robots this attacker runs in a team of
        ``robots``: their software, hence their own estimates, are its (none: an attacker
        of the sensing or the channel). A study reports the MSLE over the other robots
        beside the paper's (:mod:`resloc.experiments.attack`)."""
        return np.zeros(0, dtype=int)

    @classmethod
    def variants(cls) -> list[Strategy]:
        """One instance per point of :attr:`grid` (the study's search)."""
        return [cls(**point) for point in cls.grid]


def _spelled(value) -> str:
    """A parameter's value in a label: numbers as ``:g`` (2 and 2.0 alike), names as is."""
    return value if isinstance(value, str) else f"{value:g}"


def _like(default, value):
    """``value`` as the type of ``default`` (int or float); a non-integral value for an
    integer parameter is a ``ValueError``."""
    if isinstance(default, bool) or not isinstance(default, int | float):
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {value!r}")
    if isinstance(default, int):
        if float(value) != int(value):
            raise ValueError(f"expected an integer, got {value!r}")
        return int(value)
    return float(value)


class SensingLie(Strategy):
    """Template of a measurement attacker: a full lie per link, scaled by the victim's
    acceptance.

    Per controlled link the strategy states the injection it wants (:meth:`lie`, shape
    (n, 2)) and at most which fraction of it to send this step (:meth:`ceiling`); the
    victim's own detector, with its current sequence-test state, decides the largest
    fraction it accepts (:func:`~resloc.world.attackers.oracle.largest_accepted`), and
    that is sent.
    """

    #: Knows only the per-measurement gate (the outside reviewer's attacker).
    gate_only: ClassVar[bool] = False

    def mark(self, sdz_attacked: np.ndarray, step: AttackStep) -> np.ndarray:
        return sdz_attacked

    def lie(self, rows: np.ndarray, z: np.ndarray, z_hat: np.ndarray, step: AttackStep):
        """The full injection on ``rows``, shape (len(rows), 2)."""
        raise NotImplementedError

    def ceiling(self, step: AttackStep) -> float:
        """Largest fraction of the lie to send this step (schedules), in [0, 1]."""
        return 1.0

    def attack(self, links, step, params, memory):
        ceiling = float(self.ceiling(step))

        def tamper(rows: np.ndarray, z_hat: np.ndarray, S: np.ndarray) -> np.ndarray:
            out = links.z[rows].copy()
            hit = np.flatnonzero(step.attacked[rows])
            if not hit.size or ceiling <= 0.0:
                return out
            r = rows[hit]
            lie = self.lie(r, out[hit], z_hat[hit], step) * ceiling
            a = largest_accepted(
                out[hit],
                lie,
                z_hat[hit],
                S[hit],
                links.i[r],
                links.j[r],
                params,
                memory,
                self.gate_only,
                None if self.gate_only else fix_context(links, r, params, memory=memory),
            )
            z = out[hit] + a[:, None] * lie
            z[:, 0] = np.abs(z[:, 0])
            z[:, 1] = wrap_angle(z[:, 1])
            out[hit] = z
            return out

        return dataclasses.replace(links, tamper=tamper)
