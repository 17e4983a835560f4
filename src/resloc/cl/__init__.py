"""Cooperative localization: attack detector, adaptive event trigger, per-robot CL step.

The same functions serve one robot (batch size 1, e.g. a robot process) and a whole
batched simulation (robots x trials flattened on the leading axis).
"""

from resloc.cl.detector import InnovationNorm, attack_detected, innovation_norm
from resloc.cl.fusion import FusionMethod
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.graph import algebraic_connectivity, component_lambda2, laplacian
from resloc.cl.memory import LinkMemory
from resloc.cl.node import RobotNode
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.cl.step import LinkBatch, LinkOutcome, correct, predict
from resloc.cl.trigger import event_threshold, event_triggered

__all__ = [
    "CLParams",
    "FusionMethod",
    "InnovationNorm",
    "LinkBatch",
    "LinkMemory",
    "LinkOutcome",
    "NeighbourEstimate",
    "RobotNode",
    "ThresholdInnovation",
    "UpdateMode",
    "algebraic_connectivity",
    "attack_detected",
    "component_lambda2",
    "correct",
    "event_threshold",
    "event_triggered",
    "fusion_strategy",
    "innovation_norm",
    "laplacian",
    "predict",
]
