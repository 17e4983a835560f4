"""The neighbour-fusion methods as strategies: one declared protocol, one registry.

The CL step (:mod:`resloc.cl.step`), the simulator's runner, the robot node
(:mod:`resloc.cl.node`) and the scenario layer look a method up with
:func:`fusion_strategy` and call it; none of them tests the method's name. Adding a method is
its mathematics and its strategy class in one module and one entry in
:data:`FUSION_STRATEGIES`: its name is then a valid :class:`~resloc.cl.fusion.FusionMethod`,
``CLParams.fusion`` and ``estimator.fusion`` value.

A strategy is stateless; what a method remembers between steps lives in the
:class:`~resloc.cl.memory.LinkMemory` of the robots it serves (``memory.joint``: the
bookkeeping object of ``tracked`` / ``factorized`` / ``gauge``; ``memory.independent``: the
independent parts of ``split_ci``), set up by :meth:`FusionStrategy.init`.

One step of an estimator, in the order the callers run it::

    init (once)      -> predict (after the filter's prediction)
    -> link_fields (extra LinkBatch fields) -> moments -> update (per round of links)
    -> finish (end of the correction) -> exchange (consensus on the step's radio links)
    reported(x, P): the covariance the method stands behind (NEES, a node's ``covariance``)
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np

from resloc.cl.factorized import FactorizedCovariance
from resloc.cl.fusion import FusionMethod, fused_update, propagate_independent
from resloc.cl.gauge import GaugeCovariance
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, NeighbourEstimate, UpdateMode
from resloc.cl.tracking import JointCovariance
from resloc.filters.base import GaussianFilter, Moments
from resloc.filters.update import kalman_update
from resloc.models.motion import process_noise

__all__ = ["FUSION_STRATEGIES", "FusionStrategy", "fusion_strategy"]


class FusionStrategy(Protocol):
    """How robot i fuses neighbour j's transmitted estimate, and what it keeps for that.

    The method bodies here are the paper's ``naive`` fusion (estimates independent); a
    strategy overrides what its method changes.

    Attributes
    ----------
    method : str
        The method's name (its key in :data:`FUSION_STRATEGIES`).
    compiled : bool
        The compiled CL kernel (:mod:`resloc.cl.kernels`) implements the method.
    kernel_update, kernel_bookkeeping : str
        How the kernel runs it (read only when ``compiled``).
    node_refusal : str or None
        None when a :class:`~resloc.cl.node.RobotNode` (one robot's process) runs the
        method; otherwise why it does not.
    node_exchanges : tuple of str
        The messages a robot node exchanges after its correction besides estimates
        (``"acks"`` and ``"consensus"`` for gauge fusion, ``"delivery_acks"`` for split CI,
        ``"factors"`` for factorized fusion): what a transport must carry for the method.
    """

    method: ClassVar[str]
    compiled: ClassVar[bool] = False
    #: In the compiled kernel: the link update (``"kalman"``, the filter's; ``"ci"`` and
    #: ``"split_ci"``, :mod:`resloc.cl.kernels_fusion` (their updates:
    #: :mod:`resloc.cl.kernels_ci_update`, :mod:`resloc.cl.kernels_split`); ``"tracked"``
    #: and ``"factorized"``, the correlated joint's moments and records of
    #: :mod:`resloc.cl.kernels_joint`) and the
    #: per-link bookkeeping (``"none"``; ``"gauge"``, :mod:`resloc.cl.kernels_gauge`).
    kernel_update: ClassVar[str] = "kalman"
    kernel_bookkeeping: ClassVar[str] = "none"
    node_refusal: ClassVar[str | None] = None
    node_exchanges: ClassVar[tuple[str, ...]] = ()

    def problem(self, options: Any) -> str | None:
        """Why the method cannot run with ``options`` (anything with ``update_mode``,
        ``neighbour_estimate`` and ``update_without_transmission``: a
        :class:`~resloc.cl.params.CLParams` or the scenario's estimator section), naming the
        option and the fix; None when it can."""
        return None

    def init(
        self,
        memory: LinkMemory,
        x0: np.ndarray,
        P0: np.ndarray,
        team_size: int | None = None,
        *,
        local: bool = False,
        rounds: int | None = None,
    ) -> None:
        """Set up the method's state in ``memory`` for robots ``x0: (B, 3)``,
        ``P0: (B, 3, 3)`` (teams of ``team_size``; ``local``: one robot's process;
        ``rounds``: consensus exchanges per step, None for exact team sums)."""

    def predict(
        self,
        memory: LinkMemory,
        x: np.ndarray,
        u: np.ndarray,
        dt: float,
        params: CLParams,
        P_pred: np.ndarray,
    ) -> np.ndarray:
        """Time update of the method's state from the estimates ``x: (B, 3)`` *before* the
        prediction and odometry ``u: (B, 2)``; returns the covariances ``(B, 3, 3)`` the
        filters continue with (``P_pred``, the filters' own, unless the method is their
        authority)."""
        return P_pred

    def link_fields(self, memory: LinkMemory, j: np.ndarray) -> dict[str, np.ndarray]:
        """Extra :class:`~resloc.cl.links.LinkBatch` fields a transmission of the robots
        ``j: (E,)`` carries."""
        return {}

    def moments(
        self,
        filt: GaussianFilter,
        memory: LinkMemory | None,
        x_i: np.ndarray,
        P_i: np.ndarray,
        x_j: np.ndarray,
        P_j: np.ndarray,
        i: np.ndarray,
        j: np.ndarray,
        R: np.ndarray,
    ) -> Moments:
        """Moments of ``z_ij`` (eq. 3) of observers ``i`` at ``x_i: (E, 3)``, ``P_i``,
        from neighbours ``j`` at ``x_j``, ``P_j`` (the filter's own rule)."""
        return filt.relative_moments(x_i, P_i, x_j, P_j, R)

    def update(
        self,
        memory: LinkMemory | None,
        x_i: np.ndarray,
        P_i: np.ndarray,
        i: np.ndarray,
        j: np.ndarray,
        x_j: np.ndarray,
        P_j: np.ndarray,
        P_j_ind: np.ndarray | None,
        nu: np.ndarray,
        m: Moments,
        params: CLParams,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Update of distinct observers ``i: (E,)`` from innovations ``nu: (E, 2)`` and the
        moments ``m`` of :meth:`moments`; returns ``x: (E, 3)``, ``P: (E, 3, 3)``."""
        return kalman_update(x_i, P_i, nu, m)

    def finish(
        self, memory: LinkMemory | None, P: np.ndarray, j: np.ndarray, delivered: np.ndarray
    ) -> np.ndarray:
        """End of the correction (links' neighbours ``j: (E,)``, which were ``delivered``);
        returns the corrected covariances ``(B, 3, 3)``."""
        return P

    def exchange(self, memory: LinkMemory, i: np.ndarray, j: np.ndarray) -> None:
        """After the correction: consensus exchanges on this step's radio links ``(i, j)``."""

    def reported(self, memory: LinkMemory | None, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The covariance the method stands behind for estimates ``x: (B, 3)`` whose filters
        hold ``P: (B, 3, 3)``."""
        return P


class NaiveFusion(FusionStrategy):
    """``naive`` (the paper): neighbours' estimates independent of the observer's."""

    method: ClassVar[FusionMethod] = FusionMethod.NAIVE
    compiled: ClassVar[bool] = True


class _TransmittedOnly(FusionStrategy):
    """A consistent method: fuses a transmitted estimate, one link after the other."""

    def problem(self, options: Any) -> str | None:
        if options.update_mode is not UpdateMode.SEQUENTIAL:
            return f'needs update_mode = "sequential" (now {options.update_mode.value!r})'
        if options.update_without_transmission:
            return "fuses transmitted estimates only; set update_without_transmission = false"
        return None


class CIFusion(_TransmittedOnly):
    """``ci``: covariance intersection of the joint (:func:`~resloc.cl.fusion.fused_update`)."""

    method: ClassVar[FusionMethod] = FusionMethod.CI
    compiled: ClassVar[bool] = True
    kernel_update: ClassVar[str] = "ci"

    def update(self, memory, x_i, P_i, i, j, x_j, P_j, P_j_ind, nu, m, params):
        criterion = params.ci_criterion
        return fused_update(x_i, P_i, x_j, P_j, nu, m, params.R, self.method, criterion)[:2]


_STEP_KERNELS: list = []


def _step_kernels():
    """The modules of the once-per-step compiled twins, split CI's, ``tracked``'s and
    ``factorized``'s (:mod:`resloc.cl.kernels_fusion_step`) and split CI's end of step's
    (:mod:`resloc.cl.kernels_split`), imported on first use (the kernels import this
    module's registry) and kept: an import statement in ``predict`` and ``finish`` cost
    ~0.5-1 us a step each (measured, ``timeit``). The modules, not their functions: a test
    may replace one."""
    if not _STEP_KERNELS:
        from resloc.cl import kernels_fusion_step, kernels_split

        _STEP_KERNELS[:] = [kernels_fusion_step, kernels_split]
    return _STEP_KERNELS


class SplitCIFusion(_TransmittedOnly):
    """``split_ci``: split covariance intersection; independent parts in
    ``memory.independent`` and in every transmission (``LinkBatch.P_nb_ind``)."""

    method: ClassVar[FusionMethod] = FusionMethod.SPLIT_CI
    compiled: ClassVar[bool] = True
    kernel_update: ClassVar[str] = "split_ci"
    node_exchanges: ClassVar[tuple[str, ...]] = ("delivery_acks",)

    def init(self, memory, x0, P0, team_size=None, *, local=False, rounds=None) -> None:
        memory.independent = np.array(P0, dtype=float)  # initial errors are independent
        memory.local = local

    def predict(self, memory, x, u, dt, params, P_pred) -> np.ndarray:
        # The compiled twin when the backend allows it (see _step_kernels).
        propagated = _step_kernels()[0].compiled_independent_predict(
            x, memory.independent, u, dt, params
        )
        if propagated is None:
            noise = np.asarray(params.odometry_std), np.asarray(params.process_floor_std)
            propagated = propagate_independent(x, memory.independent, u, dt, *noise)
        memory.independent = propagated
        return P_pred

    def link_fields(self, memory, j) -> dict[str, np.ndarray]:
        # (take: the rows of memory.independent[j], a quarter of the fancy index's time)
        return {"P_nb_ind": np.asarray(memory.independent).take(j, axis=0)}

    def update(self, memory, x_i, P_i, i, j, x_j, P_j, P_j_ind, nu, m, params):
        if memory is None or memory.independent is None or P_j_ind is None:
            raise ValueError(
                "split_ci needs memory.independent (fusion_strategy('split_ci').init) and the "
                "transmitted independent parts (LinkBatch.P_nb_ind; RobotNode.correct's P_nb_ind)"
            )
        x_new, P_new, memory.independent[i], _ = fused_update(
            x_i, P_i, x_j, P_j, nu, m, params.R, self.method, params.ci_criterion,
            memory.independent[i], P_j_ind,
        )  # fmt: skip
        return x_new, P_new

    def finish(self, memory, P, j, delivered) -> np.ndarray:
        # A delivered estimate is now held by a neighbour too, so its sender's independent
        # part becomes dependent (a robot's process learns it from an acknowledgement).
        if memory.local:
            return P
        if (
            not _step_kernels()[1].compiled_independent_finish(memory.independent, j, delivered)
            and delivered.any()
        ):
            memory.independent[j[delivered]] = 0.0
        return P


class _Bookkept(_TransmittedOnly):
    """A method that records every update in ``memory.joint`` (tracked, factorized, gauge)."""

    def problem(self, options: Any) -> str | None:
        transmitted = super().problem(options)
        if transmitted is not None:
            return transmitted
        if options.neighbour_estimate is not NeighbourEstimate.CURRENT:
            return (
                f'needs neighbour_estimate = "current" (now {options.neighbour_estimate.value!r})'
            )
        return None

    def _joint(self, memory: LinkMemory | None):
        if memory is None or memory.joint is None:
            raise ValueError(
                f"fusion {str(self.method)!r} needs its bookkeeping in memory.joint "
                "(fusion_strategy(method).init(memory, x0, P0, team_size))"
            )
        return memory.joint

    def predict(self, memory, x, u, dt, params, P_pred) -> np.ndarray:
        compiled = self._compiled_predict(self._joint(memory), x, u, dt, params, P_pred)
        if compiled is not None:
            return compiled
        Q = process_noise(
            x, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std)
        )
        return self._joint(memory).predict(x, u, dt, Q, P_pred)

    def _compiled_predict(self, joint, x, u, dt, params, P_pred) -> np.ndarray | None:
        """The bookkeeping's compiled prediction, None where there is none."""
        return None

    def update(self, memory, x_i, P_i, i, j, x_j, P_j, P_j_ind, nu, m, params):
        x_new, P_new = kalman_update(x_i, P_i, nu, m)
        return x_new, self._joint(memory).update(i, j, x_i, x_j, m, params.R, P_new)

    def finish(self, memory, P, j, delivered) -> np.ndarray:
        return self._joint(memory).finish(P)


def _warm_up_joint_form() -> None:
    """The link loop's form of the correlated joints loaded (or compiled) now, while a run
    sets up, not in its first timed step (:func:`resloc.cl.kernels_joint.warm_up_joint_form`;
    imported here: the kernels import this module's registry; numba is optional)."""
    try:
        from resloc.cl.kernels_joint import warm_up_joint_form
    except ImportError:  # pragma: no cover - numba is optional
        return
    warm_up_joint_form()


def _team_size(method: str, team_size: int | None) -> int:
    if team_size is None:
        raise ValueError(f"fusion {str(method)!r} needs team_size (the team's number of robots)")
    return int(team_size)


class TrackedFusion(_Bookkept):
    """``tracked``: the team's joint covariance, kept exactly (:mod:`resloc.cl.tracking`)."""

    method: ClassVar[FusionMethod] = FusionMethod.TRACKED
    compiled: ClassVar[bool] = True
    kernel_update: ClassVar[str] = "tracked"
    node_refusal: ClassVar[str | None] = (
        "it keeps the team's joint covariance, which no single robot has "
        "(its distributed form is fusion 'factorized')"
    )

    def init(self, memory, x0, P0, team_size=None, *, local=False, rounds=None) -> None:
        memory.joint = JointCovariance(P0, _team_size(self.method, team_size))
        _warm_up_joint_form()

    def moments(self, filt, memory, x_i, P_i, x_j, P_j, i, j, R) -> Moments:
        return self._joint(memory).moments(filt, x_i, P_i, x_j, P_j, i, j, R)

    # The compiled twins of the once-per-step parts (resloc.cl.kernels_fusion_step) when the
    # backend and the bookkeeping allow them; the module imported on first use (the kernels
    # import this module's registry) and kept, as split CI's (_step_kernels: an import
    # statement cost ~0.5 us a call).
    def _compiled_predict(self, joint, x, u, dt, params, P_pred) -> np.ndarray | None:
        return _step_kernels()[0].compiled_tracked_predict(joint, x, u, dt, params)

    def finish(self, memory, P, j, delivered) -> np.ndarray:
        joint = self._joint(memory)
        compiled = _step_kernels()[0].compiled_tracked_finish(joint)
        return joint.finish(P) if compiled is None else compiled


class FactorizedFusion(TrackedFusion):
    """``factorized``: cross-covariances by factors each robot keeps
    (:mod:`resloc.cl.factorized`)."""

    method: ClassVar[FusionMethod] = FusionMethod.FACTORIZED
    compiled: ClassVar[bool] = True
    kernel_update: ClassVar[str] = "factorized"
    node_refusal: ClassVar[str | None] = None
    node_exchanges: ClassVar[tuple[str, ...]] = ("factors",)

    def init(self, memory, x0, P0, team_size=None, *, local=False, rounds=None) -> None:
        team = _team_size(self.method, team_size)
        memory.joint = FactorizedCovariance(len(P0), team, local=local)
        if not local:  # (a robot's process keeps its factors in numpy)
            _warm_up_joint_form()

    def _compiled_predict(self, joint, x, u, dt, params, P_pred) -> np.ndarray | None:
        return _step_kernels()[0].compiled_factorized_predict(joint, x, u, dt, P_pred)

    def finish(self, memory, P, j, delivered) -> np.ndarray:
        joint = self._joint(memory)
        return P if _step_kernels()[0].compiled_factorized_finish(joint) else joint.finish(P)


class GaugeFusion(_Bookkept):
    """``gauge``: the paper's estimates plus the team's common rigid-body error
    (:mod:`resloc.cl.gauge`)."""

    method: ClassVar[FusionMethod] = FusionMethod.GAUGE
    compiled: ClassVar[bool] = True
    kernel_bookkeeping: ClassVar[str] = "gauge"
    node_exchanges: ClassVar[tuple[str, ...]] = ("acks", "consensus")

    def init(self, memory, x0, P0, team_size=None, *, local=False, rounds=None) -> None:
        memory.joint = GaugeCovariance(
            x0, P0, _team_size(self.method, team_size), rounds, local=local
        )

    def predict(self, memory, x, u, dt, params, P_pred) -> np.ndarray:
        # The compiled twin (resloc.cl.kernels_gauge_step) when the backend and the bookkeeping
        # allow it; imported here: the kernels import this module's registry.
        from resloc.cl.kernels_gauge_step import compiled_gauge_predict

        joint = self._joint(memory)
        if compiled_gauge_predict(joint, x, dt, params, P_pred):
            return P_pred
        Q = process_noise(
            x, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std)
        )
        return joint.predict(x, u, dt, Q, P_pred)

    def finish(self, memory, P, j, delivered) -> np.ndarray:
        from resloc.cl.kernels_gauge_step import compiled_gauge_finish

        joint = self._joint(memory)
        if compiled_gauge_finish(joint):
            return P
        return joint.finish(P)

    def exchange(self, memory, i, j) -> None:
        self._joint(memory).exchange(i, j)

    def reported(self, memory, x, P) -> np.ndarray:
        from resloc.cl.kernels_gauge_step import compiled_gauge_reported

        joint = self._joint(memory)
        compiled = compiled_gauge_reported(joint, x, P)
        return joint.reported(x, P) if compiled is None else compiled


#: Every fusion method's strategy, by name.
FUSION_STRATEGIES: dict[str, FusionStrategy] = {
    str(s.method): s
    for s in (
        NaiveFusion(),
        CIFusion(),
        SplitCIFusion(),
        TrackedFusion(),
        FactorizedFusion(),
        GaugeFusion(),
    )
}


def fusion_strategy(method: FusionMethod | str) -> FusionStrategy:
    """The strategy of fusion ``method`` (``ValueError`` naming the registered methods when
    there is none)."""
    if isinstance(method, str):  # a registered name (a FusionMethod is its string): no
        strategy = FUSION_STRATEGIES.get(method)  # FusionMethod(...), 1 us a call per step
        if strategy is not None:
            return strategy
    return FUSION_STRATEGIES[FusionMethod(method).value]
